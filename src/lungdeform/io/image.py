"""Reading 3-D medical images: NIfTI, MetaImage (.mha/.mhd), NRRD and DICOM series; writing them.

:func:`read_image` reads a file or a DICOM folder with SimpleITK into an
:class:`~lungdeform.io.grid.Image` and refuses what is missing, empty, unreadable, ambiguous
(several DICOM series) or not 3-D scalar, with a :class:`ReadError` naming the path. It is the one
entry point from here into :mod:`lungdeform.io.dicom` (DICOM series are found, checked and read
there: :func:`~lungdeform.io.dicom.series.read_series`).

Frames and units: those of :mod:`lungdeform.io.grid` (array ``[z, y, x]``; spacing, origin and
voxel indices ``(x, y, z)``, mm LPS).
"""

from __future__ import annotations

import gzip
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from lungdeform.atomic import atomic_path
from lungdeform.errors import InputError, LungdeformError, ReadError

from .dicom.guard import is_dicom_file
from .dicom.series import read_series
from .grid import Image, check_grid, quiet_itk

IMAGE_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")
#: deflate (gzip, zlib) never expands data more than about 1032 times
MAX_INFLATE = 1032
#: Suffixes :func:`write_image` writes (single-file formats, so that a write is atomic).
WRITE_SUFFIXES = (".mha", ".nii.gz", ".nii", ".nrrd")
#: MetaImage header keys that hold numbers placing the grid (ITK reads "nan" or a missing value as 0),
#: and how many: "n" NDims, "nn" NDims squared.
_META_GEOMETRY = {"Offset": "n", "Origin": "n", "Position": "n", "ElementSpacing": "n", "ElementSize": "n",
                  "CenterOfRotation": "n", "TransformMatrix": "nn", "Rotation": "nn", "Orientation": "nn"}


def is_dicom_series_path(path) -> bool:
    """True for a path that names a DICOM series: a directory, or a DICOM file without an image suffix
    (:data:`IMAGE_SUFFIXES`); how :func:`read_image` tells a series from an image file."""
    p = Path(path)
    return p.is_dir() or (not p.name.lower().endswith(IMAGE_SUFFIXES) and is_dicom_file(p))


def is_image_path(path) -> bool:
    """True for a directory (DICOM), a DICOM file, or a file with an image suffix (:data:`IMAGE_SUFFIXES`)."""
    p = Path(path)
    return p.is_dir() or p.name.lower().endswith(IMAGE_SUFFIXES) or is_dicom_file(p)


def _check_meta_numbers(p: Path, head: bytes) -> None:
    """Refuse a MetaImage header whose grid numbers (:data:`_META_GEOMETRY`) are not NDims (or
    NDims²) finite numbers: ITK reads ``Offset = nan``, ``inf`` or a missing value as 0."""
    end = re.search(rb"^\s*ElementDataFile\s*=[^\r\n]*", head, re.M)
    head = head[:end.end()] if end else head
    ndims = re.search(rb"^\s*NDims\s*=[ \t]*(\d+)", head, re.M)
    n = int(ndims.group(1)) if ndims else None
    for m in re.finditer(rb"^[ \t]*(\w+)[ \t]*=[ \t]*([^\r\n]*)", head, re.M):
        key = m.group(1).decode(errors="replace")
        if key not in _META_GEOMETRY:
            continue
        text = m.group(2).decode(errors="replace").strip()
        try:
            values = np.array([float(t) for t in text.split()])
        except ValueError:
            values = np.array([np.nan])
        want = None if n is None else (n if _META_GEOMETRY[key] == "n" else n * n)
        if not np.isfinite(values).all() or (want is not None and len(values) != want):
            raise ReadError(f"{p}: header key {key} = {text[:80]!r} is not {want or 'NDims'} finite numbers")


