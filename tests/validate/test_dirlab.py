"""The one-scalar model, the richer models and their evaluation on DIR-Lab cases (lungdeform.validate.dirlab).

Also the builders of DIR-Lab-like folders (synthetic, or real cases copied into other archive
layouts under ``tmp_path``) shared with tests/validate/test_dirlab_files.py and tests/cli/test_validate_dirlab.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lungdeform.errors import InputError, ReadError
from lungdeform.validate import dirlab as D
from tests.conftest import require_path

SPACING = {1: (0.97, 0.97, 2.5), 2: (1.16, 1.16, 2.5)}
S_TRUE = {"T00": 1.0, "T10": 0.85, "T20": 0.55, "T30": 0.3, "T40": 0.1, "T50": 0.0}


def _write(path: Path, idx: np.ndarray, floats: bool) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = " %.6f\t %.6f\t %.6f\t\r\n" if floats else "%d\t%d\t%d\r\n"
    path.write_bytes("".join(fmt % tuple(r) for r in idx).encode())


def make_case_folder(root: Path, rng, motion="one_scalar", n75=75, n300=300):
    """A DIR-Lab-like folder with cases 1 and 2, named the two ways DIR-Lab's archives do.

    ``motion`` generates the 75-point phases (1-based float indices, no rounding) from T50 positions:
    ``one_scalar``: x = x50 + s d; ``lag``: x = x50 + (s + a b(s)) d; ``bend``: the path bends
    off d by b(s) c. Returns ``{case: {phase: (n, 3) mm}}`` (the truth) and the 300-pair truth.
    """
    (root).mkdir(parents=True, exist_ok=True)
    (root / "voxel_spacing.csv").write_text(
        "Case,dim_x,dim_y,dim_z,spacing_x_mm,spacing_y_mm,spacing_z_mm\n"
        "1,256,256,94,0.97,0.97,2.5\n2,256,256,112,1.16,1.16,2.5\n"
    )
    truth, pairs = {}, {}
    for case in (1, 2):
        sp = np.array(SPACING[case])
        if case == 1:
            ext = root / "Case1Pack" / "ExtremePhases"
            ext_name = "Case1_300_T{}_xyz.txt"
            smp = root / "Case1Pack" / "Sampled4D"
        else:
            ext = root / "case2" / "extremePhases"
            ext_name = "case2_dirLab300_T{}_xyz.txt"
            smp = root / "case2" / "sampled4D"
        a = rng.integers(20, 230, (n300, 3)).astype(float)
        a[:, 2] = rng.integers(10, 80, n300)
        b = a + rng.integers(-3, 4, (n300, 3))
        _write(ext / ext_name.format("00"), a, floats=False)
        _write(ext / ext_name.format("50"), b, floats=False)
        pairs[case] = np.linalg.norm((a - b) * sp, axis=1).mean()
        x50 = np.column_stack([rng.uniform(30, 220, n75), rng.uniform(40, 200, n75), rng.uniform(10, 80, n75)])
        d = rng.normal(0, 1.5, (n75, 3)) + [0, 0, 3]
        a_lag = rng.normal(0, 0.4, n75)
        c = np.cross(d * sp, [1.0, 0, 0]) * 0.5 / sp  # off the path, perpendicular to d in mm
        pos = {}
        for ph, s in S_TRUE.items():
            if motion == "one_scalar":
                x = x50 + s * d
            elif motion == "lag":
                x = x50 + (s + a_lag[:, None] * D.lag_basis(s)) * d
            else:
                x = x50 + s * d + D.lag_basis(s) * c
            _write(smp / f"case{case}_4D-75_T{ph[1:]}.txt", x, floats=True)
            pos[ph] = (x - 1) * sp
        truth[case] = pos
    return truth, pairs


def test_one_scalar_motion_is_recovered_exactly(tmp_path, rng):
    make_case_folder(tmp_path, rng, motion="one_scalar")
    files = D.find_cases(tmp_path)[1]
    r = D.evaluate_case(D.load_case(files), files.dims)
    # truth: the phases were generated with these scalars and no noise
    assert r.phase_scalars == pytest.approx({p: S_TRUE[p] for p in D.INTERMEDIATE}, abs=1e-6)
    assert r.one_scalar_mean_mm < 1e-5 < r.no_motion_mean_mm
    assert max(r.heldout_mean_mm.values()) < 1e-4  # every richer model contains the one-scalar one
    assert r.to_dict()["best_model_heldout_mean_mm"] < 1e-4


def test_lag_and_bend_are_found_on_held_out_phases(tmp_path, rng):
    make_case_folder(tmp_path / "lag", rng, motion="lag")
    make_case_folder(tmp_path / "bend", rng, motion="bend")
    lag = D.evaluate_case(D.load_case(D.find_cases(tmp_path / "lag")[1]))
    bend = D.evaluate_case(D.load_case(D.find_cases(tmp_path / "bend")[1]))
    # per-landmark timing: the lag model explains it, far better than one scalar
    assert lag.heldout_mean_mm["lag_landmark"] < 0.3 * lag.heldout_mean_mm["one_scalar"]
    # a bent path: only models that let the direction change explain it
    assert bend.heldout_mean_mm["curved_landmark"] < 1e-6
    assert bend.heldout_mean_mm["lag_landmark"] > 0.1
    assert bend.best_single_driver_model == "curved_landmark"
    assert D.hypothesis_summary([lag])["per_case"]["1"]["timing_gain"]["ci95_mm"][0] > 0
    assert "refuted in 1/1" in D.hypothesis_summary([bend])["direction_constant"]
    assert "refuted in 0/1" in D.hypothesis_summary([bend])["magnitude_one_scalar"]


def test_two_component_is_exact_for_two_modes(rng):
    n = 40
    x50, d, e = rng.normal(0, 20, (n, 3)), rng.normal(0, 3, (n, 3)), rng.normal(0, 1, (n, 3))
    s2 = {"T00": 0.0, "T10": 0.4, "T20": -0.3, "T30": 0.8, "T40": 0.2, "T50": 0.0}
    phases = {p: x50 + S_TRUE[p] * d + s2[p] * e for p in D.PHASES}
    err = D.heldout_errors("two_component", phases)
    # the residual of the one-scalar fit spans e⊥d; with d it spans the true plane → exact
    assert max(v.max() for v in err.values()) < 1e-9
    assert max(v.max() for v in D.heldout_errors("one_scalar", phases).values()) > 0.1


def test_regions_and_fit_inputs(rng):
    x50 = np.column_stack([rng.uniform(0, 200, 60), rng.uniform(0, 200, 60), rng.uniform(0, 100, 60)])
    reg = D.landmark_regions(x50, midline_x=100.0)
    assert set(reg) <= set(range(6))
    assert np.all((reg >= 3) == (x50[:, 0] >= 100))
    assert abs(np.bincount(reg % 3).std()) <= 1  # equal-count z bands
    with pytest.raises(InputError, match="model kind"):
        D.fit_path_model("spline", x50, x50, [x50])
    with pytest.raises(InputError, match="coincide"):
        D.phase_scalar(x50, x50, np.zeros_like(x50))
    with pytest.raises(InputError, match="needs regions"):
        D.fit_path_model("lag_region", x50 + 1, x50, [x50 + 0.5])


def test_rounding_floor_matches_uniform_error():
    # s = 0: |e_p - e50|, difference of two uniforms on a 1 mm cube; E|.| per axis is 1/3 mm,
    # so the mean norm lies between 1/3·sqrt(3)... check against a direct computation instead
    rng = np.random.default_rng(5)
    e = rng.random((2, 400_000, 3)) - 0.5
    direct = np.linalg.norm(e[0] - e[1], axis=1).mean()
    assert D.rounding_floor_mm((1, 1, 1), [0.0]) == pytest.approx(direct, rel=0.01)


def test_case_with_extreme_phases_only(tmp_path, rng):
    _, pairs = make_case_folder(tmp_path, rng)
    for f in (tmp_path / "case2" / "sampled4D").iterdir():
        f.unlink()
    files = D.find_cases(tmp_path)[2]
    r = D.evaluate_case(D.load_case(files), files.dims)
    # the 300-pair mean is still measured; the motion models are not evaluated
    assert r.mean_displacement_300_mm == pytest.approx(pairs[2])
    assert r.best_model is None and r.one_scalar_mean_mm is None
    assert D.hypothesis_summary([r])["per_case"] == {}


def test_load_errors(tmp_path, rng):
    make_case_folder(tmp_path, rng)
    p = tmp_path / "Case1Pack/Sampled4D/case1_4D-75_T30.txt"
    p.write_bytes(p.read_bytes() + b" 300.0\t 10.0\t 10.0\r\n")
    with pytest.raises(ReadError, match=r"case1_4D-75_T30.txt: landmark 76 .* outside the image"):
        D.load_case(D.find_cases(tmp_path)[1])
    p.write_bytes(b"".join(p.read_bytes().splitlines(keepends=True)[:70]))
    with pytest.raises(ReadError, match="case 1: landmark counts differ.*case1_4D-75_T30.txt: 70"):
        D.load_case(D.find_cases(tmp_path)[1])
    dup = tmp_path / "extra" / "CASE1_4d-75_t30.TXT"
    dup.parent.mkdir()
    dup.write_text("1 1 1\n")
    with pytest.raises(ReadError, match="case 1: two different files for sampled phase T30"):
        D.find_cases(tmp_path)


@pytest.mark.realdata
def test_real_dirlab_published_means_and_one_scalar(data_dir):
    root = require_path(data_dir, "dirlab-4dct-landmarks")
    cases = D.find_cases(root)
    assert sorted(cases) == [1, 2, 3, 4, 5]
    for case, files in cases.items():
        r = D.evaluate_case(D.load_case(files), files.dims)
        # Castillo et al. 2009: the published 300-pair mean displacements
        assert r.mean_displacement_300_mm == pytest.approx(D.PUBLISHED_MEAN_300_MM[case], abs=0.01)
        assert r.n_pairs == 300 and r.n_tracked == 75
        # the paper's model (one scalar per phase) beats no motion on real exhalation
        assert r.one_scalar_mean_mm < r.no_motion_mean_mm
        # T10…T40 lie on the exhale branch: the scalars fall from T00 (1) toward T50 (0)
        s = [r.phase_scalars[p] for p in D.INTERMEDIATE]
        assert all(a > b for a, b in zip(s, s[1:])) and 0 < s[-1] < s[0] <= 1.05
        assert r.best_model_heldout_mean_mm <= r.heldout_mean_mm["one_scalar"]


# --------------------------------------------------------------------------- real-archive variants
CSV_1_10 = {  # (dims, spacing) as published for cases 1–10 (DIR-Lab site; Castillo et al. 2009, 2010)
    c: g for c, g in D.PUBLISHED_GEOMETRY.items()
}


def spacing_csv_text(style: str) -> str:
    """voxel_spacing.csv for cases 1–10 written in one of several realistic dialects."""
    rows = [(c, *dims, *sp) for c, (dims, sp) in sorted(CSV_1_10.items())]
    if style == "reordered":  # other column order, extra columns, spaces, 'caseN' labels, a comment
        head = " Spacing_Z_mm , notes, Case ,spacing_y_mm, spacing_x_mm , dim_z,dim_y,dim_x\n# from the DIR-Lab site\n"
        body = "".join(f" {r[6]} , scan {r[0]}, case{r[0]} , {r[5]},{r[4]} , {r[3]},{r[2]},{r[1]}\n" for r in rows)
        return head + body + "\n\n"
    if style == "semicolon":  # European spreadsheet export, CRLF, no dims
        return "case;spacing_x_mm;spacing_y_mm;spacing_z_mm\r\n" + "".join(
            f"{r[0]};{r[4]};{r[5]};{r[6]}\r\n" for r in rows)
    if style == "tabs":  # tab-separated, 'Case N' labels, aliases for the column names
        return "Case\tx spacing (mm)\ty spacing (mm)\tz spacing (mm)\tsize x\tsize y\tsize z\n" + "".join(
            f"Case {r[0]}\t{r[4]}\t{r[5]}\t{r[6]}\t{r[1]}\t{r[2]}\t{r[3]}\n" for r in rows)
    raise ValueError(style)


def rewrite_landmark_file(src: Path, dst: Path, style: str) -> None:
    """Copy one real DIR-Lab file to ``dst`` with another whitespace/number style (same values)."""
    vals = [ln.split() for ln in src.read_text().splitlines() if ln.strip()]
    if style == "spaces_lf":
        text = "".join("   ".join(v) + "\n" for v in vals)
    elif style == "tabs_crlf_blank_tail":
        text = "".join("\t".join(v) + "\t\r\n" for v in vals) + "\r\n\r\n"
    elif style == "floats":
        text = "".join(" ".join(f"{float(x):.4f}" for x in v) + "\n" for v in vals) + "\n   \n"
    else:
        raise ValueError(style)
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(text.encode())


def make_real_variant_layout(real: Path, root: Path, csv_style: str = "reordered") -> None:
    """Copy the real DIR-Lab cases 1–5 into the layouts and names of the real archive's cases 6–10.

    Only ever written under a test's ``tmp_path`` (DIR-Lab content never enters the repository).
    case 1: ``Case1Pack/extremePhases/case1_dirLab300_T00_xyz.txt`` + ``Sampled4D``, LF, spaces;
    case 2: ``Case2Deploy/ExtremePhases/CASE2_DIRLAB300_T00_XYZ.TXT``, tabs, CRLF, blank tail;
    case 3: float coordinates in both sets; case 4: the 300 pairs only; case 5: the 75 points only,
    plus a T60 file the models do not use.
    """
    src = {c: real / f"Case{c}Pack" for c in range(1, 6)}
    ext = lambda c, ph: next((src[c] / "ExtremePhases").glob(f"*_T{ph}_xyz.txt"))  # noqa: E731
    smp = lambda c, ph: src[c] / "Sampled4D" / f"case{c}_4D-75_T{ph}.txt"  # noqa: E731
    phases = ["00", "10", "20", "30", "40", "50"]
    for ph in ("00", "50"):
        rewrite_landmark_file(ext(1, ph), root / "Case1Pack/extremePhases" / f"case1_dirLab300_T{ph}_xyz.txt", "spaces_lf")
        rewrite_landmark_file(ext(2, ph), root / "Case2Deploy/ExtremePhases" / f"CASE2_DIRLAB300_T{ph}_XYZ.TXT", "tabs_crlf_blank_tail")
        rewrite_landmark_file(ext(3, ph), root / "Case3Pack/ExtremePhases" / f"case3_dirLab300_T{ph}_xyz.txt", "floats")
        rewrite_landmark_file(ext(4, ph), root / "Case4Pack/ExtremePhases" / f"Case4_300_T{ph}_xyz.txt", "tabs_crlf_blank_tail")
    for ph in phases:
        rewrite_landmark_file(smp(1, ph), root / "Case1Pack/Sampled4D" / f"case1_4D-75_T{ph}.txt", "spaces_lf")
        rewrite_landmark_file(smp(2, ph), root / "Case2Deploy/sampled4D" / f"Case2_4D-75_T{ph}.txt", "tabs_crlf_blank_tail")
        rewrite_landmark_file(smp(3, ph), root / "Case3Pack/Sampled4D" / f"case3_4D-75_T{ph}.txt", "floats")
        rewrite_landmark_file(smp(5, ph), root / "Case5Pack/Sampled4D" / f"case5_4D-75_T{ph}.txt", "spaces_lf")
    rewrite_landmark_file(smp(5, "50"), root / "Case5Pack/Sampled4D/case5_4D-75_T60.txt", "spaces_lf")
    (root / "voxel_spacing.csv").write_bytes(spacing_csv_text(csv_style).encode())


# --------------------------------------------------------------------------- unseen archives: cases 1–10
# --------------------------------------------------------------------------- unseen archives: cases 1–10
#: Where DIR-Lab's original archives put each case's files (folder and file-name spelling differ from
ARCHIVE_LAYOUT = {
    1: ("Case1Pack/ExtremePhases/Case1_300_T{ph}_xyz.txt", "Case1Pack/Sampled4D/case1_4D-75_T{ph}.txt", "tabs_crlf"),
    2: ("Case2Pack/ExtremePhases/Case2_300_T{ph}_xyz.txt", None, "spaces"),
    3: ("case3/extremephases/case3_300_t{ph}_xyz.txt", None, "floats_crlf"),
    4: ("Case4Pack/ExtremePhases/Case4_300_T{ph}_xyz.txt", None, "spaces"),
    5: ("Case5Deploy/ExtremePhases/CASE5_300_T{ph}_XYZ.TXT", None, "tabs_crlf"),
    6: ("Case6Pack/ExtremePhases/case6_dirLab300_T{ph}_xyz.txt", "Case6Pack/Sampled4D/case6_4D-75_T{ph}.txt",
        "floats_crlf"),
    7: ("Case7Pack/extremePhases/case7_dirLab300_T{ph}_xyz.txt", None, "spaces"),
    8: ("Case8Deploy/extremePhases/case8_dirLab300_T{ph}_xyz.txt", None, "tabs_crlf"),
    9: ("case9/ExtremePhases/case9_dirLab300_T{ph}_xyz.txt", None, "spaces"),
    10: ("Case10Pack/ExtremePhases/case10_dirLab300_T{ph}_xyz.txt", "Case10Pack/Sampled4D/case10_4D-75_T{ph}.txt",
         "floats_crlf"),
}


def _write_styled(path: Path, idx: np.ndarray, style: str) -> np.ndarray:
    """Write 1-based indices in one of the archives' text styles; return the values as written."""
    if style == "tabs_crlf":  # whole numbers, tab separated, CRLF, a blank line at the end
        vals = np.rint(idx)
        text = "".join("%d\t%d\t%d\r\n" % tuple(r) for r in vals) + "\r\n"
    elif style == "spaces":  # whole numbers, runs of spaces, leading blanks, LF
        vals = np.rint(idx)
        text = "".join("  %d    %d   %d\n" % tuple(r) for r in vals)
    else:  # floats_crlf: fractional indices, tabs and spaces mixed, CRLF
        vals = np.round(idx, 4)
        text = "".join(" %.4f \t%.4f   %.4f\r\n" % tuple(r) for r in vals)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(text.encode())
    return vals


