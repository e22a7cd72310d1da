"""Finding DIR-Lab case files and reading voxel_spacing.csv (lungdeform.validate.dirlab_files).

The folders are built by the helpers in tests/validate/test_dirlab.py; where a test checks that the files
were read as the right case, it does so through the 300-pair mean of lungdeform.validate.dirlab.
"""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import ReadError
from lungdeform.validate import dirlab as D
from lungdeform.validate import dirlab_files as F
from tests.conftest import require_path
from tests.validate.test_dirlab import (
    ARCHIVE_LAYOUT,
    SPACING,
    make_archive_1_10,
    make_case_folder,
    make_real_variant_layout,
    rewrite_landmark_file,
    spacing_csv_text,
)


def test_find_cases_both_naming_schemes(tmp_path, rng):
    truth, pairs = make_case_folder(tmp_path, rng)
    cases = F.find_cases(tmp_path)
    assert sorted(cases) == [1, 2]
    assert set(cases[2].extreme) == {"T00", "T50"} and set(cases[2].sampled) == set(F.PHASES)
    assert cases[2].extreme["T00"].name == "case2_dirLab300_T00_xyz.txt"
    assert np.allclose(cases[2].spacing, SPACING[2]) and list(cases[1].dims) == [256, 256, 94]
    for case in (1, 2):
        data = D.load_case(cases[case])
        # truth: the mean computed from the generated indices with mm = (index - 1) * spacing
        assert D.mean_displacement(data.pairs["T00"], data.pairs["T50"]) == pytest.approx(pairs[case])
        assert np.allclose(data.phases["T30"], truth[case]["T30"], atol=1e-5)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda r: (r / "voxel_spacing.csv").unlink(), "no voxel_spacing.csv"),
        (lambda r: (r / "Case1Pack/Sampled4D/case1_4D-75_T20.txt").unlink(), "case 1: 75-point files missing phase.*T20"),
        (lambda r: (r / "voxel_spacing.csv").write_text("case,spacing_x_mm,spacing_y_mm,spacing_z_mm\n1,1,1,1\n"),
         "case 2: no row in"),
        (lambda r: (r / "voxel_spacing.csv").write_text("case,spacing_x_mm,spacing_y_mm,spacing_z_mm\n1,1,0,1\n2,1,1,1\n"),
         r"voxel_spacing.csv, line 2: inconsistent spacing"),
        (lambda r: (r / "voxel_spacing.csv").write_text(
            "case,spacing_x_mm,spacing_y_mm,spacing_z_mm\n1,1,1,1\n2,1,1,1\n1,1,1,2.5\n"),
         r"line 4: inconsistent spacing for case 1"),
        (lambda r: (r / "voxel_spacing.csv").write_text("case,foo,bar,baz\n1,1,1,1\n"), "missing column"),
        (lambda r: (r / "Case1Pack/ExtremePhases/case1_300_T00_xyz_copy.txt").write_text(""), None),
    ],
)
def test_discovery_errors(tmp_path, rng, mutate, message):
    make_case_folder(tmp_path, rng)
    mutate(tmp_path)
    if message is None:  # a file that does not match the pattern is ignored
        assert sorted(F.find_cases(tmp_path)) == [1, 2]
        return
    # strict: no fall-back on the published spacing, so a missing table/row is an error too
    with pytest.raises(ReadError, match=message):
        F.find_cases(tmp_path, published_fallback=False)


@pytest.mark.parametrize("style", ["reordered", "semicolon", "tabs"])
def test_voxel_spacing_dialects(tmp_path, style):
    # every dialect must give back the published table exactly (dims only where the file has them)
    p = tmp_path / "voxel_spacing.csv"
    p.write_bytes(spacing_csv_text(style).encode())
    got = F.read_voxel_spacing(p)
    assert sorted(got) == list(range(1, 11))
    for c, (dims, sp) in F.PUBLISHED_GEOMETRY.items():
        assert got[c][0] == pytest.approx(sp)
        if style == "semicolon":
            assert got[c][1] is None
        else:
            assert got[c][1].tolist() == list(dims)
        assert F.geometry_notes(c, *got[c]) == []