def _check_nrrd_numbers(p: Path, head: bytes) -> None:
    """Refuse a NRRD header whose spacings, space origin or space directions hold NaN, infinity or
    anything but numbers (``none`` aside): ITK reads a NaN spacing ("unknown" in NRRD) as 1 mm."""
    header = head.split(b"\n\n", 1)[0]
    for m in re.finditer(rb"^(spacings|space origin|space directions):[ \t]*([^\r\n]*)", header, re.M):
        text = m.group(2).decode(errors="replace").strip()
        for token in re.findall(r"[^\s(),]+", text):
            if token.lower() == "none":
                continue
            try:
                ok = np.isfinite(float(token))
            except ValueError:
                ok = False
            if not ok:
                raise ReadError(f"{p}: header field {m.group(1).decode()}: {text[:80]!r} holds {token[:20]!r}, "
                                "not a finite number")


def _check_nifti_numbers(p: Path) -> None:
    """Refuse a NIfTI-1 header whose voxel size (pixdim), qform (quatern, qoffset; when its code is
    set) or sform (srow; when its code is set) holds NaN or infinity, before ITK builds its grid,
    or whose qform and sform (both set) disagree by more than :data:`NIFTI_FORMS_TOLERANCE_MM`:
    ITK would pick one of them without a word."""
    try:
        if p.name.lower().endswith(".gz"):
            with gzip.open(p, "rb") as fh:
                raw = fh.read(348)
        else:
            with open(p, "rb") as fh:
                raw = fh.read(348)
    except (OSError, EOFError, zlib.error):
        return  # ITK says what is wrong with it
    if len(raw) < 348:
        return
    endian = next((e for e in "<>" if struct.unpack(e + "i", raw[:4])[0] == 348), None)
    if endian is None:
        return  # NIfTI-2 or none at all: ITK's grid is checked after

    def floats(offset, count):
        return np.array(struct.unpack(f"{endian}{count}f", raw[offset:offset + 4 * count]))

    qform, sform = struct.unpack(endian + "hh", raw[252:256])
    fields = {"pixdim": floats(80, 3)}
    if qform > 0:
        fields.update(quatern=floats(256, 3), qoffset=floats(268, 3))
    if sform > 0:
        fields.update(srow_x=floats(280, 4), srow_y=floats(296, 4), srow_z=floats(312, 4))
    for key, values in fields.items():
        if not np.isfinite(values).all():
            raise ReadError(f"{p}: NIfTI header field {key} holds {values.tolist()}: not finite")
    if qform > 0 and sform > 0:
        dims = np.maximum(np.array(struct.unpack(endian + "3h", raw[42:48]), float) - 1, 0)
        corners = np.array([[i, j, k] for i in (0, dims[0]) for j in (0, dims[1]) for k in (0, dims[2])])
        q_affine = _nifti_qform(fields["quatern"], fields["qoffset"], floats(76, 4))
        s_affine = np.stack([fields["srow_x"], fields["srow_y"], fields["srow_z"]])
        apart = np.abs((corners @ q_affine[:, :3].T + q_affine[:, 3]) - (corners @ s_affine[:, :3].T + s_affine[:, 3])).max()
        if apart > NIFTI_FORMS_TOLERANCE_MM:
            raise ReadError(f"{p}: the NIfTI header's qform (code {qform}) and sform (code {sform}) place the image "
                            f"{apart:.2f} mm apart at a corner of its grid: which is the patient's frame is ambiguous "
                            "and lungdeform does not guess; write the file with one transform, or both the same")


#: How far (mm, at any corner of the grid) a NIfTI's qform and sform may place a voxel apart: their
#: float32 rounding, far below a voxel; more is two different frames in one file.
NIFTI_FORMS_TOLERANCE_MM = 0.1


def _nifti_qform(quatern, qoffset, pixdim) -> np.ndarray:
    """``(3, 4) float``: voxel index → mm (the file's RAS) of a NIfTI-1 qform: the rotation of the
    quaternion ``(b, c, d)`` (``a`` from unit length), the voxel sizes ``pixdim[1:4]`` with the
    last negated when ``qfac = pixdim[0]`` is −1, then ``qoffset`` (NIfTI-1 standard, nifti1.h)."""
    b, c, d = (float(v) for v in quatern)
    a = np.sqrt(max(0.0, 1.0 - (b * b + c * c + d * d)))
    rotation = np.array([[a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
                         [2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b)],
                         [2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - b * b - c * c]])
    qfac = -1.0 if pixdim[0] < 0 else 1.0
    scale = np.array([pixdim[1], pixdim[2], qfac * pixdim[3]], float)
    return np.column_stack([rotation * scale, np.asarray(qoffset, float)])


