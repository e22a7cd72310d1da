"""``lungdeform build``: files in, model out; bad input exits 2 with one line and no output."""

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.cli.main import main
from lungdeform.geometry.mesh import icosphere
from lungdeform.io.meshfile import write_mesh
from lungdeform.io.modelfile import load_model
from tests.conftest import ellipsoid_lung
from tests.segment.test_split import two_lungs


@pytest.fixture
def lung_files(tmp_path):
    paths = []
    for side in ("left", "right"):
        s = ellipsoid_lung(side)
        paths.append(write_mesh(tmp_path / f"lung_{side}.stl", s.vertices, s.faces))
    return paths


def test_build_two_lungs_guesses_sides(tmp_path, lung_files, capsys):
    out = tmp_path / "model.npz"
    assert main(["build", *map(str, lung_files), "--out", str(out)]) == 0
    m = load_model(out)
    assert sorted(m.names) == ["left", "right"]
    # the left lung is the one at +x (LPS): the side was guessed from position
    assert m.lungs["left"].surface.vertices[:, 0].mean() > 0
    # both lungs together are calibrated at the 500 mL tidal volume
    assert sum(l.calibration_ml for l in m.lungs.values()) == pytest.approx(500.0)
    out_text = capsys.readouterr().out
    assert "model written to" in out_text and "one lung" not in out_text


def test_build_options(tmp_path, lung_files):
    out = tmp_path / "m.npz"
    code = main(["build", str(lung_files[0]), "--side", "left", "--out", str(out),
                 "--orientation", "upright", "--stiffness", "gradient:0.5,1.5", "--tidal-ml", "300"])
    assert code == 0
    lung = load_model(out).lungs["left"]
    assert np.allclose(lung.gravity, [0, 0, -1])
    assert lung.stiffness.min() == pytest.approx(0.5) and lung.stiffness.max() == pytest.approx(1.5)
    # a lone left lung: its side's usual share (46.4 %) of the both-lung 300 mL
    assert lung.calibration_ml == pytest.approx(0.464 * 300.0)


def _fails(args, capsys, *needles):
    code = main(args)
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    for n in needles:
        assert n in err
    return err


def test_bad_inputs_exit_2_with_one_line(tmp_path, capsys):
    out = tmp_path / "m.npz"
    missing = tmp_path / "nope.stl"
    _fails(["build", str(missing), "--side", "left", "--out", str(out)], capsys, "nope.stl")
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    _fails(["build", str(empty), "--side", "left", "--out", str(out)], capsys, "empty.stl")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"\x00\x01garbage" * 10)
    _fails(["build", str(junk), "--side", "left", "--out", str(out)], capsys, "junk.ply")
    s = ellipsoid_lung("left")
    v = s.vertices.copy()
    v[5] = np.nan
    nan = write_mesh(tmp_path / "nan.obj", v, s.faces)
    _fails(["build", str(nan), "--side", "left", "--out", str(out)], capsys, "nan.obj", "NaN")
    opened = write_mesh(tmp_path / "open.ply", s.vertices, s.faces[1:])
    _fails(["build", str(opened), "--side", "left", "--out", str(out)], capsys, "open.ply", "open")
    metres = write_mesh(tmp_path / "metres.stl", s.vertices / 1000, s.faces)
    _fails(["build", str(metres), "--side", "left", "--out", str(out)], capsys, "metres.stl", "--units")
    _fails(["build", str(metres), "--out", str(out)], capsys)  # no side for a single surface
    assert not out.exists() and not list(tmp_path.glob(".m.npz*"))  # no partial output


@pytest.mark.parametrize("repair", [[], ["--repair"]])
def test_absurd_coordinate_and_self_intersection_exit_2(tmp_path, capsys, repair):
    # A vertex at 1e30 mm is named (not 1280 "degenerate" faces, not a traceback under --repair); a
    # sphere whose cap is pushed through its lower wall is refused as self-intersecting, not
    # "inward" (and not flipped into a small model by --repair).
    out = tmp_path / "m.npz"
    s = icosphere(3, 60.0)
    v = s.vertices.copy()
    v[5] = [1e30, 0.0, 0.0]
    far = write_mesh(tmp_path / "far.stl", v, s.faces)
    _fails(["build", str(far), "--side", "right", "--out", str(out), *repair], capsys, "far.stl", "1e+30")
    v = s.vertices.copy()
    cap = v[:, 2] > 40
    v[cap, 2] = -60.0 - v[cap, 2]
    through = write_mesh(tmp_path / "through.ply", v, s.faces)
    _fails(["build", str(through), "--side", "right", "--out", str(out), *repair], capsys, "through.ply",
           "intersects itself")
    assert not out.exists() and not list(tmp_path.glob(".m.npz*"))  # no partial output