def test_voxel_spacing_blank_dims_and_bad_case(tmp_path):
    p = tmp_path / "voxel_spacing.csv"
    p.write_text("case,dim_x,dim_y,dim_z,spacing_x_mm,spacing_y_mm,spacing_z_mm\n6,,,,0.97,0.97,2.5\n")
    assert F.read_voxel_spacing(p)[6][1] is None  # blank size cells: no size check, not a failure
    p.write_text("case,spacing_x_mm,spacing_y_mm,spacing_z_mm\nlung,1,1,1\n")
    with pytest.raises(ReadError, match=r"voxel_spacing.csv, line 2: .*'lung' is not a case number"):
        F.read_voxel_spacing(p)
    p.write_text("")
    with pytest.raises(ReadError, match="voxel_spacing.csv: empty file"):
        F.read_voxel_spacing(p)
    # a wrong spacing is reported against the published table, not replaced
    assert F.geometry_notes(7, [1.16, 1.16, 2.5], [512, 512, 136]) == [
        "case 7: spacing [1.16, 1.16, 2.5] mm differs from the published [0.97, 0.97, 2.5] mm"]


def test_voxel_spacing_other_columns_and_no_header(tmp_path):
    p = tmp_path / "voxel_spacing.csv"
    # a 'name' column beside 'case': the case column wins; dx/dy/dz are spacings
    p.write_text("Name,Case,dx,dy,dz\nPatient A,10,0.97,0.97,2.5\n")
    got = F.read_voxel_spacing(p)
    assert list(got) == [10] and got[10][0].tolist() == [0.97, 0.97, 2.5] and got[10][1] is None
    # no header, 7 columns: the whole-number triple ≥ 16 is the image size, in either order
    p.write_text("6 0.97 0.97 2.5 512 512 128\ncase7 512 512 136 0.97 0.97 2.5\n")
    got = F.read_voxel_spacing(p)
    assert got[6][1].tolist() == [512, 512, 128] and got[7][0].tolist() == [0.97, 0.97, 2.5]
    assert got[7][1].tolist() == [512, 512, 136]
    p.write_text("6 0.97 0.97\n")
    with pytest.raises(ReadError, match=r"voxel_spacing.csv: no header and 3 columns"):
        F.read_voxel_spacing(p)


@pytest.mark.realdata
@pytest.mark.parametrize("csv_style", ["reordered", "semicolon"])
def test_real_cases_in_archive_variant_layouts(data_dir, tmp_path, csv_style):
    real = require_path(data_dir, "dirlab-4dct-landmarks")
    make_real_variant_layout(real, tmp_path, csv_style)
    cases = F.find_cases(tmp_path)
    assert sorted(cases) == [1, 2, 3, 4, 5]
    assert cases[2].extreme["T00"].name == "CASE2_DIRLAB300_T00_XYZ.TXT"
    assert set(cases[4].sampled) == set() and set(cases[5].extreme) == set()
    assert any("no 75-point files" in n for n in cases[4].notes)
    assert any("no 300-pair files" in n for n in cases[5].notes)
    assert any("case5_4D-75_T60.txt" in n and "ignored" in n for n in cases[5].notes)
    for c in (1, 2, 3, 4):
        r = D.evaluate_case(D.load_case(cases[c]), cases[c].dims)
        # whatever the layout, separators and number format: the published 300-pair means
        assert r.mean_displacement_300_mm == pytest.approx(D.PUBLISHED_MEAN_300_MM[c], abs=0.01)
    r5 = D.evaluate_case(D.load_case(cases[5]), cases[5].dims)
    r1 = D.evaluate_case(D.load_case(F.find_cases(real)[1]), None)
    assert r5.mean_displacement_300_mm is None and r5.n_tracked == 75 and r5.one_scalar_mean_mm < r5.no_motion_mean_mm
    # case 3 written as floats reads back the same as the original integers/floats
    orig3 = D.load_case(F.find_cases(real)[3])
    new3 = D.load_case(cases[3])
    for ph in F.PHASES:
        np.testing.assert_allclose(new3.phases[ph], orig3.phases[ph], atol=1e-4)
    assert r1.n_pairs == 300


# --------------------------------------------------------------------------- unseen archives: cases 1–10
@pytest.mark.parametrize(
    "name, expected",
    [
        ("Case1_300_T00_xyz.txt", (1, "extreme", "T00")),
        ("case6_dirLab300_T50_xyz.txt", (6, "extreme", "T50")),
        ("CASE8_DIRLAB300_T00_XYZ.TXT", (8, "extreme", "T00")),
        ("case10_dirLab300_T50_xyz.txt", (10, "extreme", "T50")),  # two digits: case 10, not case 1
        ("Case10_300_T00_xyz.txt", (10, "extreme", "T00")),
        ("case10_4D-75_T40.txt", (10, "sampled", "T40")),
        ("case6_4D-75_T00.txt", (6, "sampled", "T00")),
        ("case7-dirlab300-t50-xyz.txt", (7, "extreme", "T50")),
        ("dirLab300_T00_xyz.txt", (None, "extreme", "T00")),  # case number from the folder
        ("case1_T00_s.img", None),  # DIR-Lab's image files
        ("Case1_300_T00_xyz_copy.txt", None),
        ("notes_T00.txt", None),
        ("my_case1_300_T00_xyz.txt", None),
    ],
)
def test_file_names_of_the_archives(name, expected):
    assert F._classify(name) == expected


