"""CT input and grid geometry (lungdeform.segment.ct): DICOM archives, uneven slices, non-CT input, writing
masks, downsampling."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError, ReadError
from lungdeform.io.grid import Image
from lungdeform.io.image import read_image
from lungdeform.segment import ct as C
from lungdeform.segment import lungs as S
from tests.segment.test_lungs import phantom


def _write_dicom_series(folder, array, spacing, z_positions):
    import SimpleITK as sitk

    folder.mkdir(parents=True, exist_ok=True)
    w = sitk.ImageFileWriter()
    w.KeepOriginalImageUIDOn()
    series = "1.2.826.0.1.3680043.2.1125.1.99"
    for n, (sl, z) in enumerate(zip(array, z_positions)):
        im = sitk.GetImageFromArray(sl.astype(np.int16)[None])
        im.SetSpacing([float(spacing[0]), float(spacing[1]), 1.0])
        for tag, value in {
            "0008|0060": "CT", "0020|000e": series, "0020|000d": series + ".0", "0008|0018": f"{series}.{n + 1}",
            "0020|0013": str(n + 1), "0020|0032": f"-50\\-50\\{z}", "0020|0037": "1\\0\\0\\0\\1\\0",
            "0028|0030": f"{spacing[1]}\\{spacing[0]}", "0018|0050": str(spacing[2]),
        }.items():
            im.SetMetaData(tag, value)
        w.SetFileName(str(folder / f"slice{n:03d}.dcm"))
        w.Execute(im)


def test_dicom_archive_roundtrip_and_uneven_slices(tmp_path, rng):
    import tarfile

    arr = rng.integers(-1000, 100, size=(8, 16, 16)).astype(np.int16)
    _write_dicom_series(tmp_path / "ok" / "series", arr, (1.5, 1.5, 2.0), [2.0 * k for k in range(8)])
    with tarfile.open(tmp_path / "ct.tar.gz", "w:gz") as tf:
        tf.add(tmp_path / "ok", arcname="ok")
    img = C.read_ct(tmp_path / "ct.tar.gz", workdir=tmp_path)
    # truth: what we wrote (values, slice gap 2 mm, in-plane 1.5 mm, origin from ImagePositionPatient)
    assert np.array_equal(img.array, arr)
    assert np.allclose(img.spacing, [1.5, 1.5, 2.0])
    assert np.allclose(img.origin, [-50, -50, 0])
    assert img.source.endswith("ct.tar.gz")
    assert not any(p.name.startswith("lungdeform-ct-") for p in tmp_path.iterdir())  # cleaned up
    # a missing slice: gaps 2 and 4 mm → refused (by the one slice check, lungdeform.io.dicom.slices),
    # naming the folder, the cause and the files
    zs = [0, 2, 4, 8, 10, 12, 14, 16]
    _write_dicom_series(tmp_path / "gap", arr, (1.5, 1.5, 2.0), zs)
    with pytest.raises(ReadError, match=r"gap: 1 slice\(s\) missing: .*slice002\.dcm at 4\.000 mm and slice003\.dcm"):
        C.read_ct(tmp_path / "gap")


def test_folder_holding_one_archive(tmp_path, rng):
    # a dataset folder as downloaded (no DICOM file, one archive in it) is read through its archive,
    # and the image names the archive; two archives are refused, naming them
    import tarfile

    arr = rng.integers(-1000, 100, size=(6, 12, 12)).astype(np.int16)
    series = tmp_path / "series"
    _write_dicom_series(series, arr, (1.5, 1.5, 2.0), [2.0 * k for k in range(6)])
    folder = tmp_path / "dataset"
    folder.mkdir()
    with tarfile.open(folder / "ct.tar.gz", "w:gz") as tf:
        tf.add(series, arcname="series")
    img = C.read_ct(folder, workdir=tmp_path)
    assert img.source.endswith("ct.tar.gz") and np.array_equal(img.array, arr)
    (folder / "._ct.tar.gz").write_bytes(b"macOS resource fork")  # hidden files do not count
    assert C.read_ct(folder, workdir=tmp_path).source.endswith("ct.tar.gz")
    with tarfile.open(folder / "other.tar.gz", "w:gz") as tf:
        tf.add(series, arcname="series")
    with pytest.raises(ReadError, match="2 archives.*ct.tar.gz"):
        C.read_ct(folder, workdir=tmp_path)
    # a folder with anything else beside the archive is not a downloaded dataset: read as it is
    (folder / "other.tar.gz").unlink()
    (folder / "notes.txt").write_text("x")
    assert C.archive_in(folder) == folder


def test_archive_of_one_image_file_and_errors_name_the_archive(tmp_path, rng):
    # an archive holding one NIfTI is read (truth: the array written); an archive with neither a
    # DICOM series nor an image is refused in one line naming the archive, not a temporary folder
    import tarfile

    import SimpleITK as sitk

    arr = rng.integers(-1000, 100, size=(5, 9, 11)).astype(np.int16)
    (tmp_path / "in").mkdir()
    sitk.WriteImage(sitk.GetImageFromArray(arr), str(tmp_path / "in" / "ct.nii.gz"))
    with tarfile.open(tmp_path / "nii.tar.gz", "w:gz") as tf:
        tf.add(tmp_path / "in" / "ct.nii.gz", arcname="x/ct.nii.gz")
    assert np.array_equal(C.read_ct(tmp_path / "nii.tar.gz", workdir=tmp_path).array, arr)
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "readme.txt").write_text("no image")
    with tarfile.open(tmp_path / "junk.tar.gz", "w:gz") as tf:
        tf.add(tmp_path / "junk", arcname="junk")
    with pytest.raises(ReadError) as err:
        C.read_ct(tmp_path / "junk.tar.gz", workdir=tmp_path)
    msg = str(err.value)
    assert msg.startswith(str(tmp_path / "junk.tar.gz")) and "lungdeform-ct-" not in msg and "\n" not in msg


def test_bad_archive_and_mask_input(tmp_path):
    bad = tmp_path / "broken.tar.gz"
    bad.write_bytes(b"not a tar file")
    with pytest.raises(ReadError, match="broken.tar.gz"):
        C.read_ct(bad)
    import SimpleITK as sitk

    m = sitk.GetImageFromArray(np.zeros((4, 8, 8), np.uint8))
    sitk.WriteImage(m, str(tmp_path / "mask.mha"))
    with pytest.raises(InputError, match="mask.mha.*minimum value 0"):
        C.read_ct(tmp_path / "mask.mha")


def test_mask_written_with_ct_geometry(tmp_path, rng):
    img, _ = phantom(rng, gap_mm=10.0, flip_x=True)
    seg = S.segment_lungs(img)
    for suffix in ("nii.gz", "mha"):
        path = C.write_mask(seg.mask_image("left"), tmp_path / f"left.{suffix}")
        back = read_image(path)
        # truth: the same voxels at the same world points (NIfTI stores RAS; ITK converts both ways)
        assert np.array_equal(back.array.astype(bool), seg.left)
        assert np.allclose(back.spacing, img.spacing) and np.allclose(back.origin, img.origin)
        assert np.allclose(back.direction, img.direction)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["left.mha", "left.nii.gz"]  # no temp files left


def test_downsample_keeps_world_positions():
    a = np.arange(4 * 6 * 8, dtype=np.int16).reshape(4, 6, 8)
    img = Image(a, [1.0, 1.0, 2.0], [10.0, 20.0, 30.0], np.eye(3))
    d = C.downsample(img, (1, 2, 2))
    assert d.array.shape == (4, 3, 4)
    assert np.allclose(d.spacing, [2.0, 2.0, 2.0])
    # block (0,0) of voxels x∈{0,1}, y∈{0,1}: centre at index 0.5 → world 10.5, 20.5
    assert np.allclose(d.origin, [10.5, 20.5, 30.0])
    assert d.array[0, 0, 0] == pytest.approx(a[0, :2, :2].mean())
