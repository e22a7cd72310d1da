"""CLI tests of ``lungdeform track``: interior points moved by a model over volumes or a breath."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
import trimesh

from lungdeform.cli.main import main
from lungdeform.io.dicom.rtstruct import read_ct_series, read_rtstruct, write_rtstruct
from lungdeform.io.modelfile import save_model
from lungdeform.playback.trajectory import lung_scales
from tests.browser.support import two_lungs
from tests.io.dicom_support import dciodvfy, patch_element, write_ct_series


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return save_model(tmp_path_factory.mktemp("model") / "m.npz", two_lungs(2))


@pytest.fixture
def points_csv(tmp_path):
    path = tmp_path / "points.csv"
    path.write_text("x_mm,y_mm,z_mm,label\n90,0,-40,tumour\n-90,10,20,clip\n")
    return path


def _rows(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def test_track_at_volumes(model_file, points_csv, tmp_path, capsys):
    # at the end-exhale volume nothing moves; 500 mL more moves each point by its lung's interior
    # field at that lung's exact share of the 500 mL (the same scale as surface playback)
    out = tmp_path / "o"
    v_ee = sum(lung.volume_ee_ml for lung in two_lungs(2).lungs.values())
    assert main(["track", str(model_file), "--points", str(points_csv), "--out", str(out),
                 "--volume-ml", f"{v_ee}", "--volume-ml", f"{v_ee + 500}"]) == 0
    rows = _rows(out / "trajectories.csv")
    assert len(rows) == 4 and rows[0]["label"] == "tumour" and rows[0]["lung"] == "left"
    assert rows[1]["lung"] == "right" and rows[0]["t_s"] == ""
    still = np.array([[float(r[k]) for k in ("dx_mm", "dy_mm", "dz_mm")] for r in rows[:2]])
    moved = np.array([[float(r[k]) for k in ("dx_mm", "dy_mm", "dz_mm")] for r in rows[2:]])
    assert np.abs(still).max() < 1e-3 and np.linalg.norm(moved, axis=1).min() > 1.0
    info = json.loads((out / "points.json").read_text())
    assert info["points"][0]["inside"] and info["landmark_correction"] == {"left": False, "right": False}
    m = two_lungs(2)
    scales = lung_scales(m, [500.0])
    for row, (name, q) in zip(moved, [("left", [90.0, 0, -40]), ("right", [-90.0, 10, 20])]):
        want = scales[name][0] * m.lungs[name].interior.displacement(np.array([q]))[0]
        assert row == pytest.approx(want, abs=1e-3)
    assert info["points"][0]["peak_to_peak_mm"]["SI"] == pytest.approx(abs(moved[0, 2]), abs=1e-3)
    assert (out / "motion.png").read_bytes()[:4] == b"\x89PNG"
    printed = capsys.readouterr().out
    assert "tumour: left lung (inside)" in printed and "note:" not in printed
    # far beyond the model's volume range: played, with a note that it is extrapolated
    assert main(["track", str(model_file), "--points", str(points_csv), "--out", str(tmp_path / "far"),
                 "--volume-ml", f"{v_ee + 5000}"]) == 0
    assert "outside the model's range" in capsys.readouterr().out


def test_track_one_volume_reports_the_excursion(model_file, points_csv, tmp_path, capsys):
    # with one --volume-ml there is one frame, so every peak-to-peak range is 0: the console line
    # must still show how far each point moved from end-exhale (the 3-D norm of its displacement)
    out = tmp_path / "o"
    v_ee = sum(lung.volume_ee_ml for lung in two_lungs(2).lungs.values())
    assert main(["track", str(model_file), "--points", str(points_csv), "--out", str(out),
                 "--volume-ml", f"{v_ee + 500}"]) == 0
    rows = _rows(out / "trajectories.csv")
    moved = np.linalg.norm([[float(r[k]) for k in ("dx_mm", "dy_mm", "dz_mm")] for r in rows], axis=1)
    assert moved.min() > 1.0
    text = capsys.readouterr().out
    for label, dist in zip(("tumour", "clip"), moved):
        line = next(x for x in text.splitlines() if x.strip().startswith(f"{label}:"))
        assert "peak-to-peak mm LR 0.0 AP 0.0 SI 0.0" in line
        assert f"largest excursion from end-exhale {dist:.1f} mm" in line


def test_track_over_a_preset_breath(model_file, points_csv, tmp_path):
    # one breath: the trajectory starts and ends at end-exhale (a closed cycle), frames at --fps
    out = tmp_path / "p"
    assert main(["track", str(model_file), "--points", str(points_csv), "--out", str(out),
                 "--preset", "normal", "--fps", "10"]) == 0
    rows = _rows(out / "trajectories.csv")
    t = sorted({float(r["t_s"]) for r in rows})
    assert len(rows) == 2 * len(t) and t[0] == 0.0
    assert np.diff(t) == pytest.approx(np.full(len(t) - 1, np.diff(t)[0]))
    first, last = rows[:2], rows[-2:]
    for a, b in zip(first, last):
        assert [float(a[k]) for k in ("x_mm", "y_mm", "z_mm")] == pytest.approx(
            [float(b[k]) for k in ("x_mm", "y_mm", "z_mm")], abs=0.05)


@pytest.mark.parametrize("args, message", [
    (["--volume-ml", "3000", "--preset", "normal"], "mutually exclusive"),
    (["--cycles", "2"], "--cycles applies to --preset only"),
    (["--preset", "normal", "--cycles", "0"], "--cycles must be >= 1"),
    (["--tidal-ml", "1e6"], "--tidal-ml must be a tidal volume"),
    (["--volume-ml", "-5"], "--volume-ml must be > 0"),
    (["--fps", "0"], "--fps must be > 0"),
    (["--lung", "middle"], "lung 'middle' is not in the model"),
])
def test_track_bad_options(model_file, points_csv, tmp_path, capsys, args, message):
    assert main(["track", str(model_file), "--points", str(points_csv), "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_track_refuses_points_far_outside(model_file, tmp_path, capsys):
    # points in metres, or in another frame, land far from every lung: refused, naming the file
    bad = tmp_path / "metres.csv"
    bad.write_text("x_mm,y_mm,z_mm\n0.09,0,0.5\n0.3,0.2,-400\n")
    assert main(["track", str(model_file), "--points", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "metres.csv: 1 point(s) lie more than 30 mm outside every lung" in err[0]
    assert not (tmp_path / "x").exists()


def test_track_names_invalid_point_rows_or_skips_them(model_file, tmp_path, capsys):
    # One NaN row (line 3) among valid ones: refused naming its line (not "no finite marker rows");
    # with --skip-invalid the two valid points are tracked and line 3 is listed as skipped.
    pts = tmp_path / "p.csv"
    pts.write_text("x_mm,y_mm,z_mm,label\n90,0,-40,tumour\nnan,0,0,bad\n-90,10,20,clip\n")
    out = tmp_path / "x"
    assert main(["track", str(model_file), "--points", str(pts), "--out", str(out), "--volume-ml", "5000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{pts}: 1 row(s) without finite numbers in x_mm,y_mm,z_mm, at line(s) 3 " in err[0]
    assert not out.exists()
    assert main(["track", str(model_file), "--points", str(pts), "--out", str(out), "--volume-ml", "5000",
                 "--skip-invalid"]) == 0
    printed = capsys.readouterr().out
    assert f"{pts}: skipped 1 row(s) without finite x_mm,y_mm,z_mm, at line(s) 3" in printed
    assert [p["label"] for p in json.loads((out / "points.json").read_text())["points"]] == ["tumour", "clip"]


# --- RTSTRUCT in and out (docs/RADIOTHERAPY.md) ------------------------------------------------

GTV_CENTRE = np.array([90.0, 0.0, -40.0])  # inside the left lung of two_lungs(2), as the tumour above


@pytest.fixture
def gtv_files(tmp_path):
    """A CT series (32 x 32 x 20, 2 mm) around the tumour point and a 10 mm spherical GTV on it."""
    folder = write_ct_series(tmp_path / "ct", origin=tuple(GTV_CENTRE + [-31.0, -31.0, -19.0]))
    s = trimesh.creation.icosphere(4, radius=10.0)
    write_rtstruct(tmp_path / "gtv.dcm", read_ct_series(folder), [("GTV", s.vertices + GTV_CENTRE, s.faces, "GTV")])
    return folder, tmp_path / "gtv.dcm"


def test_track_rtstruct_writes_one_roi_per_volume(model_file, gtv_files, tmp_path, capsys):
    # at the end-exhale volume the structure stays where it was drawn (within half a 2 mm voxel);
    # 500 mL more moves its contour points by the interior field, as --points moves points; every
    # written contour lies on a slice of the reference series
    ct_dir, gtv = gtv_files
    v_ee = sum(lung.volume_ee_ml for lung in two_lungs(2).lungs.values())
    out, rs = tmp_path / "o", tmp_path / "moved.dcm"
    assert main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", "GTV", "--out", str(out),
                 "--volume-ml", f"{v_ee}", "--volume-ml", f"{v_ee + 500}",
                 "--out-rtstruct", str(rs), "--reference-ct", str(ct_dir)]) == 0
    printed = capsys.readouterr().out
    assert "GTV: " in printed and "left lung" in printed and f"wrote {rs}" in printed
    moved = read_rtstruct(rs)
    names = list(moved)
    assert names == [f"GTV@{v_ee:g}mL", f"GTV@{v_ee + 500:g}mL", "ITV_GTV"]
    rest = np.concatenate(moved[names[0]].contours)
    assert np.abs(np.linalg.norm(rest - GTV_CENTRE, axis=1) - 10.0).max() < 1.0
    z = read_ct_series(ct_dir).origins[:, 2]
    for c in moved[names[1]].contours:
        assert np.ptp(c[:, 2]) == 0 and np.abs(z - c[0, 2]).min() < 1e-6
    rows = _rows(out / "trajectories.csv")
    shift = np.array([[float(r[k]) for k in ("dx_mm", "dy_mm", "dz_mm")] for r in rows if float(r["delta_ml"]) > 0])
    assert np.linalg.norm(shift, axis=1).min() > 1.0


def test_track_rtstruct_phases(model_file, gtv_files, tmp_path):
    # --phases 3 over the plain cycle: three ROIs GTV@phase00 … 02 (--phase-zero end-exhale: phase 0 at
    # the end-exhale scan, where drawn; by default phase 0 is end-inhale, test_phases.py)
    ct_dir, gtv = gtv_files
    rs = tmp_path / "p.dcm"
    assert main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", "GTV", "--out", str(tmp_path / "o"),
                 "--phases", "3", "--phase-zero", "end-exhale", "--out-rtstruct", str(rs), "--reference-ct", str(ct_dir)]) == 0
    moved = read_rtstruct(rs)
    assert list(moved) == ["GTV@phase00", "GTV@phase01", "GTV@phase02", "ITV_GTV"]
    rest = np.concatenate(moved["GTV@phase00"].contours)
    assert np.abs(np.linalg.norm(rest - GTV_CENTRE, axis=1) - 10.0).max() < 1.0


def test_track_rtstruct_itv_holds_every_phase_and_the_motion_table_is_the_centroid(model_file, gtv_files, tmp_path,
                                                                                    capsys):
    # why: the ITV is the union over the phases, so every contour point of every phase ROI (read
    # back from the file) lies inside it or on its surface (within 0.5 mm: the union's 0.5 mm voxels);
    # structure_motion.csv: at phase 0 (end-exhale) the 10 mm sphere's own volume (4.19 mL) and centre,
    # at each phase a centroid displacement equal to the mean motion of its tracked contour points
    # (trajectories.csv, the independent point path) within 0.3 mm, the amplitude max − min of it
    from lungdeform.geometry.contours import contours_to_mesh
    from lungdeform.geometry.distance import SurfaceDistance
    from lungdeform.geometry.mesh import winding_numbers
    ct_dir, gtv = gtv_files
    out, rs = tmp_path / "o", tmp_path / "p.dcm"
    assert main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", "GTV", "--out", str(out),
                 "--phases", "4", "--phase-zero", "end-exhale", "--out-rtstruct", str(rs), "--reference-ct", str(ct_dir)]) == 0
    assert "ITV_GTV" in capsys.readouterr().out
    moved = read_rtstruct(rs)
    v, f = contours_to_mesh(moved["ITV_GTV"].contours)
    dist = SurfaceDistance(v, f)
    for k in range(4):
        pts = np.concatenate(moved[f"GTV@phase{k:02d}"].contours)
        outside = winding_numbers(pts, v, f) < 0.5
        assert not outside.any() or dist.distance(pts[outside]).max() < 0.5
    table = _rows(out / "structure_motion.csv")
    assert [r["state"] for r in table] == [f"phase{k:02d}" for k in range(4)]
    assert float(table[0]["volume_ml"]) == pytest.approx(4 / 3 * np.pi, rel=0.02)
    c = np.array([[float(r[f"centroid_{a}_mm"]) for a in "xyz"] for r in table])
    assert np.allclose(c[0], GTV_CENTRE, atol=0.1)
    traj = np.array([[float(t[f"d{a}_mm"]) for a in "xyz"] for t in _rows(out / "trajectories.csv")])
    for k, r in enumerate(table):
        mean = traj.reshape(4, -1, 3)[k].mean(axis=0)  # rows frame by frame
        assert np.allclose([float(r[f"d{a}_mm"]) for a in "xyz"], mean, atol=0.3)
        assert np.allclose([float(r[f"amplitude_{a}_mm"]) for a in "xyz"], np.ptp(c, axis=0), atol=2e-3)
    assert np.ptp(c[:, 2]) > 1.0  # it moves


@pytest.mark.parametrize("structure, message", [
    ("CTV", "gtv.dcm: no structure 'CTV' (structures: 'GTV')"),
])
def test_track_rtstruct_bad_structure(model_file, gtv_files, tmp_path, capsys, structure, message):
    # a name not in the file: exit 2, one line naming the file and the names there are, nothing written
    ct_dir, gtv = gtv_files
    out, rs = tmp_path / "o", tmp_path / "moved.dcm"
    assert main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", structure, "--out", str(out),
                 "--volume-ml", "3000", "--out-rtstruct", str(rs), "--reference-ct", str(ct_dir)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not out.exists() and not rs.exists()


def test_track_not_an_rtstruct(model_file, gtv_files, tmp_path, capsys):
    # a CT slice given as --rtstruct: exit 2, one line naming the file, nothing written
    ct_dir, _gtv = gtv_files
    out = tmp_path / "o"
    assert main(["track", str(model_file), "--rtstruct", str(ct_dir / "slice000.dcm"), "--structure", "GTV",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "slice000.dcm: not an RTSTRUCT" in err[0] and not out.exists()


def _run_rtstruct(model_file, gtv, ct_dir, tmp_path, structure="GTV", *extra):
    out, rs = tmp_path / "o", tmp_path / "moved.dcm"
    code = main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", structure, "--out", str(out),
                 "--phases", "2", "--out-rtstruct", str(rs), "--reference-ct", str(ct_dir), *extra])
    return code, out, rs


@pytest.mark.parametrize("damage, message", [
    # 3 of the GTV's 10 slices gone: written before with the contours of the others only
    ("drop", "slice(s) missing: the gaps between slices run from"),
    # an all-zero orientation gave no contours and exit 0; 5 values, or a position in words, a traceback
    ((0x0020, 0x0037, b"0\\0\\0\\0\\0\\0"), "slice010.dcm: ImageOrientationPatient [0.0, 0.0, 0.0, 0.0, 0.0, 0.0] is not"),
    ((0x0020, 0x0037, b"1\\0\\0\\0\\1"), "slice010.dcm: ImageOrientationPatient must be 6 finite numbers"),
    ((0x0020, 0x0032, b"a\\b\\c"), "slice010.dcm: ImagePositionPatient is not numeric"),
])
def test_track_refuses_a_damaged_reference_ct(model_file, gtv_files, tmp_path, capsys, damage, message):
    # exit 2, one line naming the file and the cause, and neither output written
    ct_dir, gtv = gtv_files
    if damage == "drop":
        for k in (9, 10, 11):
            (ct_dir / f"slice{k:03d}.dcm").unlink()
    else:
        patch_element(ct_dir / "slice010.dcm", *damage)
    code, out, rs = _run_rtstruct(model_file, gtv, ct_dir, tmp_path)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not out.exists() and not rs.exists()


def test_track_rtstruct_of_another_frame_of_reference(model_file, gtv_files, tmp_path, capsys):
    # the GTV drawn on another CT (another study and frame of reference) was written onto this one
    ct_dir, _gtv = gtv_files
    other = write_ct_series(tmp_path / "other", origin=tuple(GTV_CENTRE + [-31.0, -31.0, -19.0]), uid_root="1.2.3.99")
    s = trimesh.creation.icosphere(3, radius=10.0)
    write_rtstruct(tmp_path / "other.dcm", read_ct_series(other), [("GTV", s.vertices + GTV_CENTRE, s.faces, "GTV")])
    code, out, rs = _run_rtstruct(model_file, tmp_path / "other.dcm", ct_dir, tmp_path)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "other.dcm: structure 'GTV' is in Frame of Reference 1.2.3.99.3, --reference-ct" in err[0]
    assert "study 1.2.3.99.1 against 1.2.826.0.1.3680043.8.498.77.1: not the CT it was drawn on" in err[0]
    assert not out.exists() and not rs.exists()


def test_track_rtstruct_names(model_file, gtv_files, tmp_path, capsys):
    # a non-ASCII structure name is written as UTF-8 (SpecificCharacterSet ISO_IR 192) and reads back
    # the same; a name whose NAME@TAG exceeds a ROI Name's 64 bytes is no refusal (issue 36): written
    # cut on a character boundary with its tag whole, its whole name in ROIDescription
    ct_dir, _gtv = gtv_files
    s = trimesh.creation.icosphere(3, radius=10.0)
    ct = read_ct_series(ct_dir)
    long_name = "GTV_" + "x" * 56
    write_rtstruct(tmp_path / "in.dcm", ct, [("Tumör", s.vertices + GTV_CENTRE, s.faces, "GTV"),
                                             (long_name, s.vertices + GTV_CENTRE, s.faces, "GTV")])
    code, out, rs = _run_rtstruct(model_file, tmp_path / "in.dcm", ct_dir, tmp_path, "Tumör")
    assert code == 0, capsys.readouterr().err
    assert list(read_rtstruct(rs)) == ["Tumör@phase00", "Tumör@phase01", "ITV_Tumör"]
    rs.unlink()
    shutil.rmtree(out)
    code, out, rs = _run_rtstruct(model_file, tmp_path / "in.dcm", ct_dir, tmp_path, long_name)
    assert code == 0, capsys.readouterr().err
    rois = pydicom.dcmread(rs).StructureSetROISequence
    assert [str(r.ROIName) for r in rois] == [long_name[:56] + "@phase00", long_name[:56] + "@phase01", f"ITV_{long_name}"]
    assert [r.get("ROIDescription") for r in rois] == [f"{long_name}@phase00", f"{long_name}@phase01", None]
    err = capsys.readouterr().err.strip().splitlines()  # the two names cut, each said once
    assert len(err) == 2 and all(ln.startswith(f"note: ROI name '{long_name}@phase0") for ln in err)
    assert f"written as '{long_name[:56]}@phase00', the whole name in ROIDescription" in err[0]


#: Structure names as planning systems in other languages write them (issue 36): Chinese with Greek,
#: Greek, Arabic, combining characters (e + U+0301, decomposed), and one whose NAME@TAG is 63 bytes
NON_ASCII_NAMES = ("GTV_β肿瘤", "Όγκος_δεξιά", "ورم_الرئة", "Tume\u0301fie\u0301_G", "肿瘤肿瘤肿瘤肿瘤肿瘤肿瘤肿瘤肿瘤肿瘤")


@pytest.mark.parametrize("name", NON_ASCII_NAMES)
def test_track_non_ascii_names_round_trip(model_file, gtv_files, tmp_path, capsys, name):
    # the issue's case: "GTV_β肿瘤" was tracked, then refused at the end (StructureSetLabel "GTV_β肿瘤
    # moved" is 20 bytes of UTF-8, SH holds 16), leaving motion.png, points.json and trajectories.csv.
    # Truth: the same names come out (ROI Name, as pydicom and rt-utils read them back: NAME@TAG and
    # ITV_NAME), every derived value within its VR (the label cut on a character boundary), and
    # dciodvfy (dicom3tools) finds 0 errors
    ct_dir, _gtv = gtv_files
    s = trimesh.creation.icosphere(3, radius=10.0)
    write_rtstruct(tmp_path / "in.dcm", read_ct_series(ct_dir), [(name, s.vertices + GTV_CENTRE, s.faces, "GTV")])
    code, out, rs = _run_rtstruct(model_file, tmp_path / "in.dcm", ct_dir, tmp_path, name)
    assert code == 0, capsys.readouterr().err
    want = [f"{name}@phase00", f"{name}@phase01", f"ITV_{name}"]
    assert all(len(w.encode()) <= 64 for w in want)  # these fit a ROI Name whole
    ds = pydicom.dcmread(rs)
    assert ds.SpecificCharacterSet == "ISO_IR 192"
    assert [str(r.ROIName) for r in ds.StructureSetROISequence] == want == list(read_rtstruct(rs))
    label = str(ds.StructureSetLabel)
    assert len(label.encode()) <= 16 and f"{name} moved".startswith(label) and label
    errors, _warnings = dciodvfy(rs)
    assert errors == [], errors
    rt_utils = pytest.importorskip("rt_utils", reason="rt-utils not installed (pip install rt-utils; optional)")
    import warnings

    with warnings.catch_warnings():  # rt-utils 1.2.7 uses pydicom attributes pydicom 3 deprecates
        warnings.simplefilter("ignore", DeprecationWarning)
        rt = rt_utils.RTStructBuilder.create_from(dicom_series_path=str(ct_dir), rt_struct_path=str(rs))
        assert rt.get_roi_names() == want
        assert rt.get_roi_mask_by_name(want[0]).sum() > 100  # its contours, rasterised by rt-utils
    assert {p.name for p in out.iterdir()} == {"trajectories.csv", "points.json", "motion.png", "structure_motion.csv"}


def test_track_failing_at_its_last_output_writes_nothing(model_file, gtv_files, tmp_path, capsys, monkeypatch):
    # issue 36: a run that failed writing the RTSTRUCT (its last output) left motion.png, points.json
    # and trajectories.csv behind. Truth: the outputs are staged and appear together; a failure at
    # the last one leaves neither the folder (not there before) nor any file, nor a hidden temporary
    from lungdeform.cli import track as cli_track
    from lungdeform.errors import InputError

    ct_dir, gtv = gtv_files

    def failing(path, ds):
        Path(path).write_bytes(b"half")  # a writer that fails half way
        raise InputError(f"{path}: disk full (simulated)")

    monkeypatch.setattr(cli_track, "save_rtstruct", failing)
    code, out, rs = _run_rtstruct(model_file, gtv, ct_dir, tmp_path)
    assert code == 2 and "disk full (simulated)" in capsys.readouterr().err
    assert not out.exists() and not rs.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    # into an existing folder: its own files kept, none of the run's added
    out.mkdir()
    (out / "mine.txt").write_text("kept")
    code, out, rs = _run_rtstruct(model_file, gtv, ct_dir, tmp_path)
    assert code == 2 and sorted(p.name for p in out.iterdir()) == ["mine.txt"]


def test_track_out_rtstruct_must_not_overwrite_an_input(model_file, gtv_files, tmp_path, capsys):
    # --out-rtstruct naming the input RTSTRUCT would replace the structure set it reads
    ct_dir, gtv = gtv_files
    before = gtv.read_bytes()
    assert main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", "GTV", "--out", str(tmp_path / "o"),
                 "--phases", "2", "--out-rtstruct", str(gtv), "--reference-ct", str(ct_dir)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is the input" in err[0] and gtv.read_bytes() == before
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("args, message", [
    (["--phases", "1000000"], "--phases must be 1 to 100, got 1000000"),
    (["--fps", "1e9"], "--fps must be > 0 and at most 1000"),
    (["--preset", "normal", "--cycles", "1000000000"], "--cycles must be at most 100"),
    (["--fps", "1000"], "2000 point(s) x 4001 frame(s), more than 5000000 rows of trajectories"),
])
def test_track_schedule_is_bounded(model_file, tmp_path, capsys, args, message):
    # a million phases (a million ROIs), a billion frames per second or cycles (each simulated),
    # millions of trajectory rows: refused at once, before any allocation, instead of a MemoryError
    # traceback or a hang
    pts = tmp_path / "many.csv"
    pts.write_text("x_mm,y_mm,z_mm\n" + "90,0,-40\n" * 2000)
    out = tmp_path / "x"
    assert main(["track", str(model_file), "--points", str(pts), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()


def test_track_unreachable_volume_and_out_rtstruct_under_a_file(model_file, gtv_files, tmp_path, capsys):
    # --volume-ml 1e308 was a LinAlgError traceback; --out-rtstruct under a regular file left --out
    # behind: both are refused with one line before any output
    ct_dir, gtv = gtv_files
    out = tmp_path / "o"
    assert main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", "GTV", "--out", str(out),
                 "--volume-ml", "1e308"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--volume-ml 1e+308 mL" in err[0] and not out.exists()
    plan = tmp_path / "plan.txt"
    plan.write_text("x")
    assert main(["track", str(model_file), "--rtstruct", str(gtv), "--structure", "GTV", "--out", str(out),
                 "--phases", "2", "--out-rtstruct", str(plan / "moved.dcm"), "--reference-ct", str(ct_dir)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a file, not a folder" in err[0] and not out.exists()


# --- --scan K --out-rtstruct: the reference CT must be scan K's (docs/RADIOTHERAPY.md) -----------

def _scan(folder, uid_root="1.2.826.0.1.3680043.8.498.77", origin=GTV_CENTRE + [-31.0, -31.0, -19.0], patient="SYN001"):
    """The identity a fit records of a scan read from the series ``write_ct_series`` writes."""
    return {"source": str(folder), "patient_id": patient, "study_uid": f"{uid_root}.1", "series_uid": f"{uid_root}.2",
            "frame_of_reference": f"{uid_root}.3",
            "grid": {"size": [32, 32, 20], "spacing": [2.0, 2.0, 2.0], "origin": list(map(float, origin)),
                     "direction": np.eye(3).ravel().tolist()}}


@pytest.fixture
def scan_files(gtv_files, tmp_path):
    """Scan 0 (the GTV's CT, the model's frame) and scan 1 (another series and Frame of Reference,
    the same grid), and a model fitted to them whose alignment of scan 1 is a (2, -3, 6) mm shift."""
    ct0, gtv = gtv_files
    ct1 = write_ct_series(tmp_path / "ct1", origin=tuple(GTV_CENTRE + [-31.0, -31.0, -19.0]), uid_root="1.2.3.88")
    m = two_lungs(2)
    ee = sum(lung.volume_ee_ml for lung in m.lungs.values())
    a = np.eye(4)
    a[:3, 3] = [2.0, -3.0, 6.0]
    prov = {"volumes_ml": [ee, ee + 300.0], "alignment": [{"applied": {"matrix": a.tolist()}}],
            "scans": [_scan(ct0), _scan(ct1, "1.2.3.88")]}
    return ct0, ct1, gtv, m, prov


def _track_scan(model, gtv, ct, tmp_path, *extra):
    out, rs = tmp_path / "o", tmp_path / "moved.dcm"
    code = main(["track", str(model), "--rtstruct", str(gtv), "--structure", "GTV", "--out", str(out),
                 "--scan", "1", *extra, "--out-rtstruct", str(rs), "--reference-ct", str(ct)])
    return code, out, rs


def test_track_scan_writes_on_scan_ks_ct_in_its_frame(scan_files, tmp_path, capsys):
    # why: with --scan 1 the contours are in scan 1's own frame (the fit's (2, -3, 6) mm alignment
    # undone), so they go on scan 1's CT, whose Frame of Reference the RTSTRUCT carries; the GTV
    # drawn on scan 0 is checked against scan 0. Truth: with the same model at the same volume and
    # --no-rigid on scan 0's CT, the contours lie (2, -3, 6) mm away: the alignment's inverse shift
    from lungdeform.model.lung import Model
    ct0, ct1, gtv, m, prov = scan_files
    model = save_model(tmp_path / "fitted.npz", Model(m.lungs, prov))
    code, _out, rs = _track_scan(model, gtv, ct1, tmp_path / "a")
    assert code == 0, capsys.readouterr().err
    moved = read_rtstruct(rs)["GTV@scan1"]
    assert moved.frame_uid == "1.2.3.88.3"
    code, _out, rs0 = _track_scan(model, gtv, ct0, tmp_path / "b", "--no-rigid")
    assert code == 0, capsys.readouterr().err
    rigid = read_rtstruct(rs0)["GTV@scan1"]
    assert rigid.frame_uid == "1.2.826.0.1.3680043.8.498.77.3"
    c1, c0 = np.concatenate(moved.contours).mean(0), np.concatenate(rigid.contours).mean(0)
    assert np.allclose(c1 - c0, [-2.0, 3.0, -6.0], atol=0.5), c1 - c0  # slice sampling: within 0.5 mm


@pytest.mark.parametrize("case, message", [
    # the known gap: scan 1's contours were written onto the rest CT (scan 0's frame) unchecked
    ("rest ct", "ct: Frame of Reference 1.2.826.0.1.3680043.8.498.77.3, scan 1 ("),
    ("no record", "the model records no identity of scan 1"),
    ("other patient", "patient 'SYN001', scan 1 ("),
    ("other grid", "its slices span"),
    ("gtv not on scan 0", "not drawn on the model's scan"),
    ("scan 0 not dicom", "scan 0 of the fit (mask.nii.gz) was no DICOM series"),
    ("scan 1 a mesh", "scan 1 (lung.obj) was neither a DICOM series nor an image"),
    ("ct without pixel spacing", "ct1: DICOM file lacks PixelSpacing"),  # the image box needs it
    # --no-rigid: positions in the model's frame, so scan 1's CT is the wrong one
    ("no-rigid on scan 1", "ct1: Frame of Reference 1.2.3.88.3, scan 0 ("),
])
def test_track_scan_refuses_a_ct_that_is_not_scan_ks(scan_files, tmp_path, capsys, case, message):
    # exit 2, one line naming --reference-ct (or the structure) and the mismatch; nothing written
    from lungdeform.model.lung import Model
    ct0, ct1, gtv, m, prov = scan_files
    ct, extra = ct1, []
    if case == "rest ct":
        ct = ct0
    elif case == "no record":
        del prov["scans"]
    elif case == "other patient":
        prov["scans"][1]["patient_id"] = "OTHER"
    elif case == "other grid":
        prov["scans"][1].update(frame_of_reference="", series_uid="")
        prov["scans"][1]["grid"]["origin"][2] += 10.0
    elif case == "gtv not on scan 0":
        prov["scans"][0]["frame_of_reference"] = "1.2.3.77.3"
    elif case == "scan 0 not dicom":
        prov["scans"][0] = {"source": "mask.nii.gz", "grid": prov["scans"][0]["grid"]}
    elif case == "scan 1 a mesh":
        prov["scans"][1] = {"source": "lung.obj", "grid": None}
    elif case == "ct without pixel spacing":
        import pydicom
        for f in ct1.iterdir():
            ds = pydicom.dcmread(f)
            del ds.PixelSpacing
            ds.save_as(f)
    else:
        extra = ["--no-rigid"]
    model = save_model(tmp_path / "fitted.npz", Model(m.lungs, prov))
    code, out, rs = _track_scan(model, gtv, ct, tmp_path, *extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not out.exists() and not rs.exists()


@pytest.mark.parametrize("make, message", [
    (lambda p: p.mkdir(), ("{p}: is a folder, not a points file (give a CSV x_mm,y_mm,z_mm[,label] or an elastix "
                           "'point' file)")),
    (lambda p: p.write_text(""), ("{p}: the points file is empty (expected a CSV with header x_mm,y_mm,z_mm[,label] "
                                  "or an elastix 'point' file)")),
])
def test_track_names_a_points_folder_or_an_empty_points_file(model_file, tmp_path, capsys, make, message):
    # they used to say "no such points file" (the folder exists) and "markers need a header" (empty)
    points = tmp_path / "points.csv"
    make(points)
    assert main(["track", str(model_file), "--points", str(points), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip().splitlines() == ["error: " + message.format(p=points)]
    assert not (tmp_path / "o").exists()


def test_track_rigid_structure_moves_the_gtv_as_warp_keeps_it_in_the_image(model_file, gtv_files, tmp_path, capsys):
    # why: warp --rigid-structure GTV keeps the tumour rigid in the image while track let the same
    # GTV grow with the lung; with --rigid-structure its contours move by one rigid motion per state.
    # Truths: every pair of GTV contour points keeps its distance at every phase (rigid); its volume
    # stays the drawn one (structure_motion.csv, within 1 %) where the elastic GTV grows; at end-inhale
    # (phase 0) its centroid is that of the GTV's voxel mask (as float, resampled linearly: partial
    # voxels) warped with --rigid-structure GTV on the CT grid (2 mm voxels: within 0.3 mm), which
    # keeps the mask's volume (2 %) as track keeps the structure's
    from lungdeform.io.image import read_image, write_image
    from lungdeform.playback.displacement_field import Grid
    from lungdeform.playback.rigid import surface_mask
    from lungdeform.playback.structures import read_structure
    ct_dir, gtv = gtv_files
    base = ["track", str(model_file), "--rtstruct", str(gtv), "--structure", "GTV", "--phases", "4",
            "--reference-ct", str(ct_dir)]
    assert main([*base, "--out", str(tmp_path / "el"), "--out-rtstruct", str(tmp_path / "el.dcm")]) == 0
    assert main([*base, "--rigid-structure", "GTV", "--out", str(tmp_path / "rg"),
                 "--out-rtstruct", str(tmp_path / "rg.dcm")]) == 0
    assert "GTV: rigid" in capsys.readouterr().out
    rows = _rows(tmp_path / "rg" / "trajectories.csv")
    pos = np.array([[float(r[k]) for k in ("x_mm", "y_mm", "z_mm")] for r in rows]).reshape(4, -1, 3)
    drawn = read_structure(gtv, "GTV").points
    def pairs(p):
        return np.linalg.norm(p[:, None] - p[None], axis=-1)
    for k in range(4):
        assert np.abs(pairs(pos[k]) - pairs(drawn)).max() < 3e-4  # trajectories.csv: 4 decimals
    vol = {kind: [float(r["volume_ml"]) for r in _rows(tmp_path / kind / "structure_motion.csv")] for kind in ("el", "rg")}
    assert max(abs(v / vol["rg"][2] - 1) for v in vol["rg"]) < 0.01  # phase 2: end-exhale, the scan
    assert max(vol["el"]) / vol["el"][2] > 1.03, vol
    ct = read_image(ct_dir)
    s = read_structure(gtv, "GTV")
    mask = surface_mask(s.vertices, s.faces, Grid.of(ct)).astype(np.float32)
    write_image(tmp_path / "gtv.nii.gz", mask, ct.spacing, ct.origin, ct.direction)
    assert main(["warp", str(tmp_path / "gtv.nii.gz"), str(model_file), "--phases", "4", "--phase", "0",
                 "--rigid-structure", "GTV", "--rtstruct", str(gtv), "--out", str(tmp_path / "w.nii.gz")]) == 0
    w = read_image(tmp_path / "w.nii.gz")
    k, j, i = np.nonzero(w.array)
    weight = w.array[k, j, i].astype(float)
    centre = (Grid.of(w).world(np.stack([i, j, k], axis=1)) * weight[:, None]).sum(axis=0) / weight.sum()
    row = _rows(tmp_path / "rg" / "structure_motion.csv")[0]
    assert row["state"] == "phase00"
    track_centre = np.array([float(row[f"centroid_{a}_mm"]) for a in "xyz"])
    assert np.linalg.norm(centre - track_centre) < 0.3, (centre, track_centre)
    assert weight.sum() == pytest.approx(mask.sum(), rel=0.02)  # the image keeps the mask's volume, as track its own
