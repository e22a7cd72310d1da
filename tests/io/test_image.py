"""Reading images (lungdeform.io.image): geometry against SimpleITK and nibabel, DICOM series, errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from lungdeform.errors import InputError, ReadError
from lungdeform.io.grid import Image, index_to_world
from lungdeform.io.image import read_image, resample_channels, resample_image, write_image
from lungdeform.io.mask import mask_to_surface

from .test_mask import MIRRORED, rotation


def test_index_to_world_matches_simpleitk():
    # SimpleITK's own TransformContinuousIndexToPhysicalPoint is the reference
    import SimpleITK as sitk

    img = sitk.Image(5, 6, 7, sitk.sitkUInt8)
    img.SetSpacing((0.7, 1.3, 2.1))
    img.SetOrigin((-12.0, 40.0, 3.5))
    img.SetDirection(tuple(MIRRORED.ravel()))
    pts = np.array([[0, 0, 0], [1.5, 2.25, 3.0], [4, 5, 6]], dtype=float)
    expected = np.array([img.TransformContinuousIndexToPhysicalPoint(tuple(p)) for p in pts])
    got = index_to_world(pts, img.GetSpacing(), img.GetOrigin(), np.array(img.GetDirection()).reshape(3, 3))
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_read_image_errors(tmp_path):
    with pytest.raises(ReadError, match="no such file"):
        read_image(tmp_path / "missing.mha")
    (tmp_path / "empty.nii.gz").write_bytes(b"")
    with pytest.raises(ReadError, match=r"empty\.nii\.gz: file is empty"):
        read_image(tmp_path / "empty.nii.gz")
    (tmp_path / "junk.mha").write_bytes(b"\x00\x01junk" * 50)
    with pytest.raises(ReadError, match=r"junk\.mha: cannot read image"):
        read_image(tmp_path / "junk.mha")
    with pytest.raises(ReadError, match="no DICOM image series"):
        read_image(tmp_path)  # a directory without DICOM files


def test_read_image_rejects_2d(tmp_path):
    import SimpleITK as sitk

    sitk.WriteImage(sitk.Image(4, 5, sitk.sitkUInt8), str(tmp_path / "flat.mha"))
    with pytest.raises(ReadError, match=r"flat\.mha: expected a 3-D scalar image"):
        read_image(tmp_path / "flat.mha")


# --------------------------------------------------------------------------- reading images
@pytest.mark.parametrize("suffix", [".mha", ".nrrd", ".nii.gz"])
def test_read_image_keeps_geometry(tmp_path, rng, suffix):
    import SimpleITK as sitk

    arr = rng.integers(0, 6, size=(4, 5, 6)).astype(np.int16)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((0.7, 0.8, 1.5))
    img.SetOrigin((-100.0, 50.0, -20.0))
    img.SetDirection(tuple(MIRRORED.ravel()))
    sitk.WriteImage(img, str(tmp_path / f"lab{suffix}"))
    im = read_image(tmp_path / f"lab{suffix}")
    np.testing.assert_array_equal(im.array, arr)
    np.testing.assert_allclose(im.spacing, (0.7, 0.8, 1.5), atol=1e-6)
    np.testing.assert_allclose(im.origin, (-100.0, 50.0, -20.0), atol=1e-4)
    np.testing.assert_allclose(im.direction, MIRRORED, atol=1e-5)


def test_nifti_ras_is_converted_to_lps(tmp_path):
    # nibabel writes the RAS affine the file stores; ITK must report the same voxels at the LPS
    # point diag(-1, -1, 1) @ RAS. This is the check behind read_image's docstring.
    import nibabel as nib

    affine = np.array([[-0.8, 0, 0, 213.1], [0, 0.8, 0, -206.9], [0, 0, 1.2, -220.0], [0, 0, 0, 1]])
    affine[:3, :3] = affine[:3, :3] @ rotation([0, 0, 1], 10.0)
    data = np.zeros((6, 7, 8), np.int16)  # nibabel order (i, j, k)
    nib.save(nib.Nifti1Image(data, affine), str(tmp_path / "ras.nii.gz"))
    im = read_image(tmp_path / "ras.nii.gz")
    assert im.array.shape == (8, 7, 6)  # SimpleITK order (k, j, i)
    ijk = np.array([[0, 0, 0], [5, 6, 7], [2.5, 1.0, 4.0]])
    ras = ijk @ affine[:3, :3].T + affine[:3, 3]
    np.testing.assert_allclose(im.index_to_world(ijk), ras * [-1, -1, 1], atol=1e-3)


def test_read_dicom_series_directory(tmp_path):
    # a label volume written as a DICOM series (one file per slice), read back from the folder
    import locale

    import SimpleITK as sitk

    saved = locale.setlocale(locale.LC_ALL)
    arr = np.zeros((6, 10, 12), np.int16)
    arr[1:5, 2:8, 3:9] = 1
    spacing, origin = (2.9, 2.9, 4.0), (-50.0, -40.0, 30.0)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(arr.shape[0]):
        sl = sitk.GetImageFromArray(arr[k])
        sl.SetSpacing(spacing[:2])
        for tag, value in {
            "0008|0060": "OT",
            "0020|000d": "1.2.826.0.1.3680043.2.1125.1",
            "0020|000e": "1.2.826.0.1.3680043.2.1125.1.1",
            "0008|0018": f"1.2.826.0.1.3680043.2.1125.1.1.{k + 1}",
            "0020|0013": str(k + 1),
            "0020|0032": "\\".join(map(str, (origin[0], origin[1], origin[2] + k * spacing[2]))),
            "0020|0037": "1\\0\\0\\0\\1\\0",
            "0018|0050": str(spacing[2]),
            "0028|0030": f"{spacing[1]}\\{spacing[0]}",  # written whatever GDCM's state (run alone it omitted it)
        }.items():
            sl.SetMetaData(tag, value)
        writer.SetFileName(str(tmp_path / f"slice{k:03d}.dcm"))
        writer.Execute(sl)
    # GDCM's writer leaves the process locale at "C", which turns every later open() without an
    # explicit encoding ASCII and broke a later test in the suite: give it back (test set-up only)
    locale.setlocale(locale.LC_ALL, saved)
    im = read_image(tmp_path)
    assert locale.setlocale(locale.LC_ALL) == saved  # the reader itself leaves the locale alone
    np.testing.assert_array_equal(im.array, arr)
    np.testing.assert_allclose(im.spacing, spacing, atol=1e-6)
    np.testing.assert_allclose(im.origin, origin, atol=1e-6)
    surf = mask_to_surface(im, smooth_iterations=0)
    assert surf.volume == pytest.approx(6 * 6 * 4 * 2.9 * 2.9 * 4.0, rel=0.15)


# --------------------------------------------------------------------------- real data
@pytest.mark.realdata
def test_coronacases_frame_matches_nibabel(coronacases_001):
    # the real file: ITK's LPS geometry equals nibabel's RAS affine with x and y negated
    import nibabel as nib

    aff = nib.load(coronacases_001.source).affine
    ijk = np.array([[0, 0, 0], [511, 511, 300], [100, 200, 50]], dtype=float)
    ras = ijk @ aff[:3, :3].T + aff[:3, 3]
    np.testing.assert_allclose(coronacases_001.index_to_world(ijk), ras * [-1, -1, 1], atol=1e-3)


# --------------------------------------------------------------------------- DICOM series
def _tiny_series(folder, series_uid, n=4):
    """``n`` 6×5 int16 slices of one DICOM series ``series_uid`` in ``folder`` (locale restored)."""
    import locale

    import SimpleITK as sitk

    saved = locale.setlocale(locale.LC_ALL)
    folder.mkdir(parents=True, exist_ok=True)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(n):
        sl = sitk.GetImageFromArray(np.full((5, 6), k, np.int16))
        for tag, value in {"0008|0060": "CT", "0020|000d": "1.2.826.0.1.3680043.2.1125.7",
                           "0020|000e": series_uid, "0008|0018": f"{series_uid}.{k + 1}",
                           "0020|0013": str(k + 1), "0020|0032": f"0\\0\\{2.0 * k}",
                           "0020|0037": "1\\0\\0\\0\\1\\0"}.items():
            sl.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"{series_uid[-2:]}_{k:03d}.dcm"))
        writer.Execute(sl)
    locale.setlocale(locale.LC_ALL, saved)


def test_dicom_series_files_choices(tmp_path):
    from pathlib import Path

    from lungdeform.io.dicom.folder import SeriesChoice
    from lungdeform.io.dicom.guard import is_dicom_file
    from lungdeform.io.dicom.series import dicom_series_files

    # one folder, a CT of 4 slices and another of 2 (issue 36: two candidate CT series are refused,
    # naming both, never the larger taken without a word); a SeriesChoice picks one
    _tiny_series(tmp_path / "ct", "1.2.826.0.1.3680043.2.1125.7.11", 4)
    _tiny_series(tmp_path / "ct", "1.2.826.0.1.3680043.2.1125.7.12", 2)
    with pytest.raises(ReadError, match=r"ct: holds 2 CT series \(1.2.826.0.1.3680043.2.1125.7.11 '' \(4 CT image\(s\)\); "
                                        r"1.2.826.0.1.3680043.2.1125.7.12 '' \(2 CT image\(s\)\)\)"):
        dicom_series_files(tmp_path / "ct")
    files = dicom_series_files(tmp_path / "ct", SeriesChoice(uid="1.2.826.0.1.3680043.2.1125.7.11"))
    assert len(files) == 4 and all(Path(f).name.startswith("11_") for f in files)
    # one file of the scout: its own series, not the largest
    assert len(dicom_series_files(tmp_path / "ct" / "12_000.dcm")) == 2
    assert is_dicom_file(tmp_path / "ct" / "12_000.dcm") and not is_dicom_file(tmp_path / "ct")
    im = read_image(tmp_path / "ct" / "11_002.dcm")  # reads the whole series it belongs to
    assert im.array.shape == (4, 5, 6) and [int(im.array[k, 0, 0]) for k in range(4)] == [0, 1, 2, 3]
    # two series of the same size in one folder (the phases of a 4-D CT): ambiguous, refused
    _tiny_series(tmp_path / "4d", "1.2.826.0.1.3680043.2.1125.7.21", 3)
    _tiny_series(tmp_path / "4d", "1.2.826.0.1.3680043.2.1125.7.22", 3)
    with pytest.raises(ReadError, match=r"4d: holds 2 CT series .*which one is meant cannot be told"):
        dicom_series_files(tmp_path / "4d")


def test_header_claiming_more_voxels_than_the_file_holds(tmp_path):
    # why: found by tests/fuzz/fuzz_image_nii.py (libFuzzer out-of-memory): a 94-byte gzipped NIfTI
    # whose header claims 2566 x 1280 x 1024 voxels; deflate cannot expand 94 bytes to 6.7 GB, so
    # the header is damaged and must be refused before ITK allocates the voxels
    bad = Path(__file__).resolve().parents[1] / "corpus" / "image" / "huge_header.nii.gz"
    with pytest.raises(ReadError, match=r"huge_header\.nii\.gz: header claims 2566x1280x1024 voxels"):
        read_image(bad)


@pytest.mark.parametrize("name", ["huge_ndims.mha", "huge_ndims.nrrd"])
def test_text_header_with_a_huge_dimension_count(name):
    # why: found by tests/fuzz/fuzz_image_mha.py (libFuzzer timeout): ITK spins for minutes on
    # "NDims = 300000000000004"; the header's dimension count is checked (it must be 3) before ITK reads
    bad = Path(__file__).resolve().parents[1] / "corpus" / "image" / name
    with pytest.raises(ReadError, match=rf"{name}: expected a 3-D image, the header gives '300000000000004'"):
        read_image(bad)


def test_write_image_keeps_grid_and_pixel_type(tmp_path):
    # what is written reads back voxel for voxel with its origin, spacing, direction and dtype
    c, s = np.cos(0.2), np.sin(0.2)
    d = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    a = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    for name in ("a.mha", "a.nii.gz", "a.nrrd"):
        img = read_image(write_image(tmp_path / name, a, [0.5, 0.7, 2.0], [1.0, -2.0, 3.0], d))
        assert img.array.dtype == np.int16 and np.array_equal(img.array, a)
        assert np.allclose(img.spacing, [0.5, 0.7, 2.0]) and np.allclose(img.origin, [1, -2, 3])
        assert np.allclose(img.direction, d, atol=1e-6)
    with pytest.raises(InputError, match="unknown output image format"):
        write_image(tmp_path / "a.png", a, [1, 1, 1], [0, 0, 0], np.eye(3))


def test_resample_with_nearest_neighbour_keeps_labels():
    # a shift of exactly one voxel along x moves labels by one voxel, values only from the input
    a = np.zeros((4, 5, 6), np.uint8)
    a[1:3, 1:4, 2:4] = 7
    a[2, 2, 3] = 3
    img = Image(a, [2.0, 1.0, 1.0], [0.0, 0.0, 0.0], np.eye(3))
    field = np.zeros(a.shape + (3,))
    field[..., 0] = 2.0  # output voxel y takes the input at y + 2 mm = one voxel along x
    out = resample_image(img, field, label=True)
    assert out.array.dtype == np.uint8 and set(np.unique(out.array)) == {0, 3, 7}
    assert np.array_equal(out.array[:, :, :-1], a[:, :, 1:])


def test_resample_channels_equals_each_channel_resampled_alone():
    # why: one pass over c channels must give what resample_image gives each channel (linear, 0
    # outside): a field of 0.37 voxel along x and -0.6 along z, the last slab's sources off the image
    rng = np.random.default_rng(5)
    a = rng.normal(size=(5, 6, 7, 3)).astype(np.float32)
    img = Image(a[..., 0], [1.5, 1.0, 2.0], [3.0, -2.0, 1.0], np.eye(3))
    field = np.zeros(a.shape[:3] + (3,))
    field[..., 0], field[..., 2] = 0.37 * 1.5, -0.6 * 2.0
    out = resample_channels(img, a, field)
    for c in range(3):
        alone = resample_image(Image(a[..., c], img.spacing, img.origin, img.direction), field, default=0.0).array
        assert np.allclose(out[..., c], alone, atol=1e-6)
    assert np.all(out[0] == 0) and np.any(out[1] != 0)
    with pytest.raises(InputError, match="channels"):
        resample_channels(img, a[:-1], field)


def _ct_series(folder, z_mm, tags=None):
    """A CT series of a 40 mm ball (0 HU in -1000 HU air, 2 mm pixels) with one slice per position
    ``z_mm`` (ImagePositionPatient z; in-plane origin -31 mm), plus ``tags`` in every slice."""
    import SimpleITK as sitk

    folder.mkdir(parents=True, exist_ok=True)
    j, i = np.mgrid[:32, :32] * 2.0 - 31.0
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k, z in enumerate(z_mm):
        arr = np.where(i ** 2 + j ** 2 + z ** 2 <= 400, 0, -1000).astype(np.int16)[None]
        img = sitk.GetImageFromArray(arr)
        img.SetSpacing((2.0, 2.0, 1.0))
        for key, value in {"0008|0060": "CT", "0020|000e": "1.2.826.0.1.3680043.8.498.5.1",
                           "0008|0018": f"1.2.826.0.1.3680043.8.498.5.1.{k + 1}", "0020|0013": str(k + 1),
                           "0020|0032": f"-31\\-31\\{z}", "0020|0037": "1\\0\\0\\0\\1\\0", "0028|0030": "2\\2",
                           **(tags or {})}.items():
            img.SetMetaData(key, value)
        writer.SetFileName(str(folder / f"ct{k:03d}.dcm"))
        writer.Execute(img)
    return folder


def test_dicom_series_of_uneven_or_tilted_slices_refused(tmp_path):
    # why: ITK spaces a series by its extent / (n - 1) and ignores a gantry tilt: slices 6 mm then
    # 3 mm apart were read 4.5 mm apart (the lungs' volumes 25 % wrong), and a tilted series as if
    # untilted, without a word; read_image refuses both, naming the series and the files
    even = read_image(_ct_series(tmp_path / "even", np.arange(-24.0, 25.0, 3.0)))
    assert np.allclose(even.spacing, [2, 2, 3])
    uneven = np.r_[np.arange(-24.0, 0.0, 6.0), np.arange(0.0, 25.0, 3.0)]
    with pytest.raises(ReadError, match=r"uneven: uneven slice spacing: the gaps between slices run from 3 to 6 mm"):
        read_image(_ct_series(tmp_path / "uneven", uneven))
    gap = np.r_[np.arange(-24.0, 0.0, 3.0), np.arange(3.0, 25.0, 3.0)]
    with pytest.raises(ReadError, match=r"gap: 1 slice\(s\) missing: .* 6 mm between ct007\.dcm at -3\.000 mm"):
        read_image(_ct_series(tmp_path / "gap", gap))
    with pytest.raises(ReadError, match=r"tilt: .*ct000\.dcm: GantryDetectorTilt is 20 degrees"):
        read_image(_ct_series(tmp_path / "tilt", np.arange(-24.0, 25.0, 3.0), {"0018|1120": "20"}))
    stacked = tmp_path / "stacked"
    _ct_series(stacked, np.arange(-24.0, 25.0, 3.0))
    import pydicom

    for k, f in enumerate(sorted(stacked.glob("*.dcm"))):  # the 20 degree tilt as positions only
        ds = pydicom.dcmread(f)
        ds.ImagePositionPatient = [-31.0, -31.0 + np.tan(np.radians(20)) * 3.0 * k, -24.0 + 3.0 * k]
        ds.save_as(f)
    with pytest.raises(ReadError, match=r"stacked: the slices are stacked 20 degrees off their normal"):
        read_image(stacked)


def test_grid_cap_on_read_and_write(tmp_path, monkeypatch):
    # why: a header declaring 1000^3 voxels made ITK allocate gigabytes (a MemoryError after 17 s);
    # the grid is capped from the header before any voxel is read, and on write before any byte is
    # written; the cap is raised by an argument or $LUNGDEFORM_MAX_VOXELS
    import SimpleITK as sitk

    from lungdeform.io.grid import MAX_VOXELS

    assert 512 * 512 * 2000 <= MAX_VOXELS < 1000 ** 3
    huge = tmp_path / "huge.mhd"
    huge.write_text("ObjectType = Image\nNDims = 3\nDimSize = 1000 1000 1000\nElementType = MET_UCHAR\n"
                    "ElementSpacing = 1 1 1\nElementDataFile = huge.raw\n")
    with open(tmp_path / "huge.raw", "wb") as fh:  # sparse: no disk used
        fh.truncate(1000 ** 3)
    monkeypatch.setattr(sitk, "ReadImage", lambda *a, **k: pytest.fail("the voxels were read"))
    with pytest.raises(ReadError, match=r"huge\.mhd: the image grid 1000 x 1000 x 1000 is 1,000,000,000 voxels, "
                                        r"over the limit of 536,870,912 \(raise it with 'lungdeform --max-voxels N"):
        read_image(huge)
    monkeypatch.undo()
    a = np.zeros((10, 10, 10), np.int16)
    write_image(tmp_path / "ok.mha", a, (1, 1, 1), (0, 0, 0), np.eye(3))
    with pytest.raises(ReadError, match=r"ok\.mha: the image grid 10 x 10 x 10 is 1,000 voxels, over the limit of 999"):
        read_image(tmp_path / "ok.mha", max_voxels=999)
    with pytest.raises(InputError, match=r"big\.mha: the image grid 10 x 10 x 10 is 1,000 voxels, over the limit of 999"):
        write_image(tmp_path / "big.mha", a, (1, 1, 1), (0, 0, 0), np.eye(3), max_voxels=999)
    assert not (tmp_path / "big.mha").exists()
    monkeypatch.setenv("LUNGDEFORM_MAX_VOXELS", "999")
    with pytest.raises(ReadError, match="over the limit of 999"):
        read_image(_ct_series(tmp_path / "dicom", [0.0, 2.0]))  # 32 x 32 x 2 = 2048 voxels
    monkeypatch.setenv("LUNGDEFORM_MAX_VOXELS", "2048")
    assert read_image(tmp_path / "dicom").array.shape == (2, 32, 32)


def test_max_voxels_option(tmp_path, monkeypatch, capsys):
    # why: the CLI raises (or lowers) the cap for every command with one option before the command
    # name; a bad value is one error line, exit 2, before any work
    from lungdeform.cli.main import main

    monkeypatch.delenv("LUNGDEFORM_MAX_VOXELS", raising=False)
    mask = tmp_path / "mask.mha"
    write_image(mask, np.ones((10, 10, 10), np.uint8), (4, 4, 4), (0, 0, 0), np.eye(3))
    assert main(["--max-voxels", "999", "build", str(mask), "--side", "left", "--out", str(tmp_path / "o" / "m.npz")]) == 2
    assert "mask.mha: the image grid 10 x 10 x 10 is 1,000 voxels, over the limit of 999" in capsys.readouterr().err
    assert main(["--max-voxels", "lots", "build", str(mask), "--side", "left", "--out", str(tmp_path / "o" / "m.npz")]) == 2
    assert capsys.readouterr().err.strip() == "error: --max-voxels must be a positive whole number of voxels, got 'lots'"
    assert not (tmp_path / "o").exists()


def test_max_voxels_lasts_one_command(tmp_path, monkeypatch):
    # --max-voxels sets the cap for its own command (and its workers), not for whatever the process
    # runs next: an in-process main() left 999 behind and every later image read was refused
    from lungdeform.cli.main import main
    from lungdeform.io.grid import MAX_VOXELS_ENV

    monkeypatch.delenv(MAX_VOXELS_ENV, raising=False)
    main(["--max-voxels", "999", "build", str(tmp_path / "none.nii.gz"), "--out", str(tmp_path / "m.npz")])
    assert MAX_VOXELS_ENV not in os.environ


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz", ".mha", ".nrrd"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_voxels_are_refused_naming_the_first(tmp_path, suffix, value):
    # why: ITK reads a NaN or inf NIfTI voxel as 0 (a NaN region of a CT became 0 HU, soft tissue,
    # and segment, warp and build went on: exit 0); other formats keep it, and every consumer then
    # coerced it (a NaN fails every threshold). Truth: the voxel written, named by its (x, y, z) index
    import SimpleITK as sitk
    a = np.zeros((4, 5, 6), np.float32)
    a[2, 3, 1] = value
    path = tmp_path / f"v{suffix}"
    sitk.WriteImage(sitk.GetImageFromArray(a), str(path))
    with pytest.raises(ReadError, match=rf"v{suffix.replace('.', '[.]')}: .*\(1, 3, 2\).*finite numbers only"):
        read_image(path)
    a[2, 3, 1] = -1000.5  # the same file finite: read as written
    sitk.WriteImage(sitk.GetImageFromArray(a), str(path))
    assert read_image(path).array[2, 3, 1] == -1000.5


def test_a_nifti_whose_qform_and_sform_disagree_is_refused(tmp_path):
    # why: ITK picks one of the two transforms without a word (here the qform: the image read 0.05 mm
    # off the sform); two frames 5 mm apart in one file is a patient placed in two places, so it is
    # refused, naming both codes and the distance. Truth: nibabel's own affines of the same header
    # (an independent reader), a rotated anisotropic grid, a negative qfac, float32 rounding allowed
    import nibabel as nib
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    arr = (rng.random((12, 14, 9)) > 0.5).astype(np.uint8)
    aff = np.eye(4)
    aff[:3, :3] = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix() @ np.diag([0.8, 0.9, -2.5])
    aff[:3, 3] = [-100.0, 50.0, 30.0]
    for shift, refused in ((0.0, False), (0.05, False), (5.0, True)):
        img = nib.Nifti1Image(arr, aff)
        q = aff.copy()
        q[:3, 3] += [0.0, shift, 0.0]
        img.set_qform(q, code=1)
        img.set_sform(aff, code=2)
        path = tmp_path / f"m{shift}.nii.gz"
        nib.save(img, path)
        header = nib.load(path).header
        assert header["pixdim"][0] == -1  # the flipped axis is stored as qfac
        apart = np.abs(header.get_qform()[:3, 3] - header.get_sform()[:3, 3]).max()
        assert apart == pytest.approx(shift, abs=1e-4)
        if refused:
            with pytest.raises(ReadError, match=r"qform \(code 1\) and sform \(code 2\) place the image 5\.00 mm apart"):
                read_image(path)
        else:
            assert read_image(path).array.shape == arr.shape[::-1]


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_a_truncated_nifti_is_refused(tmp_path, suffix):
    # why: ITK reads a NIfTI file that ends early without an error, its missing voxels as 0 (a mask cut
    # in half read as half a lung). Truth: the intact file reads back the written voxels; the same bytes
    # cut short (the file, or the gzip stream) are refused naming the file, whatever is cut
    import gzip

    import SimpleITK as sitk

    rng = np.random.default_rng(5)
    arr = (rng.random((10, 12, 14)) > 0.5).astype(np.uint8)
    path = tmp_path / f"m{suffix}"
    sitk.WriteImage(sitk.GetImageFromArray(arr), str(path))
    np.testing.assert_array_equal(read_image(path).array, arr)
    raw = gzip.decompress(path.read_bytes()) if suffix == ".nii.gz" else path.read_bytes()
    assert len(raw) == 352 + arr.size  # header, extension flag, voxels: what the check counts
    cut = tmp_path / f"cut{suffix}"
    for size in (len(raw) - 1, len(raw) // 2, 400):  # the last voxel, half of them, all but a few
        body = raw[:size]
        cut.write_bytes(gzip.compress(body) if suffix == ".nii.gz" else body)
        with pytest.raises(ReadError, match=rf"^{cut}: truncated NIfTI file \(it holds {size} of the {len(raw)} bytes"):
            read_image(cut)
    if suffix == ".nii.gz":  # the gzip stream itself cut short
        cut.write_bytes(path.read_bytes()[:-40])
        with pytest.raises(ReadError, match=rf"^{cut}: truncated NIfTI file \(its gzip stream is damaged\)"):
            read_image(cut)


def test_a_direction_that_is_not_a_rotation_is_refused(tmp_path):
    # why: a MetaImage TransformMatrix with a shear (or a zero row) reads in ITK as it is written, and
    # ITK's filters and NIfTI writer treat it as orthonormal: the voxels would land elsewhere without a
    # word. Truth: a rotation and a reflection (DᵀD = I) read with their direction; a shear of 0.3 and a
    # degenerate matrix are refused naming the file; float32-rounded cosines pass
    import SimpleITK as sitk
    from scipy.spatial.transform import Rotation

    img = sitk.GetImageFromArray(np.ones((4, 5, 6), np.uint8))
    rot = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    for name, d in (("rot", rot), ("mirror", np.diag([-1.0, 1.0, 1.0])), ("f32", rot.astype(np.float32))):
        img.SetDirection(tuple(float(v) for v in np.asarray(d, float).ravel()))
        sitk.WriteImage(img, str(tmp_path / f"{name}.mha"))
        np.testing.assert_allclose(read_image(tmp_path / f"{name}.mha").direction, d, atol=1e-6)
    text = (tmp_path / "rot.mha").read_bytes()
    head, _, body = text.partition(b"ElementDataFile = LOCAL\n")
    for name, matrix in (("shear", b"1 0 0 0.3 1 0 0 0 1"), ("flat", b"1 0 0 1 0 0 0 0 1")):
        bad = tmp_path / f"{name}.mha"
        lines = [ln if not ln.startswith(b"TransformMatrix") else b"TransformMatrix = " + matrix
                 for ln in head.splitlines()]
        bad.write_bytes(b"\n".join(lines) + b"\nElementDataFile = LOCAL\n" + body)
        with pytest.raises(ReadError, match=rf"^{bad}: the header's direction matrix .* is not orthonormal"):
            read_image(bad)


@pytest.mark.parametrize("compress", [False, True])
def test_a_truncated_metaimage_is_refused_in_one_line(tmp_path, compress):
    # why: ITK refused a MetaImage cut short with "No such file or directory" and printed two lines of
    # its own on stderr; the refusal now says what is wrong. Truth: the intact file reads back its
    # voxels; the same file without its last byte, or half its voxel data, is refused naming the file
    # and the byte counts of the header's own grid (or CompressedDataSize)
    import SimpleITK as sitk

    rng = np.random.default_rng(8)
    arr = (rng.random((10, 12, 14)) > 0.5).astype(np.uint8)
    path = tmp_path / "m.mha"
    sitk.WriteImage(sitk.GetImageFromArray(arr), str(path), useCompression=compress)
    np.testing.assert_array_equal(read_image(path).array, arr)
    raw = path.read_bytes()
    data = len(raw) - (raw.index(b"ElementDataFile = LOCAL\n") + len(b"ElementDataFile = LOCAL\n"))
    assert compress or data == arr.size
    cut = tmp_path / "cut.mha"
    for drop in (1, data // 2):
        cut.write_bytes(raw[:-drop])
        with pytest.raises(ReadError, match=rf"^{cut}: truncated MetaImage file \(it holds {data - drop} of the {data} bytes"):
            read_image(cut)