def test_units_option_rescales(tmp_path):
    s = ellipsoid_lung("left")
    metres = write_mesh(tmp_path / "metres.stl", s.vertices / 1000, s.faces)
    out = tmp_path / "m.npz"
    assert main(["build", str(metres), "--side", "left", "--units", "m", "--out", str(out)]) == 0
    assert load_model(out).lungs["left"].volume_ee_ml == pytest.approx(s.volume_ml, rel=1e-5)


def test_a_lung_too_small_for_its_breath_is_refused(tmp_path, capsys):
    # why: a lung written in centimetres (45 × 70 × 110 mm semi-axes read as 4.5 × 7 × 11 "mm": 22 "mm"
    # across, inside the 20–2000 mm size check) encloses 1.4 mL; its share of a 500 mL breath, 232 mL,
    # is over 150 times its volume, past the 3 times no lung exceeds, and it used to build without a word (a
    # model whose every state dvf, warp and track refuse). Exit 2, one line naming the file, no output;
    # the same file with --units cm builds, the lung's volume 1000 times larger (the truth: mm³ = cm³/1000)
    s = ellipsoid_lung("left")
    cm = write_mesh(tmp_path / "cm.stl", s.vertices / 10, s.faces)
    out = tmp_path / "m.npz"
    err = _fails(["build", str(cm), "--side", "left", "--out", str(out)], capsys, "cm.stl", "past 3 times")
    assert f"encloses {s.volume_ml / 1000:.4g} mL" in err
    assert not out.exists() and not list(tmp_path.glob(".m.npz*"))
    assert main(["build", str(cm), "--side", "left", "--units", "cm", "--out", str(out)]) == 0
    assert load_model(out).lungs["left"].volume_ee_ml == pytest.approx(s.volume_ml, rel=1e-5)


def test_truncated_mesh_and_empty_mask_exit_2(tmp_path, capsys):
    import SimpleITK as sitk

    out = tmp_path / "m.npz"
    s = ellipsoid_lung("left")
    good = write_mesh(tmp_path / "lung.stl", s.vertices, s.faces)
    cut = tmp_path / "cut.stl"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])  # binary STL cut in half
    _fails(["build", str(cut), "--side", "left", "--out", str(out)], capsys, "cut.stl")
    img = sitk.Image(20, 20, 20, sitk.sitkUInt8)  # all zero: no foreground
    img.SetSpacing((2.0, 2.0, 2.0))
    empty = tmp_path / "empty_mask.mha"
    sitk.WriteImage(img, str(empty))
    _fails(["build", str(empty), "--side", "left", "--out", str(out)], capsys, "empty_mask.mha", "foreground")
    assert not out.exists()


def test_swapped_sides_refused(tmp_path, lung_files, capsys):
    # truth: lung_files[0] is the left lung (at +x, LPS). Telling build the opposite, or naming the
    # groups of a label map the wrong way round, used to build a model with swapped sides
    out = tmp_path / "m.npz"
    err = _fails(["build", *map(str, lung_files), "--side", "right", "--side", "left", "--out", str(out)], capsys,
                 "the surface taken as left (lung_right", "sides or labels swapped, or the meshes are in RAS")
    assert "mean x -" in err
    assert not out.exists()
    # a lobe map with its groups swapped: labels 3–5 (right lobes) called "left"
    import SimpleITK as sitk

    k, j, i = np.mgrid[:24, :20, :40]
    lab = np.zeros((24, 20, 40), np.uint8)
    for lobe, xc in ((1, 29.5), (3, 9.5)):  # index x grows to patient left (identity direction)
        lab[((k - 11.5) / 9) ** 2 + ((j - 9.5) / 7) ** 2 + ((i - xc) / 7) ** 2 <= 1] = lobe
    img = sitk.GetImageFromArray(lab)
    img.SetSpacing((8.0, 8.0, 8.0))  # lungs of about 1 L each: a lung of 2 mL cannot breathe 500 mL
    sitk.WriteImage(img, str(tmp_path / "lobes.nii.gz"))
    _fails(["build", str(tmp_path / "lobes.nii.gz"), "--labels", "left=3;right=1", "--out", str(out)], capsys,
           "the surface taken as left (lobes-left")
    assert main(["build", str(tmp_path / "lobes.nii.gz"), "--labels", "left=1;right=3", "--out", str(out)]) == 0