def test_archive_layout_cases_1_to_10(tmp_path, rng):
    truth = make_archive_1_10(tmp_path, rng)
    found = F.discover(tmp_path)
    assert sorted(found.cases) == list(range(1, 11)) and found.skipped == {}
    # case 10 keeps its own files; none of them is taken for case 1 (or the other way round)
    assert all("case10" in p.name.lower() for p in [*found.cases[10].extreme.values(), *found.cases[10].sampled.values()])
    assert all("case10" not in str(p).lower() for p in found.cases[1].extreme.values())
    for c in range(1, 11):
        f = found.cases[c]
        # 6–10 are not in voxel_spacing.csv: the published spacing is used, and said so
        assert f.spacing.tolist() == list(F.PUBLISHED_GEOMETRY[c][1])
        assert (f.spacing_source == F.PUBLISHED_SOURCE) == (c > 5)
        if c > 5:
            assert f.notes[0] == (f"case {c}: no row in {tmp_path / 'voxel_spacing.csv'}: used the published DIR-Lab "
                                  f"spacing {list(F.PUBLISHED_GEOMETRY[c][1])} mm and size {list(F.PUBLISHED_GEOMETRY[c][0])}")
        r = D.evaluate_case(D.load_case(f), f.dims)
        # truth: the mean of the generated pairs in mm (tabs, runs of spaces, CRLF, floats alike)
        assert r.mean_displacement_300_mm == pytest.approx(truth[c], abs=1e-9)
        if ARCHIVE_LAYOUT[c][1] is None:  # 300 pairs only: reported, models skipped, said why
            assert r.best_model is None and any("no 75-point files" in n and "models skipped" in n for n in f.notes)
        else:  # the 75 points move with one scalar per phase (up to the 4-decimal rounding of the files)
            assert r.one_scalar_mean_mm < 1e-3 < r.no_motion_mean_mm
    with pytest.raises(ReadError, match=r"case 6: no row in .*voxel_spacing\.csv for its landmark files \(e\.g\. .*case6_"):
        F.discover(tmp_path, published_fallback=False)


def test_data_folder_is_a_case_folder_or_above(tmp_path, rng):
    truth = make_archive_1_10(tmp_path / "dirlab", rng, spacing_rows=range(1, 11))
    # the case folder itself: voxel_spacing.csv is found in the folder above
    for folder in ("Case10Pack", "Case8Deploy", "case9", "Case10Pack/ExtremePhases"):
        found = F.discover(tmp_path / "dirlab" / folder)
        c = int(folder.split("/")[0].lower().removeprefix("case").removesuffix("pack").removesuffix("deploy"))
        assert list(found.cases) == [c] and found.cases[c].spacing_source.endswith("voxel_spacing.csv")
        r = D.evaluate_case(D.load_case(found.cases[c]), found.cases[c].dims)
        assert r.mean_displacement_300_mm == pytest.approx(truth[c])
    # the parent of the data folder, beside other data
    (tmp_path / "other" / "scan.nii.gz").parent.mkdir()
    (tmp_path / "other" / "scan.nii.gz").write_bytes(b"\x1f\x8b")
    assert sorted(F.find_cases(tmp_path)) == list(range(1, 11))
    # a case folder with no table anywhere above: the published spacing, with a note saying so
    lone = tmp_path / "lone" / "x" / "y" / "Case6Pack"
    lone.parent.mkdir(parents=True)
    (tmp_path / "dirlab" / "Case6Pack").rename(lone)
    found = F.discover(lone)
    assert found.cases[6].spacing_source == F.PUBLISHED_SOURCE
    assert "no voxel_spacing.csv found in" in found.cases[6].notes[0]


