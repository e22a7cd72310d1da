"""The radiotherapy workflow fed inputs that do not belong together or are damaged (docs/RADIOTHERAPY.md):
each command must stop with exit 2 and one line naming the file and the cause, and write nothing.
A wrong answer is worse than a crash: a structure of another patient or frame, a CT with a missing
or repeated slice, NaN voxels, a mask off the image's grid."""

from __future__ import annotations

import shutil

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
import trimesh

from lungdeform.cli.main import main
from lungdeform.io.dicom.rtstruct import read_ct_series, write_rtstruct
from lungdeform.io.modelfile import save_model
from tests.browser.support import two_lungs
from tests.io.dicom_support import write_ct_series

GTV = np.array([90.0, 0.0, -40.0])  # inside the left lung of two_lungs(2)
ORIGIN = tuple(GTV + [-31.0, -31.0, -19.0])  # a 32 x 32 x 20 CT of 2 mm voxels around it


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A model, a CT series around the GTV, the GTV drawn on it, and the model's volume + 300 mL."""
    d = tmp_path_factory.mktemp("base")
    m = two_lungs(2)
    save_model(d / "m.npz", m)
    ct = write_ct_series(d / "ct", origin=ORIGIN)
    s = trimesh.creation.icosphere(3, radius=8.0)
    write_rtstruct(d / "gtv.dcm", read_ct_series(ct), [("GTV", s.vertices + GTV, s.faces, "GTV")])
    return {"dir": d, "volume": f"{sum(lung.volume_ee_ml for lung in m.lungs.values()) + 300:.1f}"}