def _check_header(p: Path, max_voxels=None) -> None:
    """Refuse, before ITK reads its voxels, an image file whose header is absurd: a dimension count
    over 10 (text headers), a file pattern as MetaImage data file, grid numbers that are not finite
    (:func:`_check_meta_numbers`, :func:`_check_nrrd_numbers`, :func:`_check_nifti_numbers`, then
    ITK's origin, spacing and direction), a grid over the cap (:func:`check_grid`), or a
    single-file image whose header claims more voxel bytes than the file can hold even deflated at
    the most (:data:`MAX_INFLATE`): ITK would try to allocate them. The sizes of files whose voxels live in another file (.mhd, .nhdr,
    a .mha or .nrrd naming a data file) are not judged against the file size."""
    name = p.name.lower()
    with open(p, "rb") as fh:
        head = fh.read(65536)
    _check_text_header(p, name, head)
    if name.endswith((".mha", ".mhd")):
        _check_meta_numbers(p, head)
    if name.endswith((".nrrd", ".nhdr")):
        _check_nrrd_numbers(p, head)
    if name.endswith((".nii", ".nii.gz")):
        _check_nifti_numbers(p)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(p))
    with quiet_itk():
        reader.ReadImageInformation()
    _check_inflate(p, name, head, reader)
    check_grid(reader.GetSize(), p, max_voxels)
    for key, values in (("origin", reader.GetOrigin()), ("spacing", reader.GetSpacing()),
                        ("direction", reader.GetDirection())):
        if not np.isfinite(values).all():
            raise ReadError(f"{p}: the header's {key} {list(values)} is not finite")
    _check_orthonormal(p, reader.GetDirection())
    if name.endswith((".nii", ".nii.gz")):
        _check_nifti_length(p)
    if name.endswith(".mha"):
        _check_meta_length(p, head, _voxel_bytes(reader))


#: How far a direction matrix may be from orthonormal (largest entry of DᵀD − I): float32 headers and
#: DICOM's six-decimal cosines are within 1e-5; a shear or a scaled axis is far beyond.
ORTHONORMAL_TOLERANCE = 1e-3


def _check_orthonormal(p: Path, direction) -> None:
    """Refuse a header whose direction matrix (``direction``, n² numbers, ITK's) is not a rotation or
    a reflection: a shear or a scaled axis is no voxel grid ITK resamples or a scanner writes, and
    ITK's filters would treat it as orthonormal (and its NIfTI writer coerces it), placing voxels
    elsewhere than the header says without a word."""
    n = int(round(len(direction) ** 0.5))  # a 2-D or 4-D image: refused after reading, as not 3-D
    d = np.asarray(direction, float).reshape(n, n)
    off = float(np.abs(d.T @ d - np.eye(n)).max())
    if off > ORTHONORMAL_TOLERANCE:
        rows = "; ".join(" ".join(f"{v:g}" for v in row) for row in d)
        raise ReadError(f"{p}: the header's direction matrix [{rows}] is not orthonormal (DᵀD differs from the "
                        f"identity by {off:.3g}): a sheared or scaled grid; lungdeform reads rotations only")


