"""``lungdeform fit``: surfaces at two volumes in, model + metrics + HTML report out; bad input exits 2."""

import json

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.cli.main import main
from lungdeform.io.landmarks import write_elastix_points
from lungdeform.io.meshfile import write_mesh
from lungdeform.io.modelfile import load_model
from lungdeform.model.lung import BuildSettings, build_lung
from tests.conftest import ellipsoid_lung
from tests.segment.test_split import two_lungs

TRUE = np.array([0.2, 1.5, 0.4, 0.8, 0.9, 1.8, 0.3, 1.0, 0.5])


@pytest.fixture
def pair(tmp_path):
    # synthetic truth: the end-exhale ellipsoid and the same lung deformed by a known model (+200 mL)
    lung = ellipsoid_lung("right")
    model = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(200.0, 200.0))
    a = write_mesh(tmp_path / "ee.ply", lung.vertices, lung.faces)
    b = write_mesh(tmp_path / "ei.ply", lung.vertices + model.displacement, lung.faces)
    return a, b, lung


def _one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")
    return err[0]


def test_fit_writes_model_metrics_report(tmp_path, pair, capsys):
    a, b, lung = pair
    out = tmp_path / "out"
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(out), "--evaluations", "400"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    for name in ("model", "no_motion", "affine", "apex_scaling"):
        assert set(m[name]) >= {"surface_mean_mm", "surface_rms_mm", "surface_p95_mm", "landmark_mean_mm"}
    # the model reproduces a surface made by the model (truth) better than no motion
    assert m["model"]["surface_mean_mm"] < 0.3 * m["no_motion"]["surface_mean_mm"]
    model = load_model(out / "model.npz")
    lm = model.lungs["right"]
    assert lm.n_vertices == lung.n_vertices
    # at the second volume the stored model gives the fitted surface: p + s·u
    assert lm.volume_ee_ml + lm.unit_ml == pytest.approx(m["volumes_ml"][1])
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 5
    assert "wrote" in capsys.readouterr().out


def test_given_volumes_fix_the_changes_and_metrics_are_strict_json(tmp_path, pair, capsys):
    # truth: given volumes 100 mL off the measured ones in absolute terms but with the measured
    # change keep the model's end-exhale volume (its surface's) and its unit (the change); the
    # metrics parse with a strict JSON reader (no bare NaN, e.g. landmark errors without landmarks)
    from lungdeform.io.meshfile import load_surface

    a, b, _ = pair
    va, vb = (load_surface(p)[0].volume_ml for p in (a, b))
    out = tmp_path / "given"
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(out), "--evaluations", "60",
                 "--no-baselines", "--direction-degree", "0", "--volumes", f"{va + 100},{vb + 100}"]) == 0
    text = (out / "metrics.json").read_text()
    m = json.loads(text, parse_constant=lambda c: pytest.fail(f"metrics.json holds {c}"))
    assert m["volumes_given_ml"] == pytest.approx([va + 100, vb + 100])
    assert m["volumes_ml"] == pytest.approx([va, vb])
    assert load_model(out / "model.npz").lungs["right"].unit_ml == pytest.approx(vb - va)
    capsys.readouterr()
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(tmp_path / "neg"), "--volumes", "-5,10"]) == 2
    assert "--volumes must be positive mL" in _one_error_line(capsys)


def test_volumes_not_increasing(tmp_path, pair, capsys):
    a, b, _ = pair
    code = main(["fit", str(a), str(b), "--side", "right", "--out", str(tmp_path / "o"), "--volumes", "1500,1400"])
    assert code == 2
    line = _one_error_line(capsys)
    assert "volumes must increase" in line and "ei.ply" in line
    assert not (tmp_path / "o" / "model.npz").exists()


def test_sides_do_not_match(tmp_path, pair, capsys):
    a, _, _ = pair
    left = ellipsoid_lung("left")
    c = write_mesh(tmp_path / "left.ply", left.vertices * np.array([1, 1, 1]) * 1.05, left.faces)
    assert main(["fit", str(a), str(c), "--side", "right", "--out", str(tmp_path / "o")]) == 2
    assert "sides do not match" in _one_error_line(capsys)