def _refused(args, capsys, message, outputs):
    code = main([str(a) for a in args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], (code, err)
    assert not [o for o in outputs if o.exists()]


def _edit(src, dst, **tags):
    ds = pydicom.dcmread(src)
    for key, value in tags.items():
        setattr(ds, key, value)
    ds.save_as(dst)
    return dst


def _gtv_on(folder, path):
    s = trimesh.creation.icosphere(3, radius=8.0)
    write_rtstruct(path, read_ct_series(folder), [("GTV", s.vertices + GTV, s.faces, "GTV")])
    return path


@pytest.mark.parametrize("command", ["track", "dvf", "warp"])
@pytest.mark.parametrize("case", ["patient", "frame", "other series"])
def test_a_structure_that_is_not_drawn_on_the_ct_is_refused(base, tmp_path, capsys, command, case):
    # the structure (track --out-rtstruct; dvf and warp --rigid-structure, which took any RTSTRUCT
    # unchecked: a GTV of another patient or frame was held rigid wherever its numbers fell) must be of
    # the CT's patient and Frame of Reference, and where it references slices of this series, all of them
    d, ct = base["dir"], base["dir"] / "ct"
    if case == "patient":
        rs, message = _edit(d / "gtv.dcm", tmp_path / "rs.dcm", PatientID="SOMEONE-ELSE"), "not the same patient"
    elif case == "frame":
        other = write_ct_series(tmp_path / "other", origin=ORIGIN, uid_root="1.2.3.99")
        rs, message = _gtv_on(other, tmp_path / "rs.dcm"), "is in Frame of Reference 1.2.3.99.3"
    else:  # one contour on a slice of another series, the others on this one's
        ds = pydicom.dcmread(d / "gtv.dcm")
        ds.ROIContourSequence[0].ContourSequence[2].ContourImageSequence[0].ReferencedSOPInstanceUID = "1.2.3.4.5"
        rs, message = tmp_path / "rs.dcm", "is drawn on 1 slice(s) that"
        ds.save_as(rs)
    out = tmp_path / "out"
    if command == "track":
        args = ["track", d / "m.npz", "--rtstruct", rs, "--structure", "GTV", "--volume-ml", base["volume"],
                "--out", out, "--out-rtstruct", tmp_path / "moved.dcm", "--reference-ct", ct]
    elif command == "dvf":
        args = ["dvf", d / "m.npz", "--reference", ct, "--volume-ml", base["volume"], "--node-mm", "12",
                "--rigid-structure", "GTV", "--rtstruct", rs, "--out", tmp_path / "f.mha"]
    else:
        args = ["warp", ct, d / "m.npz", "--volume-ml", base["volume"], "--node-mm", "12",
                "--rigid-structure", "GTV", "--rtstruct", rs, "--out", out]
    _refused(args, capsys, message, [out, tmp_path / "moved.dcm", tmp_path / "f.mha"])


def _damage(ct, folder, kind):
    """A copy of the series ``ct`` with a slice missing, two slices at one position, or uneven gaps."""
    shutil.copytree(ct, folder)
    if kind == "missing":
        (folder / "slice010.dcm").unlink()
        return folder, "slice(s) missing"
    for k in range(10, 20) if kind == "uneven" else [10]:
        ds = pydicom.dcmread(folder / f"slice{k:03d}.dcm")
        x, y, z = (float(v) for v in ds.ImagePositionPatient)
        ds.ImagePositionPatient = [x, y, z + 0.7] if kind == "uneven" else [x, y, z - 2.0]
        ds.save_as(folder / f"slice{k:03d}.dcm")
    return folder, "uneven slice spacing" if kind == "uneven" else "two slices at"


@pytest.mark.parametrize("command", ["segment", "warp", "dvf", "track"])
@pytest.mark.parametrize("kind", ["missing", "duplicate", "uneven"])
def test_a_ct_series_that_is_no_regular_grid_is_refused_by_every_command(base, tmp_path, capsys, command, kind):
    # every command that reads the CT (segmenting it, warping it, registering on it, writing contours
    # on its slices) refuses it with the same words (one check, io.dicom.slices.check_gaps) before any output
    d = base["dir"]
    ct, message = _damage(d / "ct", tmp_path / "ct", kind)
    out, reg, rs = tmp_path / "out", tmp_path / "reg.dcm", tmp_path / "moved.dcm"
    args = {"segment": ["segment", ct, "--out", out],
            "warp": ["warp", ct, d / "m.npz", "--volume-ml", base["volume"], "--node-mm", "12", "--out", out],
            "dvf": ["dvf", d / "m.npz", "--reference", ct, "--volume-ml", base["volume"], "--node-mm", "12",
                    "--out", tmp_path / "f.mha", "--out-reg", reg],
            "track": ["track", d / "m.npz", "--rtstruct", d / "gtv.dcm", "--structure", "GTV", "--volume-ml",
                      base["volume"], "--out", out, "--out-rtstruct", rs, "--reference-ct", ct]}[command]
    _refused(args, capsys, message, [out, reg, rs, tmp_path / "f.mha"])


@pytest.mark.parametrize("command", ["segment", "warp", "build", "fit", "dvf"])
def test_nan_or_inf_voxels_in_a_nifti_are_refused(base, tmp_path, capsys, command):
    # ITK reads NaN and inf NIfTI voxels as 0: segment, warp and build went on (exit 0) with a CT
    # whose NaN region had become 0 HU, or a mask with a hole; now the file is refused, naming the voxel
    d = base["dir"]
    a = np.full((20, 32, 32), -800.0, np.float32)
    a[5, 6, 7] = np.nan
    a[6, 6, 7] = np.inf
    image = sitk.GetImageFromArray(a)
    image.SetOrigin(ORIGIN)
    image.SetSpacing((2.0, 2.0, 2.0))
    sitk.WriteImage(image, str(tmp_path / "bad.nii.gz"))
    out = tmp_path / "out"
    args = {"segment": ["segment", tmp_path / "bad.nii.gz", "--out", out],
            "warp": ["warp", tmp_path / "bad.nii.gz", d / "m.npz", "--volume-ml", base["volume"], "--out", tmp_path / "w.mha"],
            "build": ["build", tmp_path / "bad.nii.gz", "--side", "left", "--out", tmp_path / "b.npz"],
            "fit": ["fit", tmp_path / "bad.nii.gz", tmp_path / "bad.nii.gz", "--side", "left", "--out", out],
            "dvf": ["dvf", d / "m.npz", "--reference", tmp_path / "bad.nii.gz", "--volume-ml", base["volume"],
                    "--out", tmp_path / "f.mha"]}[command]
    _refused(args, capsys, "bad.nii.gz: voxel (x, y, z) (7, 6, 5) is nan in the file",
             [out, tmp_path / "w.mha", tmp_path / "b.npz", tmp_path / "f.mha"])


@pytest.mark.parametrize("command", ["warp", "dvf"])
def test_a_rigid_mask_off_the_ct_is_refused(base, tmp_path, capsys, command):
    # a mask of another geometry is taken on the CT's grid by nearest neighbour (the same LPS world);
    # one that lies beyond the CT (another scan's frame) covers no voxel of it: refused, not a no-op
    d = base["dir"]
    mask = sitk.GetImageFromArray(np.ones((10, 16, 16), np.uint8))
    mask.SetOrigin(tuple(np.array(ORIGIN) + [0.0, 0.0, 300.0]))
    mask.SetSpacing((4.0, 4.0, 4.0))
    sitk.WriteImage(mask, str(tmp_path / "mask.nii.gz"))
    out = tmp_path / ("w" if command == "warp" else "f.mha")
    args = (["warp", d / "ct", d / "m.npz"] if command == "warp" else ["dvf", d / "m.npz", "--reference", d / "ct"])
    _refused(args + ["--volume-ml", base["volume"], "--node-mm", "12", "--rigid-mask", tmp_path / "mask.nii.gz",
                     "--out", out], capsys, "mask.nii.gz: covers 0 voxel(s) of the grid", [out])