def make_archive_1_10(root: Path, rng, spacing_rows=(1, 2, 3, 4, 5)) -> dict[int, float]:
    """Synthetic landmark files for DIR-Lab cases 1–10 laid out as in :data:`ARCHIVE_LAYOUT`.

    Coordinates are random (seeded), inside each case's published image size; case ``c`` moves
    about ``c`` voxels so that every case has its own mean (case 10's files read as case 1's would
    show). ``voxel_spacing.csv`` lists only ``spacing_rows``. Returns the true 300-pair mean (mm)
    per case, from the values as written and the published spacing.
    """
    root.mkdir(parents=True, exist_ok=True)
    truth = {}
    for c, (ext, smp, style) in ARCHIVE_LAYOUT.items():
        dims, sp = np.array(D.PUBLISHED_GEOMETRY[c][0]), np.array(D.PUBLISHED_GEOMETRY[c][1])
        a = rng.uniform(20, dims - 20, (300, 3))
        b = np.clip(a + rng.normal(0, c / 2, (300, 3)), 1, dims)
        va = _write_styled(root / ext.format(ph="00"), a, style)
        vb = _write_styled(root / ext.format(ph="50"), b, style)
        truth[c] = float(np.linalg.norm((va - vb) * sp, axis=1).mean())
        if smp:
            x50 = rng.uniform(30, dims - 30, (75, 3))
            d = rng.normal(0, 2, (75, 3)) + [0, 0, 4]
            for ph, s in S_TRUE.items():
                _write_styled(root / smp.format(ph=ph[1:]), x50 + s * d, "floats_crlf")
    rows = "".join(f"{c},{','.join(map(str, D.PUBLISHED_GEOMETRY[c][0]))},{','.join(map(str, D.PUBLISHED_GEOMETRY[c][1]))}\n"
                   for c in spacing_rows)
    (root / "voxel_spacing.csv").write_text("case,dim_x,dim_y,dim_z,spacing_x_mm,spacing_y_mm,spacing_z_mm\n" + rows)
    return truth