def test_side_that_the_shape_contradicts(tmp_path, capsys):
    # truth: the embedded right lung (from CT) and a 5 % larger copy, fitted as the left lung: the
    # concave medial face lies toward +x, so the side is wrong (or the surfaces are in RAS)
    from lungdeform.data import default_lungs

    s = default_lungs()["right"]
    a = write_mesh(tmp_path / "ee.ply", s.vertices, s.faces)
    c = s.vertices.mean(axis=0)
    b = write_mesh(tmp_path / "ei.ply", c + 1.05 * (s.vertices - c), s.faces)
    assert main(["fit", str(a), str(b), "--side", "left", "--out", str(tmp_path / "o")]) == 2
    line = _one_error_line(capsys)
    assert "ee.ply: the lung's shape says right, not left" in line and not (tmp_path / "o" / "model.npz").exists()


def test_missing_and_empty_inputs(tmp_path, pair, capsys):
    import SimpleITK as sitk

    a, _, _ = pair
    assert main(["fit", str(a), str(tmp_path / "nope.ply"), "--side", "right", "--out", str(tmp_path / "o")]) == 2
    assert "nope.ply" in _one_error_line(capsys)
    empty = tmp_path / "empty.mha"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((5, 6, 7), np.uint8)), str(empty))
    assert main(["fit", str(empty), str(a), "--side", "right", "--out", str(tmp_path / "o")]) == 2
    assert "empty.mha" in _one_error_line(capsys)


def test_inconsistent_spacing(tmp_path, capsys, monkeypatch):
    # refused as soon as the second image is read: its surface is never extracted (for a CT, its
    # segmentation never runs)
    import SimpleITK as sitk

    import lungdeform.io.mask as M

    extracted = []
    real = M.extract_surface
    monkeypatch.setattr(M, "extract_surface", lambda image, **kw: extracted.append(image.source) or real(image, **kw))

    z, y, x = np.mgrid[:30, :30, :30]
    ball = (((x - 15) ** 2 + (y - 15) ** 2 + (z - 15) ** 2) < 100).astype(np.uint8)
    paths = []
    for name, sp in (("a.mha", (2.0, 2.0, 2.0)), ("b.mha", (2.0, 2.0, 2.5))):
        img = sitk.GetImageFromArray(ball)
        img.SetSpacing(sp)
        sitk.WriteImage(img, str(tmp_path / name))
        paths.append(str(tmp_path / name))
    assert main(["fit", *paths, "--side", "right", "--out", str(tmp_path / "o")]) == 2
    assert "b.mha: voxel spacing [2.0, 2.0, 2.5] mm differs from" in _one_error_line(capsys)
    assert len(extracted) == 1 and "a.mha" in extracted[0]


def test_fit_with_landmarks_is_held_out(tmp_path, pair, capsys):
    # synthetic truth with interior landmarks moved by the true field (its sliding interpolation):
    # the headline model is the surface fit with the interior landmark correction, scored on held-out
    # landmarks; the surface-driven field alone, the landmark-informed fit and references are
    # reported beside it, each with its protocol
    from lungdeform.interior.sliding import surface_weights
    from lungdeform.io.landmarks import write_elastix_points

    a, b, lung = pair
    u = build_lung(lung, "right", constants=TRUE, settings=BuildSettings(200.0, 200.0)).displacement
    rng = np.random.default_rng(2)
    lm = lung.vertices.mean(0) + rng.uniform(-1, 1, size=(12, 3)) * np.array([20.0, 35.0, 55.0])
    la = write_elastix_points(tmp_path / "ee.txt", lm)
    lb = write_elastix_points(tmp_path / "ei.txt", lm + surface_weights(lung, lm) @ u)
    out = tmp_path / "out"
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(out), "--evaluations", "150",
                 "--landmarks", str(la), "--landmarks", str(lb), "--folds", "3", "--landmark-comparisons"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["headline_fit"] == "optimizer" and m["interior_correction"] and m["landmark_cv"]["folds"] == 3
    for name in ("model", "model_surface_only", "model_landmark_fit", "affine_landmarks", "landmarks_tps", "no_motion"):
        assert name in m and name in m["protocols"]
    assert "held-out" in m["protocols"]["model"]
    # the truth is in the model's form: held-out landmarks within a fraction of their motion
    assert m["model"]["landmark_mean_mm"] < 0.2 * m["no_motion"]["landmark_mean_mm"]
    assert m["fit"]["landmarks"]["landmarks_used"] == 12 and m["fit"]["optimizer"]["landmarks_used"] == 0
    # the model file carries the correction, so 'lungdeform track' moves interior points with it
    saved = load_model(out / "model.npz").lungs["right"]
    assert saved.landmarks.shape == saved.landmark_correction.shape == (12, 3) and saved.interior.corrected
    # without --landmark-comparisons: the correction only, no landmark-informed fits
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(tmp_path / "quick"), "--evaluations", "60",
                 "--no-baselines", "--landmarks", str(la), "--landmarks", str(lb), "--folds", "3"]) == 0
    q = json.loads((tmp_path / "quick" / "metrics.json").read_text())
    assert q["interior_correction"] and "landmarks" not in q["fit"] and "model_landmark_fit" not in q
    capsys.readouterr()
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(tmp_path / "o2"),
                 "--landmarks", str(la), "--landmarks", str(lb), "--folds", "20"]) == 2
    assert "--folds must be between 2 and the number of landmarks (12)" in _one_error_line(capsys)


