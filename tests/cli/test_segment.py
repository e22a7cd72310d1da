"""``lungdeform segment CT --out DIR``: masks, volumes.json, overlay.png; bad input exits 2."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk

from lungdeform.cli import main as cli_main
from lungdeform.io.image import read_image
from tests.conftest import require_path
from tests.segment.test_lungs import phantom
from tests.segment.test_split import two_lungs


@pytest.fixture
def run():
    """``main(argv)``: the real CLI, every command module loaded (a missing one must fail)."""
    return cli_main.main


def _write_ct(img, path):
    im = sitk.GetImageFromArray(np.asarray(img.array))
    im.SetSpacing(img.spacing.tolist())
    im.SetOrigin(img.origin.tolist())
    im.SetDirection(img.direction.ravel().tolist())
    sitk.WriteImage(im, str(path))
    return path


@pytest.mark.parametrize("fmt", ["nii.gz", "mha"])
def test_segment_writes_masks_volumes_overlay(tmp_path, rng, run, capsys, fmt):
    img, truth = phantom(rng, gap_mm=10.0)
    ct = _write_ct(img, tmp_path / "ct.mha")
    out = tmp_path / "out"
    assert run(["segment", str(ct), "--out", str(out), "--format", fmt]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"left_lung.{fmt}", f"right_lung.{fmt}", "overlay.png", "volumes.json"])
    left = read_image(out / f"left_lung.{fmt}")
    # truth: the phantom's analytic left lung, on the CT grid with the CT's geometry
    inter = np.count_nonzero(left.array.astype(bool) & truth["left"])
    assert 2 * inter / (left.array.astype(bool).sum() + truth["left"].sum()) > 0.97
    assert np.allclose(left.origin, img.origin) and np.allclose(left.spacing, img.spacing)
    report = json.loads((out / "volumes.json").read_text())
    vml = np.prod(img.spacing) / 1000
    assert report["volumes_ml"]["left"] == pytest.approx(left.array.astype(bool).sum() * vml)
    assert "Trachea seed" in report["airway_removal"]
    text = capsys.readouterr().out
    assert "left lung" in text and f"left_lung.{fmt}" in text


@pytest.mark.parametrize(
    "make, args, message",
    [
        (lambda p: p / "missing.nii.gz", [], "missing.nii.gz: no such file"),
        (lambda p: _write_ct(type("I", (), {"array": np.zeros((4, 8, 8), np.uint8), "spacing": np.ones(3),
                                            "origin": np.zeros(3), "direction": np.eye(3)})(), p / "mask.mha"),
         [], "mask.mha: minimum value 0"),
        (lambda p: p / "x.mha", ["--format", "png"], "--format must be one of"),
    ],
)
def test_bad_input_exits_2(tmp_path, run, capsys, make, args, message):
    ct = make(tmp_path)
    out = tmp_path / "out"
    assert run(["segment", str(ct), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and message in err
    assert not out.exists() or not any(out.iterdir())


def test_no_lungs_exits_2(tmp_path, run, capsys):
    arr = np.full((20, 40, 40), 40, np.int16)
    arr[:, :3] = -1000
    im = sitk.GetImageFromArray(arr)
    sitk.WriteImage(im, str(tmp_path / "abdomen.nii.gz"))
    assert run(["segment", str(tmp_path / "abdomen.nii.gz"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "abdomen.nii.gz" in err and "empty mask" in err


@pytest.mark.realdata
def test_popi_archive(data_dir, tmp_path, run, monkeypatch):
    ct = require_path(data_dir, "popi-ct-phase00", "popi_phase00_dicom_141slices.tar.gz")
    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the archive is extracted under tmp_path
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    out = tmp_path / "out"
    assert run(["segment", str(ct), "--out", str(out), "--downsample", "2"]) == 0
    report = json.loads((out / "volumes.json").read_text())
    v = report["volumes_ml"]
    assert v["right"] > v["left"] > 1800 and v["left"] + v["right"] == pytest.approx(5300, rel=0.05)
    assert (out / "overlay.png").stat().st_size > 10_000
    assert not any(p.name.startswith("lungdeform-ct-") for p in tmp_path.iterdir())


def test_segment_with_surfaces(tmp_path, rng, run):
    from lungdeform.geometry.mesh import signed_volume
    from lungdeform.io.meshfile import read_mesh

    img, _ = phantom(rng, gap_mm=10.0)
    ct = _write_ct(img, tmp_path / "ct.mha")
    out = tmp_path / "out"
    assert run(["segment", str(ct), "--out", str(out), "--surfaces", "--target-vertices", "2000"]) == 0
    report = json.loads((out / "volumes.json").read_text())
    for side in ("left", "right"):
        v, f = read_mesh(out / f"{side}_lung.stl")
        # truth: the enclosed volume of the surface matches the mask volume (marching cubes + Taubin)
        assert signed_volume(v, f) / 1000 == pytest.approx(report["volumes_ml"][side], rel=0.05)
        assert report["surfaces"][side]["vertices"] == len(np.unique(f))
    # LPS: the left lung surface lies at +x
    assert read_mesh(out / "left_lung.stl")[0][:, 0].mean() > 0 > read_mesh(out / "right_lung.stl")[0][:, 0].mean()


def _dicom_phantom(folder, rng):
    """The phantom CT as a DICOM series in ``folder`` (locale restored: GDCM's writer resets it)."""
    import locale

    from tests.segment.test_ct import _write_dicom_series

    saved = locale.setlocale(locale.LC_ALL)
    img, _ = phantom(rng, gap_mm=10.0)
    sp = img.spacing
    _write_dicom_series(folder, img.array, sp, [float(k * sp[2]) for k in range(img.array.shape[0])])
    locale.setlocale(locale.LC_ALL, saved)
    return folder


def test_dicom_series_from_its_folder_one_file_or_a_parent_folder(tmp_path, rng, run, capfd):
    # truth: the same series read three ways gives the same masks. Before, one .dcm file was an
    # "unknown image format", and a patient/study/series parent "no DICOM series" plus two ITK
    # WARNING blocks on stderr
    series = _dicom_phantom(tmp_path / "patient 1" / "study" / "series", rng)
    volumes = {}
    for name, path in {"folder": series, "file": series / "slice007.dcm", "parent": tmp_path / "patient 1"}.items():
        out = tmp_path / f"out-{name}"
        assert run(["segment", str(path), "--out", str(out)]) == 0, name
        volumes[name] = json.loads((out / "volumes.json").read_text())["volumes_ml"]
    assert volumes["file"] == volumes["folder"] == volumes["parent"]
    assert volumes["folder"]["left"] > 100 and volumes["folder"]["airway"] > 1
    assert "WARNING" not in capfd.readouterr().err


def test_dicom_ambiguous_or_missing_series_one_error_line(tmp_path, rng, run, capfd):
    # two series under one parent (e.g. two phases): refused naming both, never picked at random
    _dicom_phantom(tmp_path / "two" / "phase00", rng)
    _dicom_phantom(tmp_path / "two" / "phase50", rng)
    (tmp_path / "empty").mkdir()
    (tmp_path / "fake.dcm").write_text("not dicom")
    cases = {tmp_path / "two": ("holds 2 CT series (phase00: 1.2.826.0.1.3680043.2.1125.1.99 '' (50 CT image(s)); "
                                "phase50: 1.2.826.0.1.3680043.2.1125.1.99 '' (50 CT image(s))): which one is meant "
                                "cannot be told; choose one with --series UID or --series-description TEXT"),
             tmp_path / "empty": "no DICOM image series (found: nothing)",
             tmp_path / "fake.dcm": "not a readable DICOM image slice"}
    for path, message in cases.items():
        out = tmp_path / "out"
        assert run(["segment", str(path), "--out", str(out)]) == 2
        err = capfd.readouterr().err.strip().splitlines()  # capfd: ITK writes to fd 2 itself
        assert len(err) == 1 and err[0].startswith(f"error: {path}") and message in err[0], err
        assert not out.exists()


def test_binary_mask_of_both_lungs_gives_left_and_right(tmp_path, run, capsys):
    # truth: a binary mask of two touching ellipsoids (tests/segment/test_split.py) is split, not
    # segmented as a CT: left_lung holds the +x ellipsoid, right_lung the other, volumes said
    image, left, right = two_lungs()
    path = tmp_path / "both.nii.gz"
    _write_ct(image, path)
    out = tmp_path / "o"
    assert run(["segment", str(path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "a mask holding both lungs in one label" in text and "no airway removal" in text
    for side, truth in (("left", left), ("right", right)):
        got = sitk.GetArrayFromImage(sitk.ReadImage(str(out / f"{side}_lung.nii.gz"))) > 0
        assert (got & truth).sum() / truth.sum() > 0.99 and abs(int(got.sum()) - int(truth.sum())) < 0.03 * truth.sum()
    report = json.loads((out / "volumes.json").read_text())
    assert report["details"]["split"]["touching"] is True


def test_a_failure_at_the_last_output_writes_nothing(tmp_path, run, capsys, monkeypatch):
    # issue 36: outputs were written one by one, so a failure at volumes.json (the last) left the
    # masks and the overlay. Truth: staged, they appear together or not at all: no --out folder
    from lungdeform.cli import segment as cli_segment

    image, _left, _right = two_lungs()
    _write_ct(image, tmp_path / "both.nii.gz")

    def failing(path, data):
        raise OSError(28, "No space left on device (simulated)", str(path))

    monkeypatch.setattr(cli_segment, "write_bytes", failing)
    assert run(["segment", str(tmp_path / "both.nii.gz"), "--out", str(tmp_path / "o")]) != 0
    assert not (tmp_path / "o").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