def _check_nifti_length(p: Path) -> None:
    """Refuse a NIfTI-1 file (``.nii``, or its gzip stream for ``.nii.gz``) that ends before the voxels
    its header promises (vox_offset plus dims × bitpix bytes): ITK reads a truncated file without an
    error, the missing voxels as 0 (measured with SimpleITK 2.5: half a mask's .nii.gz read as the
    other half of the lung gone). A gzip stream cut short is refused the same way."""
    opener = gzip.open if p.name.lower().endswith(".gz") else open
    try:
        with opener(p, "rb") as fh:
            raw = fh.read(348)
            endian = next((e for e in "<>" if len(raw) == 348 and struct.unpack(e + "i", raw[:4])[0] == 348), None)
            if endian is None:
                return  # NIfTI-2 or none at all: ITK says what is wrong with it
            dims = struct.unpack(endian + "8h", raw[40:56])
            bitpix = struct.unpack(endian + "h", raw[72:74])[0]
            offset = struct.unpack(endian + "f", raw[108:112])[0]
            if not 0 <= offset < 2 ** 31:
                return  # a vox_offset that is no offset: ITK says what is wrong with it
            offset = int(offset)
            voxels = int(np.prod([max(d, 1) for d in dims[1:1 + min(max(dims[0], 1), 7)]], dtype=np.int64))
            need = max(offset, 348) + voxels * max(bitpix, 8) // 8
            have = len(raw) + _bytes_available(fh, need - len(raw))
    except (OSError, EOFError, zlib.error):
        have, need = -1, 0
    if have < need:
        what = "its gzip stream is damaged" if have < 0 else f"it holds {have} of the {need} bytes its header promises"
        raise ReadError(f"{p}: truncated NIfTI file ({what}); the missing voxels would read as 0")


def _bytes_available(fh, want: int) -> int:
    """How many of the next ``want`` bytes ``fh`` holds (read in 4 MiB blocks, stopping at ``want``)."""
    got = 0
    while got < want:
        block = fh.read(min(1 << 22, want - got))
        if not block:
            break
        got += len(block)
    return got


def _check_inflate(p: Path, name: str, head: bytes, reader: sitk.ImageFileReader) -> None:
    """Refuse a single-file image whose header (``reader``, information read) claims more voxel
    bytes than the file can hold even deflated at the most (:data:`MAX_INFLATE`)."""
    if not name.endswith((".nii", ".nii.gz", ".mha", ".nrrd")):
        return
    if name.endswith(".mha") and not re.search(rb"ElementDataFile\s*=\s*LOCAL", head):
        return
    if name.endswith(".nrrd") and re.search(rb"^data ?file:", head, re.M | re.I):
        return
    claimed = _voxel_bytes(reader)
    if claimed > MAX_INFLATE * p.stat().st_size:
        raise ReadError(f"{p}: header claims {'x'.join(map(str, reader.GetSize()))} voxels "
                        f"({claimed:.3g} bytes), more than the {p.stat().st_size}-byte file can hold: damaged header")