def test_align_none_and_joint_against_a_known_translation(tmp_path, pair, capsys):
    # truth: the target is the model's deformation of the end-exhale lung, in its frame, then moved
    # by a known table shift. --align none must leave the target where it is (identity applied);
    # --align joint must find the shift back (applied translation = −shift; the model form is exact,
    # measured error 0.001 mm, the apex alignment alone 1.1 mm off; asserted within 0.1 mm) and then
    # fit the surface to near zero (measured 0.0007 mm).
    from lungdeform.io.meshfile import load_surface

    a, b, lung = pair
    shift = np.array([1.5, -2.0, 2.5])
    surf, _ = load_surface(b)
    c = write_mesh(tmp_path / "ei_shifted.ply", surf.vertices + shift, surf.faces)
    # the paper's directions only and no surface refinement: the direction correction's constant
    # term and the refinement would hide part of an unremoved shift, and this test is about the alignment
    common = ["--side", "right", "--evaluations", "300", "--no-baselines", "--direction-degree", "0",
              "--refine-mm", "0"]
    assert main(["fit", str(a), str(c), "--out", str(tmp_path / "none"), "--align", "none", *common]) == 0
    m = json.loads((tmp_path / "none" / "metrics.json").read_text())
    assert m["alignment"][0]["method"] == "none" and "apex" not in m["alignment"][0]
    assert np.asarray(m["alignment"][0]["applied"]["matrix"]) == pytest.approx(np.eye(4))
    assert m["model"]["surface_mean_mm"] > 0.5  # the unremoved shift shows
    assert main(["fit", str(a), str(c), "--out", str(tmp_path / "joint"), "--align", "joint", *common]) == 0
    j = json.loads((tmp_path / "joint" / "metrics.json").read_text())
    applied = np.asarray(j["alignment"][0]["applied"]["matrix"])
    assert applied[:3, :3] == pytest.approx(np.eye(3), abs=0.02)
    moved = surf.vertices + shift
    assert (moved @ applied[:3, :3].T + applied[:3, 3]) == pytest.approx(surf.vertices, abs=0.1)
    assert j["model"]["surface_mean_mm"] < 0.1
    assert j["fit"]["optimizer"]["translations_mm"] is not None
    capsys.readouterr()
    assert main(["fit", str(a), str(c), "--out", str(tmp_path / "bad"), "--align", "sideways", *common]) == 2
    assert "--align" in _one_error_line(capsys)