def _result(case: int, held: dict) -> "D.CaseResult":
    """A CaseResult with only the held-out means that model choice reads."""
    best = min(held, key=held.get) if held else None
    return D.CaseResult(case, 300, None, None, 75, {}, None, None, {}, held, best,
                        held.get(best) if held else None, best, None)


def test_default_model_is_chosen_on_the_other_cases():
    # hand-made held-out means (mm). Leave-one-case-out, by hand:
    #   case 1: others 2, 3 -> a 3.0, b 1.55 -> b (2.5 on case 1; its own best a 0.5 is the diagnostic)
    #   case 2: others 1, 3 -> a 1.75, b 2.05 -> a (3.0 on case 2)
    #   case 3: others 1, 2 -> a 1.75, b 2.0 -> a (3.0 on case 3)
    # case 4 has no 75-point phases: no default, and no say in the others' choice
    results = [_result(1, {"a": 0.5, "b": 2.5}), _result(2, {"a": 3.0, "b": 1.5}),
               _result(3, {"a": 3.0, "b": 1.6}), _result(4, {})]
    assert D.default_models(results) == {1: ("b", 2.5), 2: ("a", 3.0), 3: ("a", 3.0), 4: (None, None)}
    # pooled over all three: a 6.5/3 = 2.167, b 5.6/3 = 1.867 -> b
    pooled = D.pooled_choice(results)
    assert pooled["model"] == "b" and pooled["cases"] == [1, 2, 3]
    assert pooled["mean_of_case_means_mm"] == pytest.approx({"a": 6.5 / 3, "b": 5.6 / 3})
    # one case alone: no other case to choose on
    assert D.default_models(results[:1]) == {1: (None, None)}