def test_case_numbers_from_folders_and_duplicates(tmp_path, rng):
    truth = make_archive_1_10(tmp_path, rng)
    ext = tmp_path / "Case7Pack/extremePhases"
    for ph in ("00", "50"):  # a file name without the case number: the folder Case7Pack gives it
        (ext / f"case7_dirLab300_T{ph}_xyz.txt").rename(ext / f"dirLab300_T{ph}_xyz.txt")
    # the same file twice under the two naming schemes (identical numbers): kept once, noted
    (tmp_path / "Case6Pack/ExtremePhases/Case6_300_T00_xyz.txt").write_bytes(
        (tmp_path / "Case6Pack/ExtremePhases/case6_dirLab300_T00_xyz.txt").read_bytes().replace(b"\r\n", b"\n"))
    # archive debris: macOS resource forks and hidden copies are not landmark files
    junk = tmp_path / "__MACOSX/Case1Pack/ExtremePhases/._Case1_300_T00_xyz.txt"
    junk.parent.mkdir(parents=True)
    junk.write_bytes(b"\x00\x05\x16\x07 Mac OS X")
    found = F.discover(tmp_path)
    assert sorted(found.cases) == list(range(1, 11))
    assert D.evaluate_case(D.load_case(found.cases[7])).mean_displacement_300_mm == pytest.approx(truth[7])
    assert any(" repeats " in n and "same numbers" in n and "Case6_300_T00_xyz.txt" in n and
               "case6_dirLab300_T00_xyz.txt" in n for n in found.cases[6].notes)
    # a case file filed under another case's folder is read by its name, and noted
    moved = tmp_path / "Case8Deploy/extremePhases/case9_dirLab300_T00_xyz.txt"
    (tmp_path / "case9/ExtremePhases/case9_dirLab300_T00_xyz.txt").rename(moved)
    assert any("lies in a folder named for case 8" in n for n in F.discover(tmp_path).cases[9].notes)


def test_spacing_table_named_and_shaped_differently(tmp_path, rng):
    truth = make_archive_1_10(tmp_path, rng, spacing_rows=())
    (tmp_path / "voxel_spacing.csv").unlink()
    # DIR-Lab's web-page table, one combined cell per quantity, under another name
    (tmp_path / "VoxelSpacing.txt").write_text(
        "Case\tImage Dims\tVoxel Size (mm)\r\n" + "".join(
            f"Case{c}Pack\t{' x '.join(map(str, g[0]))}\t{' x '.join(map(str, g[1]))}\r\n"
            for c, g in F.PUBLISHED_GEOMETRY.items() if c <= 5))
    # a second table beside case 8, no header: case sx sy sz
    (tmp_path / "Case8Deploy" / "spacing.csv").write_text("8 0.97 0.97 2.5\n")
    (tmp_path / "spacing_notes.txt").write_text("The spacings come from the DIR-Lab web site.\n")
    found = F.discover(tmp_path)
    assert found.cases[3].spacing_source.endswith("VoxelSpacing.txt")
    assert found.cases[3].dims.tolist() == [256, 256, 104]
    assert found.cases[8].spacing_source.endswith("spacing.csv") and found.cases[8].dims is None
    assert found.cases[9].spacing_source == F.PUBLISHED_SOURCE
    assert any("ignored" in n and "spacing_notes.txt" in n for n in found.notes)
    for c in (3, 8, 9):
        r = D.evaluate_case(D.load_case(found.cases[c]), found.cases[c].dims)
        assert r.mean_displacement_300_mm == pytest.approx(truth[c])
    # two tables that disagree about a case: refused, naming both
    (tmp_path / "Case8Deploy" / "spacing.csv").write_text("3 1.0 1.0 2.5\n")
    with pytest.raises(ReadError, match=r"case 3: spacing .* in .*spacing\.csv but .* in .*VoxelSpacing\.txt"):
        F.discover(tmp_path)


def test_cases_that_cannot_be_used_are_skipped_with_the_reason(tmp_path, rng):
    make_archive_1_10(tmp_path, rng)
    ext = tmp_path / "Case7Pack/extremePhases"
    for ph in ("00", "50"):  # not a DIR-Lab case: no published spacing to fall back on
        (ext / f"case7_dirLab300_T{ph}_xyz.txt").rename(tmp_path / f"case11_dirLab300_T{ph}_xyz.txt")
    found = F.discover(tmp_path)
    assert 11 not in found.cases and 7 not in found.cases
    assert found.skipped[11].startswith(f"case 11: skipped: no row in {tmp_path / 'voxel_spacing.csv'}")
    assert "case11_dirLab300_T00_xyz.txt" in found.skipped[11]
    # nothing usable at all: one error naming why (no table inside or up to 3 folders above)
    only = tmp_path / "a" / "b" / "c" / "only11"
    only.mkdir(parents=True)
    for p in tmp_path.glob("case11_*"):
        p.rename(only / p.name)
    with pytest.raises(ReadError, match=r"only11: no usable DIR-Lab case: case 11: skipped: no voxel_spacing.csv"):
        F.discover(only)
    # an archive that was not extracted: say so
    zipped = tmp_path / "zipped"
    zipped.mkdir()
    (zipped / "Case6Pack.zip").write_bytes(b"PK\x05\x06" + bytes(18))
    with pytest.raises(ReadError, match=r"no DIR-Lab landmark files .*extract the archive\(s\) first, e\.g\. .*Case6Pack\.zip"):
        F.discover(zipped)