def test_unconverged_fit_is_said_and_zero_evaluations_refused(tmp_path, pair, capsys):
    a, b, _ = pair
    # a budget of 1 evaluation cannot converge: metrics.json records success false, and the user is
    # told on stderr (it used to exit 0 with no word, the table showing a model worse than no motion)
    out = tmp_path / "o"
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(out), "--evaluations", "1",
                 "--no-baselines"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["fit"]["optimizer"]["success"] is False
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: the optimizer fit did not converge")
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(tmp_path / "z"), "--evaluations", "0"]) == 2
    # the library names the parameter (max_evaluations); the command says its option
    assert "--evaluations must be a whole number >= 1, got 0" in _one_error_line(capsys)
    assert not (tmp_path / "z").exists()


def test_fit_masks_holding_both_lungs_keeps_that_lungs_landmarks(tmp_path, capsys):
    # truth: two binary masks of both lungs in one label (touching ellipsoids, the second larger:
    # tests/segment/test_split.py); --side left fits the left ellipsoid of each split, and of 10
    # landmark rows (6 in the left lung, 4 in the right) only the 6 left ones are used, said in a note
    ee, left_ee, _ = two_lungs(source="ee.nii.gz")
    ei, left_ei, _ = two_lungs(source="ei.nii.gz", scale=(1.05, 1.05, 1.1))
    paths = []
    for image, name in ((ee, "ee.nii.gz"), (ei, "ei.nii.gz")):
        im = sitk.GetImageFromArray(np.asarray(image.array))
        im.SetSpacing(image.spacing.tolist())
        im.SetOrigin(image.origin.tolist())
        sitk.WriteImage(im, str(tmp_path / name))
        paths.append(str(tmp_path / name))
    rng = np.random.default_rng(3)
    lm = np.concatenate([[42.0, 0, 0] + rng.uniform(-1, 1, (6, 3)) * [12, 10, 20],
                         [-42.0, 0, 0] + rng.uniform(-1, 1, (4, 3)) * [12, 10, 20]])
    la = write_elastix_points(tmp_path / "ee.txt", lm)
    lb = write_elastix_points(tmp_path / "ei.txt", lm * [1.0, 1.0, 1.1])
    out = tmp_path / "out"
    assert main(["fit", *paths, "--side", "left", "--out", str(out), "--evaluations", "40", "--no-baselines",
                 "--no-stiffness", "--align", "none", "--landmarks", str(la), "--landmarks", str(lb),
                 "--folds", "3"]) == 0
    text = capsys.readouterr().out
    assert "note: " in text and "a mask holding both lungs in one label" in text
    assert "kept the 6 landmarks in the left lung; dropped 4 of 10 in the other lung" in text
    m = json.loads((out / "metrics.json").read_text())
    assert m["landmark_cv"]["landmarks"] == 6
    voxel_ml = float(np.prod(ee.spacing)) / 1000
    assert m["volumes_ml"][0] == pytest.approx(left_ee.sum() * voxel_ml, rel=0.05)