def _voxel_bytes(reader: sitk.ImageFileReader) -> float:
    """The bytes of voxel data the header (``reader``, information read) describes."""
    bits = re.search(r"(\d+)-bit", sitk.GetPixelIDValueAsString(reader.GetPixelID()))
    return float(np.prod(reader.GetSize(), dtype=np.float64)) * reader.GetNumberOfComponents() * (
        int(bits.group(1)) // 8 if bits else 1)


def _check_meta_length(p: Path, head: bytes, claimed: float) -> None:
    """Refuse a single-file MetaImage (``ElementDataFile = LOCAL``) that ends before its voxels
    (``claimed`` bytes, or its ``CompressedDataSize``): ITK's own refusal printed two lines of its
    own and "No such file or directory", naming nothing that is wrong."""
    end = re.search(rb"^\s*ElementDataFile\s*=[ \t]*LOCAL[ \t]*\r?\n", head, re.M)
    if end is None:
        return
    if re.search(rb"^\s*CompressedData\s*=[ \t]*True", head[:end.end()], re.M | re.I):
        size = re.search(rb"^\s*CompressedDataSize\s*=[ \t]*(\d+)", head[:end.end()], re.M)
        if size is None:
            return  # ITK inflates to the end of the file
        claimed = float(size.group(1))
    have = p.stat().st_size - end.end()
    if have < claimed:
        raise ReadError(f"{p}: truncated MetaImage file (it holds {have} of the {claimed:.0f} bytes of voxel data "
                        "its header promises)")


def _check_text_header(p: Path, name: str, head: bytes) -> None:
    """Refuse a text header (MetaImage, NRRD) whose dimension count is absurd (over 10: ITK spins on
    NDims = 3e14), and a MetaImage data file given as a file pattern."""
    # (2-D or 4-D images are refused after reading, with the usual message)
    key = rb"^\s*NDims\s*=[ \t]*(\S*)" if name.endswith((".mha", ".mhd")) else rb"^dimension:[ \t]*(\S*)"
    # every occurrence: a header may repeat the key, and ITK does not read the first one only
    counts = re.findall(key, head, re.M) if name.endswith((".mha", ".mhd", ".nrrd", ".nhdr")) else []
    for ndims in counts:
        if not (ndims.isdigit() and 1 <= int(ndims) <= 10):
            raise ReadError(f"{p}: expected a 3-D image, the header gives {ndims.decode(errors='replace')!r} "
                            "dimensions")
    datafile = re.search(rb"^\s*ElementDataFile\s*=[ \t]*([^\r\n]*)", head, re.M)
    if name.endswith((".mha", ".mhd")) and datafile and b"%" in datafile.group(1):
        # a printf-style file pattern: ITK divides by zero on a malformed one and the process dies (SIGFPE)
        raise ReadError(f"{p}: ElementDataFile {datafile.group(1).decode(errors='replace').strip()!r} is a file "
                        "pattern; lungdeform reads LOCAL data, LIST or one data file")


def read_image(path, *, max_voxels=None, series=None, ignored: list | None = None) -> Image:
    """Read a 3-D image with SimpleITK: NIfTI, MetaImage (.mha/.mhd), NRRD, or a DICOM directory.

    Frame: ITK reports every format in LPS. For NIfTI this means ITK has already negated the
    first two rows of the file's RAS qform/sform; checked on Coronacases_001 (nibabel affine
    ``diag(-0.81, 0.81, 1)``, offset ``(213.1, -206.9, -220.1)`` RAS; ITK direction
    ``diag(1, -1, 1)``, origin ``(-213.1, 206.9, -220.1)`` LPS: the same voxels land on the same
    points), and tested in tests/io/test_image.py. So no conversion is done here.

    Voxels: a float image holding NaN or ±inf is refused (:class:`ReadError` naming the file and the
    first such voxel).

    DICOM: a folder, a parent folder of one series, or one file of a series
    (:func:`~lungdeform.io.dicom.series.dicom_series_files`), its slices checked (:func:`~lungdeform.io.dicom.series.dicom_series_geometry`: one
    orientation, evenly spaced, no gantry tilt). Every header is checked before any voxel is read:
    a grid over ``max_voxels`` (:func:`~lungdeform.io.grid.voxel_limit`) and grid numbers that are not finite are
    refused. Raises :class:`ReadError` naming the path when it is missing, empty, unreadable,
    ambiguous (several series) or not 3-D scalar. A DICOM folder as exports come is read
    (:mod:`~lungdeform.io.dicom.folder`: its RTSTRUCT, RTPLAN, RTDOSE, localizer, non-DICOM files left
    out); ``series`` (:class:`~lungdeform.io.dicom.folder.SeriesChoice`) chooses among several CT
    series, and ``ignored``, when given, gets the line naming what else the folder held.
    """

    p = Path(path)
    if not p.exists():
        raise ReadError(f"{p}: no such file or directory")
    try:
        if not p.is_dir() and p.stat().st_size == 0:
            raise ReadError(f"{p}: file is empty")
        if is_dicom_series_path(p):
            img = read_series(p, max_voxels, series, ignored)
        else:
            if not p.name.lower().endswith(IMAGE_SUFFIXES):
                raise ReadError(f"{p}: unknown image format (supported: {', '.join(IMAGE_SUFFIXES)}, "
                                "a DICOM file or folder)")
            _check_header(p, max_voxels)
            img = sitk.ReadImage(str(p))
    except LungdeformError:
        raise
    except Exception as exc:  # SimpleITK raises RuntimeError with a long multi-line text
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        detail = next((ln for ln in lines if "rror" in ln or "nable" in ln), lines[-1] if lines else "")
        raise ReadError(f"{p}: cannot read image ({detail[:200]})") from exc
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise ReadError(
            f"{p}: expected a 3-D scalar image, got {img.GetDimension()}-D with "
            f"{img.GetNumberOfComponentsPerPixel()} components per voxel"
        )
    array = sitk.GetArrayFromImage(img)
    _check_finite(array, p)
    if array.dtype.kind == "f" and p.name.lower().endswith((".nii", ".nii.gz")):
        _check_nifti_voxels(p)  # ITK reads a NaN or inf NIfTI voxel as 0: looked for in the file itself
    return Image(
        array=array,
        spacing=np.array(img.GetSpacing()),
        origin=np.array(img.GetOrigin()),
        direction=np.array(img.GetDirection()).reshape(3, 3),
        source=str(p),
    )


def _check_finite(array: np.ndarray, p: Path) -> None:
    """ReadError naming ``p`` when a float image holds NaN or ±inf voxels: no CT number or mask
    value is, and each consumer would coerce them silently (a NaN voxel fails every threshold, so
    it left a hole in a mask, and went through a warp into its output)."""
    if array.dtype.kind != "f":
        return
    bad = ~np.isfinite(array)
    if bad.any():
        k, j, i = (int(v[0]) for v in np.nonzero(bad))
        raise ReadError(f"{p}: {int(bad.sum())} voxel(s) are not finite (NaN or inf), the first at index (x, y, z) "
                        f"({i}, {j}, {k}) = {array[k, j, i]}; a CT or mask holds finite numbers only")


#: NIfTI-1 float datatypes (header byte 70): float32, float64
_NIFTI_FLOATS = {16: "f4", 64: "f8"}


def _check_nifti_voxels(p: Path) -> None:
    """ReadError naming ``p`` when the float voxels of a NIfTI-1 file hold NaN or ±inf. ITK's NIfTI
    reader returns such voxels as 0 (measured with SimpleITK 2.x: NaN and inf written, 0.0 read), so
    a NaN region of a CT would read as 0 HU, soft tissue, without a word; the file's own bytes are
    scanned instead (after ITK read it: the header is sound)."""
    opener = gzip.open if p.name.lower().endswith(".gz") else open
    with opener(p, "rb") as fh:
        raw = fh.read(348)
        endian = next((e for e in "<>" if len(raw) == 348 and struct.unpack(e + "i", raw[:4])[0] == 348), None)
        if endian is None:
            return
        dims = struct.unpack(endian + "8h", raw[40:56])
        code = _NIFTI_FLOATS.get(struct.unpack(endian + "h", raw[70:72])[0])
        if code is None:
            return
        dtype = np.dtype(endian + code)
        fh.seek(int(struct.unpack(endian + "f", raw[108:112])[0]))
        total, seen, chunk = int(np.prod(dims[1:1 + max(dims[0], 1)], dtype=np.int64)), 0, 1 << 22
        while seen < total:
            block = np.frombuffer(fh.read(min(chunk, total - seen) * dtype.itemsize), dtype)
            if block.size == 0:
                return
            bad = np.flatnonzero(~np.isfinite(block))
            if bad.size:
                i, j, k = np.unravel_index(seen + int(bad[0]), (dims[1], max(dims[2], 1), max(dims[3], 1)), order="F")
                raise ReadError(f"{p}: voxel (x, y, z) ({i}, {j}, {k}) is {block[bad[0]]} in the file (ITK would read it "
                                "as 0); a CT or mask holds finite numbers only")
            seen += block.size


def write_suffix(path) -> str:
    """The format suffix (:data:`WRITE_SUFFIXES`) of an output path, or :class:`InputError` naming it."""
    path = Path(path)
    name = path.name.lower()
    for suffix in WRITE_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    raise InputError(f"{path}: unknown output image format (use {', '.join(WRITE_SUFFIXES)})")


def to_sitk(array, spacing, origin, direction) -> sitk.Image:
    """A SimpleITK image of ``array`` (``(z, y, x)`` scalar or ``(z, y, x, c)`` vector voxels) with the
    grid ``spacing``, ``origin`` (mm, LPS) and ``direction`` (3, 3) of :class:`Image`."""
    a = np.asarray(array)
    img = sitk.GetImageFromArray(a, isVector=a.ndim == 4)
    img.SetSpacing([float(x) for x in np.asarray(spacing, float)])
    img.SetOrigin([float(x) for x in np.asarray(origin, float)])
    img.SetDirection([float(x) for x in np.asarray(direction, float).ravel()])
    return img


def write_image(path, array, spacing, origin, direction, *, max_voxels=None) -> Path:
    """Write ``array`` (scalar ``(z, y, x)`` or vector ``(z, y, x, c)``, its dtype kept) on the given grid
    to ``path`` (.mha, .nii.gz, .nii or .nrrd by its name), atomically. A vector image of 3 float
    components is what ITK, elastix, plastimatch and 3D Slicer read as a displacement field (LPS mm
    in .mha/.nrrd; ITK writes NIfTI vector images as intent "vector"). A grid over the cap
    (:func:`check_grid`) is refused with :class:`InputError` before anything is written."""
    p = Path(path)
    suffix = write_suffix(p)
    check_grid(np.shape(array)[:3][::-1], p, max_voxels, InputError)
    img = to_sitk(array, spacing, origin, direction)
    with atomic_path(p, suffix=suffix) as tmp:
        sitk.WriteImage(img, str(tmp), True)
    return p


def resample_image(image: Image, field, *, label: bool = False, default: float | None = None,
                   grid: Image | None = None) -> Image:
    """``image`` resampled on its own grid (or on ``grid``'s: its shape, spacing, origin and direction)
    through the displacement field ``field : (z, y, x, 3)`` mm LPS on that output grid (the ITK
    resampling convention: output voxel ``y`` takes the input at ``y + field(y)``): linear
    interpolation, or nearest neighbour with ``label`` (labels kept as they are); pixel type kept.
    Outside the image: ``default`` (0 for labels, else the image's minimum, e.g. air in a CT)."""
    img = to_sitk(image.array, image.spacing, image.origin, image.direction)
    g = image if grid is None else grid
    fill = (0.0 if label else float(np.min(image.array))) if default is None else float(default)
    out = _resample(img, field, g, sitk.sitkNearestNeighbor if label else sitk.sitkLinear, fill, image.source)
    return Image(sitk.GetArrayFromImage(out), g.spacing, g.origin, g.direction, image.source)


def resample_channels(image: Image, channels, field, *, grid: Image | None = None) -> np.ndarray:
    """``channels : (z, y, x, c)`` values on ``image``'s grid resampled together, linearly, as
    :func:`resample_image` does (one pass: the field is interpolated once for all ``c``): ``(z', y',
    x', c) float32`` on ``grid``'s grid (``image``'s without one); 0 outside the image."""
    a = np.asarray(channels, np.float32)
    if a.ndim != 4 or a.shape[:3] != image.array.shape:
        raise InputError(f"{image.source}: channels of shape {a.shape}, expected {image.array.shape} + (c,)")
    img = to_sitk(a, image.spacing, image.origin, image.direction)
    g = image if grid is None else grid
    return sitk.GetArrayFromImage(_resample(img, field, g, sitk.sitkLinear, 0.0, image.source)).reshape(
        tuple(g.array.shape if hasattr(g, "array") else g.shape) + (a.shape[3],))


def _resample(img: sitk.Image, field, g, interpolator, fill: float, source: str) -> sitk.Image:
    """``img`` resampled on ``g``'s grid through ``field : (z, y, x, 3)`` mm LPS on that grid."""
    shape = tuple(g.array.shape) if hasattr(g, "array") else tuple(g.shape)
    f = np.asarray(field, np.float64)
    if f.shape != shape + (3,):
        raise InputError(f"{source}: the field has shape {f.shape}, the output grid {shape} (+ 3 components)")
    target = to_sitk(np.zeros(shape, np.uint8), g.spacing, g.origin, g.direction)
    transform = sitk.DisplacementFieldTransform(to_sitk(f, g.spacing, g.origin, g.direction))
    return sitk.Resample(img, target, transform, interpolator, fill, img.GetPixelID())