def test_linked_case_folders_are_followed(tmp_path, rng):
    truth = make_archive_1_10(tmp_path / "store", rng, spacing_rows=range(1, 11))
    view = tmp_path / "view"
    view.mkdir()
    for c in ("Case6Pack", "Case10Pack"):
        (view / c).symlink_to(tmp_path / "store" / c, target_is_directory=True)
    (view / "voxel_spacing.csv").symlink_to(tmp_path / "store" / "voxel_spacing.csv")
    (view / "Case10Pack" / "loop").symlink_to(view, target_is_directory=True)  # a cycle must not hang
    found = F.discover(view)
    assert sorted(found.cases) == [6, 10]
    assert D.evaluate_case(D.load_case(found.cases[10])).mean_displacement_300_mm == pytest.approx(truth[10])


@pytest.mark.realdata
def test_real_cases_relabelled_as_cases_6_to_10(data_dir, tmp_path):
    """Real cases 1–5 copied (in tmp_path only) into the archive names of cases 6–10: case k → k + 5."""
    real = require_path(data_dir, "dirlab-4dct-landmarks")
    rows = []
    for k in range(1, 6):
        c = k + 5
        ext, smp, style = ARCHIVE_LAYOUT[c]
        smp = smp or f"Case{c}Pack/Sampled4D/case{c}_4D-75_T{{ph}}.txt"
        for ph in ("00", "50"):
            rewrite_landmark_file(next((real / f"Case{k}Pack/ExtremePhases").glob(f"*_T{ph}_xyz.txt")),
                     tmp_path / ext.format(ph=ph), "tabs_crlf_blank_tail" if style == "tabs_crlf" else "spaces_lf")
        for ph in ("00", "10", "20", "30", "40", "50"):
            rewrite_landmark_file(real / f"Case{k}Pack/Sampled4D/case{k}_4D-75_T{ph}.txt", tmp_path / smp.format(ph=ph), "floats")
        dims, sp = F.PUBLISHED_GEOMETRY[k]
        rows.append(f"case{c},{','.join(map(str, dims))},{','.join(map(str, sp))}\n")
    # the table gives the source cases' real geometry under the new numbers, except for case 6
    # (real case 1's spacing, 0.97 mm, is also case 6's published one): that row is left out
    (tmp_path / "voxel_spacing.csv").write_text("case,dim_x,dim_y,dim_z,spacing_x_mm,spacing_y_mm,spacing_z_mm\n"
                                                + "".join(rows[1:]))
    found = F.discover(tmp_path)
    assert sorted(found.cases) == [6, 7, 8, 9, 10]
    assert found.cases[6].spacing_source == F.PUBLISHED_SOURCE
    for c, f in found.cases.items():
        r = D.evaluate_case(D.load_case(f), f.dims)
        # Castillo et al. 2009: the published mean of the source case (case 10 ← case 5: 7.48, not 3.89)
        assert r.mean_displacement_300_mm == pytest.approx(D.PUBLISHED_MEAN_300_MM[c - 5], abs=0.01)
        assert r.n_pairs == 300 and r.n_tracked == 75 and r.one_scalar_mean_mm < r.no_motion_mean_mm
        if c > 6:  # the relabelled geometry is reported against the published one, never replaced
            assert any("differs from the published" in n for n in f.notes)
    one = F.discover(tmp_path / "Case10Pack")
    assert list(one.cases) == [10]
    assert D.evaluate_case(D.load_case(one.cases[10])).mean_displacement_300_mm == pytest.approx(7.48, abs=0.01)


@pytest.mark.parametrize("dims", ["inf,256,94", "256,-inf,94", "nan,256,94"])
def test_voxel_spacing_refuses_non_finite_image_size(tmp_path, dims):
    # why: found by tests/fuzz/fuzz_dirlab_spacing.py: int(round(inf)) raises OverflowError (and
    # int(round(nan)) ValueError); both must come out as ReadError naming the file and line
    f = tmp_path / "voxel_spacing.csv"
    f.write_text(f"case,dim_x,dim_y,dim_z,spacing_x_mm,spacing_y_mm,spacing_z_mm\n1,{dims},0.97,0.97,2.5\n")
    with pytest.raises(ReadError, match=r"voxel_spacing\.csv, line 2: not a number"):
        F.read_voxel_spacing(f)