def test_correspondence_interior_and_motion_prior(tmp_path, capsys):
    # truth: the end-inhale lung is the end-exhale one expanded 15 % about its centroid, and so are
    # its interior landmarks; the correspondence interior (moment affine + smooth map) carries them
    # within a small fraction of their motion, the model file keeps the map, and a motion prior of a
    # pure offset moves every surface-only prediction by exactly that offset times the prior's taper
    # at the landmark's depth, and leaves the model's surface where the field puts it (the taper is 0
    # there: the lung keeps its surface and volume change)
    from lungdeform.interior.motion_prior import MotionPrior, save_prior, taper_at

    lung = ellipsoid_lung("right")
    c = lung.vertices.mean(axis=0)
    a = write_mesh(tmp_path / "ee.ply", lung.vertices, lung.faces)
    b = write_mesh(tmp_path / "ei.ply", c + 1.15 * (lung.vertices - c), lung.faces)
    lm = c + np.random.default_rng(3).uniform(-1, 1, size=(12, 3)) * np.array([20.0, 35.0, 55.0])
    lm = np.r_[lm, c + 0.97 * (lung.vertices[:: len(lung.vertices) // 4][:4] - c)]  # and 4 just below the surface
    la = write_elastix_points(tmp_path / "ee.txt", lm)
    lb = write_elastix_points(tmp_path / "ei.txt", c + 1.15 * (lm - c))
    common = ["--side", "right", "--evaluations", "40", "--no-baselines", "--no-stiffness", "--landmarks", str(la),
              "--landmarks", str(lb), "--folds", "3", "--align", "none"]
    assert main(["fit", str(a), str(b), "--out", str(tmp_path / "plain"), *common]) == 0
    m = json.loads((tmp_path / "plain" / "metrics.json").read_text())
    motion = np.linalg.norm(0.15 * (lm - c), axis=1).mean()
    assert m["interior"]["surface_part"] == "correspondence" and "model_surface_sliding" in m
    assert m["model_surface_only"]["landmark_mean_mm"] < 0.1 * motion
    assert load_model(tmp_path / "plain" / "model.npz").lungs["right"].interior_map is not None
    prior = save_prior(tmp_path / "prior.json", MotionPrior(np.r_[[[0.0, -3.0, 1.0]], np.zeros((3, 3))], ("x", "y")))
    assert main(["fit", str(a), str(b), "--out", str(tmp_path / "prior"), "--motion-prior", str(prior), *common]) == 0
    plain, fitted = (load_model(tmp_path / k / "model.npz").lungs["right"] for k in ("plain", "prior"))
    w = taper_at(lm, fitted.surface)
    assert w.min() < 0.9 and w.max() > 0.5  # some landmarks in the taper, some deep: both are checked
    with np.load(tmp_path / "plain" / "landmarks.npz") as p0, np.load(tmp_path / "prior" / "landmarks.npz") as p1:
        np.testing.assert_allclose(p1["surface_only"] - p0["surface_only"], w[None, :, None] * [0.0, -3.0, 1.0],
                                   atol=1e-6)
    v = fitted.surface.vertices
    np.testing.assert_allclose(fitted.interior_map(v), plain.interior_map(v), atol=1e-9)
    capsys.readouterr()
    assert main(["fit", str(a), str(b), "--out", str(tmp_path / "o3"), "--motion-prior", str(prior),
                 "--interior", "sliding", *common]) == 2
    assert "--motion-prior needs the correspondence interior, not 'sliding'" in _one_error_line(capsys)
    (tmp_path / "bad.json").write_text("{")
    assert main(["fit", str(a), str(b), "--out", str(tmp_path / "o4"), "--motion-prior", str(tmp_path / "bad.json"),
                 *common]) == 2
    assert "bad.json: not a readable motion prior" in _one_error_line(capsys)
    assert not (tmp_path / "o3").exists() and not (tmp_path / "o4").exists()


@pytest.mark.parametrize("mode", ["description", "index"])
def test_one_4dct_folder_is_fitted_on_all_phases(tmp_path, rng, capsys, mode):
    # truth: a 4-D CT of 4 phases (tests/fourdct_phantom.py) whose lungs grow by 6 % per axis and phase,
    # written last phase first: the fit must segment every phase, measure volumes rising ~19-20 % a
    # phase (1.06^3), and fit the 3 larger phases as targets in volume order
    from tests.fourdct_phantom import write_4dct

    write_4dct(tmp_path / "ct4d", rng, 4, mode)
    out = tmp_path / "out"
    assert main(["fit", str(tmp_path / "ct4d"), "--out", str(out), "--side", "right", "--no-baselines",
                 "--evaluations", "20", "--direction-degree", "0", "--no-stiffness", "--align", "none"]) == 0
    text = capsys.readouterr().out
    assert "4-D CT of 4 phases; right lung by phase:" in text
    m = json.loads((out / "metrics.json").read_text())
    assert len(m["inputs"]) == 4 and all(str(tmp_path / "ct4d") in p for p in m["inputs"])
    ratios = np.diff(np.log(m["volumes_ml"]))
    assert np.allclose(ratios, 3 * np.log(1.06), atol=0.03)
    assert len(m["targets"]) == 3
    # the model records each fitted scan's series, in fit order (what `track --scan K --out-rtstruct`
    # checks its --reference-ct against): each phase's series and Frame of Reference, with
    # its phase's grid (this phantom's slices carry no Frame of Reference: recorded as ""); the
    # independent reader is pydicom on each phase's own files
    import pydicom
    scans = load_model(out / "model.npz").provenance["scans"]
    assert [s["source"] for s in scans] == m["inputs"]
    by_series = {}
    for f in sorted((tmp_path / "ct4d").rglob("*.dcm")):
        ds = pydicom.dcmread(f, stop_before_pixels=True)
        by_series[str(ds.SeriesInstanceUID)] = str(ds.get("FrameOfReferenceUID", ""))
    # ("index": one series holding the four phases)
    assert len(scans) == 4 and sorted({s["series_uid"] for s in scans}) == sorted(by_series)
    assert len(by_series) == (4 if mode == "description" else 1)
    assert all(s["frame_of_reference"] == by_series[s["series_uid"]] for s in scans)
    assert all(len(s["grid"]["size"]) == 3 and len(s["grid"]["direction"]) == 9 for s in scans)


def test_4dct_whose_phases_cannot_be_told_apart_exits_2(tmp_path, rng, capsys):
    # four series, same description, no temporal tags: one line naming the folder, no output written
    from tests.fourdct_phantom import write_4dct

    write_4dct(tmp_path / "ct4d", rng, 4, "same")
    out = tmp_path / "out"
    assert main(["fit", str(tmp_path / "ct4d"), "--out", str(out), "--side", "right"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(tmp_path / "ct4d") in err and "cannot be told apart" in err
    assert not (out / "model.npz").exists()


def test_a_bad_input_leaves_no_output_folder_and_out_may_not_be_an_input(tmp_path, pair, capsys):
    # why: fit created --out before it read its inputs, so a refused input left an empty folder;
    # and an --out whose model.npz / metrics.json is one of the inputs would overwrite it
    a, b, _ = pair
    out = tmp_path / "o"
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(out), "--volumes", "1500,1400"]) == 2
    assert "volumes must increase" in _one_error_line(capsys) and not out.exists()
    metrics = tmp_path / "metrics.json"
    metrics.write_text("{}")
    assert main(["fit", str(a), str(b), "--side", "right", "--out", str(tmp_path), "--landmarks", str(metrics),
                 "--landmarks", str(metrics)]) == 2
    assert "would overwrite the input" in _one_error_line(capsys) and metrics.read_text() == "{}"


def test_a_full_cycle_4dct_is_fitted_with_its_hysteresis(tmp_path, rng, capsys):
    # truth: a 5-phase cycle (tests/fourdct_phantom.py) of lung scales 1.0, 1.08, 1.16, 1.08, 1.0 by
    # phase, the 60 % lung moved 6 mm along z (one slice), every slice in one Frame of Reference.
    # Equal volumes are exact (the same voxels, shifted): 20 % and 60 % are two targets at one
    # volume, 80 % has the end-exhale volume (no target); the exhale phases 60 % and 80 % are paired
    # with the inhale phases of equal volume, 20 % (a 6 mm shift: every distance <= 6 mm, mean > 1)
    # and 0 % (the same lung: 0 mm); one Frame of Reference: no alignment fitted
    from tests.fourdct_phantom import write_cycle

    write_cycle(tmp_path / "ct4d", rng, [1.0, 1.08, 1.16, 1.08, 1.0], [0, 0, 0, 6.0, 0], frame_uid="1.2.826.0.1.9")
    out = tmp_path / "out"
    assert main(["fit", str(tmp_path / "ct4d"), "--out", str(out), "--side", "right", "--no-baselines",
                 "--evaluations", "20", "--direction-degree", "0", "--no-stiffness"]) == 0
    text = capsys.readouterr().out
    assert "alignment: none (every phase shares one DICOM Frame of Reference (1.2.826.0.1.9)" in text
    assert "hysteresis: exhale 60% " in text and "vs inhale 20% " in text
    m = json.loads((out / "metrics.json").read_text())
    assert [p.rsplit("[", 1)[1] for p in m["inputs"]] == ["0%]", "20%]", "60%]", "40%]"]
    assert m["volumes_ml"][1] == m["volumes_ml"][2] and len(m["targets"]) == 3
    assert m["alignment_choice"] == {"asked": "auto", "used": "none", "why": m["alignment_choice"]["why"]}
    assert all(a["method"] == "none" and a["applied"]["translation_mm"] == [0.0, 0.0, 0.0] for a in m["alignment"])
    pairs = {(p["exhale"], p["inhale"]): p for p in m["cycle"]["hysteresis"]}
    assert set(pairs) == {("60%", "20%"), ("80%", "0%")}
    assert pairs[("80%", "0%")]["max_mm"] == 0.0
    assert 1.0 < pairs[("60%", "20%")]["mean_mm"] and pairs[("60%", "20%")]["max_mm"] <= 6.0 + 1e-6
    assert any("80% has the end-exhale volume" in n for n in m["notes"])
    report = (out / "report.html").read_text(encoding="utf-8")
    assert "Alignment: <b>none</b>" in report and "<td>60%</td>" in report and "<h2>Hysteresis" in report
    # every target's error map in one figure, its distributions in another (a row, a panel per target):
    # six PNGs whatever the number of phases
    assert report.count("data:image/png;base64,") == 6 and "(one row per target)" in report


@pytest.mark.realdata
def test_popi_ten_phase_full_cycle_4dct_goes_through_fit(data_dir, tmp_path, capsys):
    # the README workflow on the POPI phase-00 CT: segment → build → warp --phases 10 over a 4 s,
    # 500 mL cosine breath (the CT downsampled 2 × 2 × 2 to 256 × 256 × 71, a 12 mm field lattice, to
    # keep this short) → fit on the 10-phase folder, inhale and exhale. Truth: phases count from
    # end-inhale (docs/RADIOTHERAPY.md), so 0 % is the largest (+500 mL) and 50 % the source scan at
    # end-exhale (+0 mL), the smallest; the warp is a function of volume only
    # (no hysteresis), so each exhale phase matches the inhale phase of similar volume within about a
    # voxel; every phase keeps POPI's Frame of Reference, so no alignment is fitted
    from tests.cli.test_warp import _curve
    from tests.popi_workflow import downsampled_series, extract_popi, popi_model

    popi = extract_popi(data_dir, tmp_path)
    model = popi_model(popi, tmp_path, 1500)
    head = downsampled_series(popi, tmp_path / "ct", (2, 2, 2))
    assert main(["warp", str(tmp_path / "ct"), str(model), "--curve", str(_curve(tmp_path / "c.csv")), "--phases",
                 "10", "--node-mm", "12", "--out", str(tmp_path / "4dct")]) == 0
    capsys.readouterr()
    out = tmp_path / "fit"
    assert main(["fit", str(tmp_path / "4dct"), "--side", "right", "--out", str(out), "--no-baselines",
                 "--no-stiffness", "--direction-degree", "0", "--evaluations", "40"]) == 0
    text = capsys.readouterr().out
    assert f"alignment: none (every phase shares one DICOM Frame of Reference ({head.FrameOfReferenceUID})" in text
    m = json.loads((out / "metrics.json").read_text())
    labels = [p.rsplit("[", 1)[1].rstrip("]") for p in m["inputs"]]
    assert labels[0] == "50%" and labels[-1] == "0%" and sorted(labels) == sorted(f"{10 * i}%" for i in range(10))
    assert np.all(np.diff(m["volumes_ml"]) >= 0)
    pairs = m["cycle"]["hysteresis"]
    assert [p["exhale"] for p in pairs] == ["10%", "20%", "30%", "40%"]
    assert all(p["mean_mm"] < 1.0 and p["p95_mm"] < 2.5 for p in pairs)
    assert sum(f"hysteresis: exhale {p['exhale']} " in text for p in pairs) == 4
    assert all(per["model"]["surface_mean_mm"] < 2.0 for per in m["targets"].values())


def test_series_with_one_4dct_folder_is_refused(tmp_path, capsys):
    # --series chooses among an input folder's CT series; one input is a 4-D CT whose series are its
    # phases: an option that would be ignored is refused, before any work
    (tmp_path / "4d").mkdir()
    assert main(["fit", str(tmp_path / "4d"), "--side", "right", "--out", str(tmp_path / "o"),
                 "--series-description", "phase 30%"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--series-description 'phase 30%': one input is a 4-D CT folder" in err[0]
    assert not (tmp_path / "o").exists()
