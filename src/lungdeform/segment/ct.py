"""CT input and grid geometry: reading a CT in HU, checking it, reordering and coarsening its grid.

- :func:`read_ct` reads a NIfTI/MHA/NRRD file, a DICOM series (a folder, a parent folder or one
  file) or a .tar.gz/.zip of one (:func:`extracted`; DICOM slices checked by the one slice check,
  :func:`lungdeform.io.dicom.slices.check_slices`, inside :func:`~lungdeform.io.image.read_image`) and
  checks that the image is CT in Hounsfield units (:func:`check_ct`);
- :func:`axial_axes` and :func:`to_axial` give the array in (z, y, x) order along world z, y, x
  (an exact transpose); :func:`downsample` block-means by integer factors;
- :func:`write_mask` writes a mask image atomically.

Frames: images are :class:`lungdeform.io.grid.Image`: ``array`` is ``(z, y, x)`` (SimpleITK order),
HU for a CT, 0/1 for a mask; spacing x y z mm, origin mm LPS, direction columns (index axes
i, j, k) in LPS.
"""

from __future__ import annotations

import tarfile
import tempfile
import zipfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from lungdeform.atomic import atomic_path
from lungdeform.errors import InputError, ReadError
from lungdeform.io.grid import Image
from lungdeform.io.image import IMAGE_SUFFIXES, read_image

ARCHIVE_SUFFIXES = (".tar.gz", ".tgz", ".tar", ".zip")


# =========================================================================== reading
def is_archive(path) -> bool:
    """True if ``path`` names a .tar.gz/.tgz/.tar/.zip file."""
    return Path(path).name.lower().endswith(ARCHIVE_SUFFIXES)


@contextmanager
def extracted(path, workdir=None):
    """Extract a .tar.gz/.tgz/.tar/.zip archive into a temporary folder (inside ``workdir`` if
    given); yield the folder that holds the most files (the DICOM series). Removed on exit."""
    path = Path(path)
    with tempfile.TemporaryDirectory(prefix="lungdeform-ct-", dir=workdir) as tmp:
        try:
            if path.name.lower().endswith(".zip"):
                with zipfile.ZipFile(path) as zf:
                    for member in zf.namelist():
                        target = (Path(tmp) / member).resolve()
                        if not str(target).startswith(str(Path(tmp).resolve())):
                            raise ReadError(f"{path}: archive member {member!r} points outside the archive")
                    zf.extractall(tmp)
            else:
                with tarfile.open(path) as tf:
                    tf.extractall(tmp, filter="data")
        except (tarfile.TarError, zipfile.BadZipFile, EOFError, OSError) as exc:
            raise ReadError(f"{path}: cannot extract archive ({exc})") from exc
        counts: dict[Path, int] = {}
        for f in Path(tmp).rglob("*"):
            if f.is_file():
                counts[f.parent] = counts.get(f.parent, 0) + 1
        if not counts:
            raise ReadError(f"{path}: the archive is empty")
        yield max(counts, key=lambda d: (counts[d], -len(d.parts)))


def archive_in(path) -> Path:
    """``path``, or the archive inside the folder ``path`` when that folder holds nothing else: no
    subfolder and no other file, hidden files (``.DS_Store``, ``._name``) aside. That is a dataset
    folder as downloaded: ``popi-ct-phase00/popi_phase00_dicom_141slices.tar.gz``. Several archives
    alone in a folder are refused, naming them. Only the folder's own entries are listed."""
    path = Path(path)
    if not path.is_dir():
        return path
    entries = [p for p in path.iterdir() if not p.name.startswith(".")]
    archives = sorted(p for p in entries if is_archive(p) and p.is_file())
    if not archives or len(archives) != len(entries):
        return path
    if len(archives) > 1:
        raise ReadError(f"{path}: no DICOM series here, and {len(archives)} archives "
                        f"({', '.join(a.name for a in archives[:4])}{', …' if len(archives) > 4 else ''}): give one of them")
    return archives[0]


def read_ct(path, workdir=None, series=None) -> Image:
    """Read a CT: NIfTI/MHA/NRRD file, a DICOM directory, or a .tar.gz/.zip of a DICOM series or of
    one image file (or a folder that holds only such an archive, :func:`archive_in`: the archive is
    read, and named as the source).

    DICOM series are checked for even slice spacing (by :func:`~lungdeform.io.image.read_image`:
    :func:`lungdeform.io.dicom.slices.check_slices`). The image must
    look like HU (some voxels below −500): otherwise :class:`InputError`. Archives are extracted
    into a temporary folder (inside ``workdir`` if given) that is removed afterwards. ``series``
    (:class:`~lungdeform.io.dicom.folder.SeriesChoice`) chooses among several CT series of a folder.
    """
    path = Path(path)
    if not path.exists():
        raise ReadError(f"{path}: no such file or directory")
    path = archive_in(path)
    if is_archive(path):
        with extracted(path, workdir) as folder:
            images = [p for p in folder.rglob("*") if p.is_file() and p.name.lower().endswith(IMAGE_SUFFIXES)]
            try:
                if len(images) == 1:  # one NIfTI/MHA/NRRD file in the archive
                    img = read_image(images[0])
                else:
                    img = read_image(folder, series=series)
            except ReadError as exc:  # name the archive, not the temporary folder (gone by now)
                raise ReadError(f"{path}: {str(exc).replace(str(folder), 'in the archive')}") from exc
        img = Image(img.array, img.spacing, img.origin, img.direction, source=str(path))
    else:
        img = read_image(path, series=series)
    check_ct(img)
    return img