@pytest.mark.parametrize("args, message", [
    (["--solver", "gauss"], "--solver must be one of bicgstab, gmres, direct, got 'gauss'"),
    (["--d-min", "0"], "--d-min must be a finite number in (0, 100] mm, got 0"),
    (["--target-vertices", "50"], "--target-vertices must be at least 100, got 50"),
])
def test_options_named_in_errors(tmp_path, lung_files, capsys, args, message):
    _fails(["build", str(lung_files[0]), "--side", "left", "--out", str(tmp_path / "m.npz"), *args], capsys, message)


def test_build_one_lung_takes_its_side_from_its_shape(tmp_path, capsys):
    # truth: the embedded right lung (from CT) written without a side in its name is built as the
    # right lung (its concave medial face lies toward +x); told it is the left, build refuses
    from lungdeform.data import default_lungs

    s = default_lungs()["right"]
    # placed 300 mm toward patient left (where a left lung lies): the shape, not the position, decides
    path = write_mesh(tmp_path / "lung.ply", s.vertices + np.array([300.0, 0.0, 0.0]), s.faces)
    assert main(["build", str(path), "--out", str(tmp_path / "m.npz")]) == 0
    assert load_model(tmp_path / "m.npz").names == ["right"]
    capsys.readouterr()
    assert main(["build", str(path), "--side", "left", "--out", str(tmp_path / "bad.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shape says right, not left" in err[0] and not (tmp_path / "bad.npz").exists()
    # a user who knows better skips the check
    assert main(["build", str(path), "--side", "left", "--no-side-check", "--out", str(tmp_path / "ok.npz")]) == 0
    assert load_model(tmp_path / "ok.npz").names == ["left"]


def test_build_refuses_sides_it_cannot_tell(tmp_path, capsys):
    # an unnamed convex lung has no medial face to read, and three unnamed surfaces cannot be
    # paired by position: both ask for --side, with one line and no output
    e = ellipsoid_lung("left")
    one = write_mesh(tmp_path / "blob.stl", e.vertices, e.faces)
    assert main(["build", str(one), "--out", str(tmp_path / "a.npz")]) == 2
    assert "cannot tell the side of" in capsys.readouterr().err
    three = [write_mesh(tmp_path / f"b{i}.stl", e.vertices + 200.0 * i, e.faces) for i in range(3)]
    assert main(["build", *map(str, three), "--out", str(tmp_path / "b.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot tell the sides of 3 surfaces" in err[0]
    assert not (tmp_path / "a.npz").exists() and not (tmp_path / "b.npz").exists()


def _mask_file(path, a, spacing=(4.0, 4.0, 4.0)):
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(a.astype(np.uint8))
    img.SetSpacing(spacing)
    sitk.WriteImage(img, str(path))
    return path


def test_build_warns_when_the_mask_fills_the_image(tmp_path, capsys):
    # a mask that is the whole image (touching all six faces) used to build without a word; the
    # lung is cut by the border, so build still works but says so on stderr, naming the file
    a = np.ones((20, 25, 15), np.uint8)  # 60 x 100 x 80 mm: lung-sized
    path = _mask_file(tmp_path / "full.nii.gz", a)
    out = tmp_path / "m.npz"
    assert main(["build", str(path), "--side", "right", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"warning: {path}: the mask touches the image border on faces i-low, i-high, j-low" in err
    assert "the lung may be cropped" in err and out.exists()


def test_build_refuses_two_equal_blobs(tmp_path, capsys):
    # two equal 12-voxel cubes of 4 mm (110.6 mL each), one above the other (not a left and a right
    # lung, which the split would take apart): one used to be dropped silently
    a = np.zeros((34, 16, 16), np.uint8)  # numpy (z, y, x): stacked head to foot
    a[2:14, 2:14, 2:14] = 1
    a[20:32, 2:14, 2:14] = 1
    path = _mask_file(tmp_path / "pair.nii.gz", a)
    out = tmp_path / "m.npz"
    _fails(["build", str(path), "--side", "right", "--out", str(out)], capsys,
           "pair.nii.gz", "kept 111 mL; would drop 111 mL", "two lungs in one label?", "--labels")
    assert not out.exists() and list(tmp_path.iterdir()) == [path]  # nothing half-written


def _write_mask(image, path):
    im = sitk.GetImageFromArray(np.asarray(image.array))
    im.SetSpacing(image.spacing.tolist())
    im.SetOrigin(image.origin.tolist())
    sitk.WriteImage(im, str(path))
    return path


def test_build_mask_holding_both_lungs(tmp_path, capsys):
    # truth: the mask holds two touching ellipsoids in one label (tests/segment/test_split.py);
    # --side left takes the left one (at +x, the smaller) of the split, not the fused component,
    # and says so; without --side the mask gives both lungs
    image, left, right = two_lungs()
    path = _write_mask(image, tmp_path / "both.nii.gz")
    voxel_ml = float(np.prod(image.spacing)) / 1000
    assert main(["build", str(path), "--side", "left", "--target-vertices", "1500",
                 "--out", str(tmp_path / "left.npz")]) == 0
    out = capsys.readouterr().out
    assert "a mask holding both lungs in one label" in out and "took the left lung" in out
    model = load_model(tmp_path / "left.npz")
    assert model.names == ["left"]
    assert model.lungs["left"].volume_ee_ml == pytest.approx(left.sum() * voxel_ml, rel=0.05)
    assert main(["build", str(path), "--target-vertices", "1500", "--out", str(tmp_path / "both.npz")]) == 0
    assert sorted(load_model(tmp_path / "both.npz").names) == ["left", "right"]


def test_stl_that_welds_into_a_pinch_exits_2_with_one_line(tmp_path, capsys):
    # an STL from another program whose float32 corners weld two vertices into one: refused, one line
    from tests.geometry.test_remesh import touching_poles
    from tests.io.test_meshfile import write_soup_stl

    v, f = touching_poles()
    stl = write_soup_stl(tmp_path / "welded.stl", v[f])
    out = tmp_path / "m.npz"
    _fails(["build", str(stl), "--side", "left", "--out", str(out)], capsys, "welded.stl", "not 2-manifold")
    assert not out.exists()


def test_one_lung_takes_its_share_and_says_so(tmp_path, lung_files, capsys):
    # a lone lung does not breathe the whole (both-lung) tidal volume: the right lung takes 53.6 % of
    # 500 mL, recorded as its calibration, played as 53.6 % of a both-lung breath, and said in one line
    from lungdeform.playback.schedule import lung_shares
    from lungdeform.playback.trajectory import lung_scales

    out = tmp_path / "m.npz"
    assert main(["build", str(lung_files[1]), "--side", "right", "--out", str(out)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "one lung" in ln]
    assert lines == [("right: one lung: its share 53.6% of --tidal-ml 500 mL = 268 mL "
                      "(Yamada et al., Respiration 2020;99:598, supine CT volumes; docs/DEFAULTS.md)")]
    m = load_model(out)
    lung = m.lungs["right"]
    assert lung.calibration_ml == pytest.approx(268.0)
    assert lung_shares(m) == pytest.approx({"right": 0.536})
    # truth, measured on the mesh: at the peak of a 500 mL breath the lung holds V_EE + 268 mL
    (scale,) = lung_scales(m, [500.0])["right"]
    assert lung.surface_at(scale=scale).volume_ml == pytest.approx(lung.volume_ee_ml + 268.0, abs=1e-6)


def test_build_records_the_scans_breathing_state(tmp_path, lung_files, capsys):
    # why: a planning CT at end-inhale is said to be one; the model file keeps it (an end-inhale
    # scan 500 mL above end-exhale at the default --tidal-ml), build says both volumes, and a state
    # that is none of the accepted ones is refused before any surface is read, naming the option
    out = tmp_path / "m.npz"
    assert main(["build", *map(str, lung_files), "--scan-state", "end-inhale", "--out", str(out)]) == 0
    m = load_model(out)
    assert (m.scan.name, m.scan.above_ee_ml) == ("end-inhale", 500.0)
    scan = sum(lung.volume_ee_ml for lung in m.lungs.values())
    text = capsys.readouterr().out
    assert (f"scan: end-inhale, 500 mL above end-exhale: the lungs together {scan:.0f} mL at the scan, "
            f"{scan - 500:.0f} mL at end-exhale") in text
    assert main(["build", *map(str, lung_files), "--scan-state", "0.4", "--tidal-ml", "600", "--out", str(out)]) == 0
    assert load_model(out).scan.above_ee_ml == pytest.approx(240.0)
    _fails(["build", str(tmp_path / "missing.stl"), "--scan-state", "inhaled", "--out", str(tmp_path / "x.npz")],
           capsys, "--scan-state must be end-exhale, end-inhale, mid")
