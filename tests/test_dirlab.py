"""DIR-Lab discovery, the one-scalar model and the richer models (lungdeform.dirlab)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lungdeform import dirlab as D
from lungdeform.errors import InputError, ReadError
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


def test_find_cases_both_naming_schemes(tmp_path, rng):
    truth, pairs = make_case_folder(tmp_path, rng)
    cases = D.find_cases(tmp_path)
    assert sorted(cases) == [1, 2]
    assert set(cases[2].extreme) == {"T00", "T50"} and set(cases[2].sampled) == set(D.PHASES)
    assert cases[2].extreme["T00"].name == "case2_dirLab300_T00_xyz.txt"
    assert np.allclose(cases[2].spacing, SPACING[2]) and list(cases[1].dims) == [256, 256, 94]
    for case in (1, 2):
        data = D.load_case(cases[case])
        # truth: the mean computed from the generated indices with mm = (index - 1) * spacing
        assert D.mean_displacement(data.pairs["T00"], data.pairs["T50"]) == pytest.approx(pairs[case])
        assert np.allclose(data.phases["T30"], truth[case]["T30"], atol=1e-5)


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
        (lambda r: (r / "voxel_spacing.csv").write_text("case,sx,sy,sz\n1,1,1,1\n"), "missing column"),
        (lambda r: (r / "Case1Pack/ExtremePhases/case1_300_T00_xyz_copy.txt").write_text(""), None),
    ],
)
def test_discovery_errors(tmp_path, rng, mutate, message):
    make_case_folder(tmp_path, rng)
    mutate(tmp_path)
    if message is None:  # a file that does not match the pattern is ignored
        assert sorted(D.find_cases(tmp_path)) == [1, 2]
        return
    with pytest.raises(ReadError, match=message):
        D.find_cases(tmp_path)


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
    with pytest.raises(ReadError, match="case 1: two files for sampled phase T30"):
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