def check_ct(image: Image) -> None:
    """Refuse images that are not CT in Hounsfield units (no air-like values, or not finite)."""
    a = image.array
    if a.size == 0:
        raise InputError(f"{image.source}: the image is empty")
    lo = float(a.min())
    if not np.isfinite(lo) or not np.isfinite(float(a.max())):
        raise InputError(f"{image.source}: the image holds NaN or infinite values")
    if lo > -500:
        raise InputError(
            f"{image.source}: minimum value {lo:g} — a CT in HU has air near −1000; "
            "this looks like a mask or an image without its rescale slope/intercept"
        )


# =========================================================================== grid
#: cos 30°: each index axis must lie within 30° of a world axis (a gantry tilt up to 30° passes).
MAX_TILT_COS = float(np.cos(np.radians(30.0)))


def axial_axes(image: Image) -> tuple[int, int, int]:
    """Array axes of ``image`` that run along world z, y and x (LPS), in that order.

    ``(0, 1, 2)`` for the usual axial (z, y, x) array; another permutation for an image stored
    as sagittal or coronal slices or with swapped in-plane axes (e.g. a NIfTI written in another
    axis order). Signs (feet-first, mirrored) are not part of it. Raises :class:`InputError` when
    an index axis lies more than 30° from every world axis (oblique slices, e.g. a gantry tilt
    beyond 30°), which needs resampling.
    """
    d = np.abs(np.asarray(image.direction, float))  # columns: index axes i, j, k in LPS
    world = [int(np.argmax(d[:, a])) for a in range(3)]  # world axis of each index axis
    if sorted(world) != [0, 1, 2] or min(d[w, a] for a, w in enumerate(world)) < MAX_TILT_COS:
        raise InputError(f"{image.source}: slices are not axial (direction {np.round(image.direction, 4).tolist()}); "
                         "resample to axial slices first")
    # array axis of index axis a is 2 - a (SimpleITK order (k, j, i))
    return tuple(2 - world.index(w) for w in (2, 1, 0))


def to_axial(image: Image, perm: tuple[int, int, int] | None = None) -> Image:
    """``image`` transposed so that its array is (z, y, x) along world z, y, x (:func:`axial_axes`).

    An exact reordering (no resampling): every voxel keeps its world position; the origin (the
    first voxel) is unchanged, spacing and direction columns follow their axes."""
    perm = axial_axes(image) if perm is None else tuple(perm)
    if perm == (0, 1, 2):
        return image
    index_axes = [2 - a for a in perm[::-1]]  # index axes (i, j, k) of the axial image, in the old order
    sp = np.asarray(image.spacing, float)[index_axes]
    d = np.asarray(image.direction, float)[:, index_axes]
    return Image(np.transpose(np.asarray(image.array), perm), sp, image.origin, d, source=image.source)


def downsample(image: Image, factors=(1, 2, 2)) -> Image:
    """Block-mean downsampling by integer ``factors`` along (z, y, x); spacing scales accordingly.

    The origin moves to the centre of the first block, so world positions stay consistent.
    """
    f = tuple(int(v) for v in factors)
    if len(f) != 3 or min(f) < 1:
        raise InputError(f"factors must be 3 positive integers (z, y, x), got {factors!r}")
    a = np.asarray(image.array, dtype=np.float32)
    shp = tuple(s // k for s, k in zip(a.shape, f))
    if min(shp) < 1:
        raise InputError(f"factors {f} leave no voxel of an image of shape {a.shape}")
    a = a[: shp[0] * f[0], : shp[1] * f[1], : shp[2] * f[2]]
    a = a.reshape(shp[0], f[0], shp[1], f[1], shp[2], f[2]).mean(axis=(1, 3, 5))
    fx = np.array([f[2], f[1], f[0]], float)
    shift = (fx - 1) / 2 * np.asarray(image.spacing)
    return Image(a, np.asarray(image.spacing) * fx, np.asarray(image.origin) + image.direction @ shift,
                 image.direction, source=image.source)


# =========================================================================== writing
def write_mask(image: Image, path) -> Path:
    """Write a mask :class:`Image` as .nii.gz/.nii/.mha/.nrrd (by suffix), atomically.

    SimpleITK writes the LPS geometry; for NIfTI it converts to the file's RAS convention itself.
    """


    path = Path(path)
    name = path.name.lower()
    suffix = next((s for s in (".nii.gz", ".nii", ".mha", ".mhd", ".nrrd") if name.endswith(s)), None)
    if suffix is None:
        raise InputError(f"{path}: mask format must be .nii.gz, .nii, .mha or .nrrd")
    img = sitk.GetImageFromArray(np.ascontiguousarray(image.array, dtype=np.uint8))
    img.SetSpacing([float(v) for v in image.spacing])
    img.SetOrigin([float(v) for v in image.origin])
    img.SetDirection([float(v) for v in np.asarray(image.direction).ravel()])

    with atomic_path(path, suffix) as tmp:
        sitk.WriteImage(img, str(tmp), useCompression=True)
    return path
