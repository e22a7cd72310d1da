"""Reading 3-D medical images: NIfTI, MetaImage (.mha/.mhd), NRRD and DICOM series.

:func:`read_image` reads a file or a DICOM folder with SimpleITK into an :class:`Image` and refuses
what is missing, empty, unreadable, ambiguous (several DICOM series) or not 3-D scalar, with a
:class:`ReadError` naming the path; :func:`dicom_series_files` picks the series a path names.

Frames and units: arrays follow SimpleITK: ``array`` is indexed ``[k, j, i]`` = ``[z, y, x]``;
spacing (mm), origin (mm, LPS world) and voxel indices ``ijk`` are ordered ``(x, y, z)``; the
columns of ``direction`` are the index axes in LPS. :func:`index_to_world` maps ``ijk : (n, 3)
float`` to world points ``(n, 3) float`` mm LPS.
"""

from __future__ import annotations

import gzip
import os
import re
import struct
import zlib
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from lungdeform.atomic import atomic_path
from lungdeform.errors import InputError, LungdeformError, ReadError

from .slices import GEOMETRY_TAGS, SliceGeometry, check_slices, check_spacing

IMAGE_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")
#: deflate (gzip, zlib) never expands data more than about 1032 times
MAX_INFLATE = 1032
#: Suffixes :func:`write_image` writes (single-file formats, so that a write is atomic).
WRITE_SUFFIXES = (".mha", ".nii.gz", ".nii", ".nrrd")
#: DICOM value representations whose explicit-VR element header holds a 4-byte length (PS3.5 7.1.2)
_LONG_VRS = frozenset((b"OB", b"OW", b"OF", b"OD", b"OL", b"OV", b"SQ", b"UC", b"UR", b"UT", b"UN", b"SV", b"UV"))
#: every value representation of PS3.5 Table 6.2-1
_VRS = _LONG_VRS | frozenset(v.encode() for v in (
    "AE AS AT CS DA DS DT FL FD IS LO LT PN SH SL SS ST TM UI UL US").split())
_IMPLICIT_LE, _BIG_ENDIAN, _DEFLATED = b"1.2.840.10008.1.2", b"1.2.840.10008.1.2.2", b"1.2.840.10008.1.2.1.99"
#: Default largest grid read or written, in voxels: 2^29 ≈ 5.4e8 (a CT of 512 × 512 × 2000 slices
#: fits; 1000^3 does not). Raised by :data:`MAX_VOXELS_ENV` or a ``max_voxels`` argument.
MAX_VOXELS = 2 ** 29
#: The environment variable that raises (or lowers) :data:`MAX_VOXELS` (``lungdeform --max-voxels`` sets it).
MAX_VOXELS_ENV = "LUNGDEFORM_MAX_VOXELS"
#: MetaImage header keys that hold numbers placing the grid (ITK reads "nan" or a missing value as 0),
#: and how many: "n" NDims, "nn" NDims squared.
_META_GEOMETRY = {"Offset": "n", "Origin": "n", "Position": "n", "ElementSpacing": "n", "ElementSize": "n",
                  "CenterOfRotation": "n", "TransformMatrix": "nn", "Rotation": "nn", "Orientation": "nn"}


@dataclass(frozen=True, eq=False)
class Image:
    """A 3-D scalar image in the ITK/LPS convention.

    Attributes
    ----------
    array : (z, y, x) array
        Voxel values, indexed ``[k, j, i]`` as SimpleITK gives them.
    spacing : (3,) float
        Voxel size in mm along ``(i, j, k)`` = ``(x, y, z)`` index axes.
    origin : (3,) float
        World position (mm, LPS) of the centre of voxel ``(0, 0, 0)``.
    direction : (3, 3) float
        Columns are the unit directions of the index axes ``i, j, k`` in LPS world.
    source : str
        The file or folder it came from (used in messages).
    """

    array: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    source: str = "image"

    def __post_init__(self):
        a = np.asarray(self.array)
        if a.ndim != 3:
            raise InputError(f"{self.source}: image array must be 3-D (z, y, x), got shape {a.shape}")
        sp = np.asarray(self.spacing, dtype=np.float64).reshape(3)
        org = np.asarray(self.origin, dtype=np.float64).reshape(3)
        d = np.asarray(self.direction, dtype=np.float64).reshape(3, 3)
        for name, value in (("spacing", sp), ("origin", org), ("direction", d)):
            if not np.isfinite(value).all():
                raise InputError(f"{self.source}: {name} must be finite, got {value.tolist()}")
        if not (sp > 0).all():
            raise InputError(f"{self.source}: spacing must be positive, got {sp}")
        if abs(abs(np.linalg.det(d)) - 1.0) > 1e-3:
            raise InputError(f"{self.source}: direction must be orthonormal, det = {np.linalg.det(d):.4g}")
        for name, value in (("array", a), ("spacing", sp), ("origin", org), ("direction", d)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def index_to_world(self, ijk) -> np.ndarray:
        """``(n, 3)`` voxel indices (i=x, j=y, k=z) -> ``(n, 3) float`` mm LPS."""
        return index_to_world(ijk, self.spacing, self.origin, self.direction)


def index_to_world(ijk, spacing, origin, direction) -> np.ndarray:
    """World points ``(n, 3) float`` mm LPS of voxel indices ``ijk : (n, 3) float`` (i, j, k).

    ``world = origin + direction @ (spacing * ijk)`` (ITK's TransformContinuousIndexToPhysicalPoint).
    """
    ijk = np.asarray(ijk, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(direction, dtype=np.float64).reshape(3, 3)
    return np.ascontiguousarray((ijk * np.asarray(spacing, float)) @ d.T + np.asarray(origin, float))


def is_image_path(path) -> bool:
    """True for a directory (DICOM), a DICOM file, or a file with an image suffix (:data:`IMAGE_SUFFIXES`)."""
    p = Path(path)
    return p.is_dir() or p.name.lower().endswith(IMAGE_SUFFIXES) or is_dicom_file(p)


def is_dicom_file(path) -> bool:
    """True for a file named ``*.dcm``/``*.ima`` or holding the DICOM preamble (``DICM`` at byte 128)."""
    p = Path(path)
    if not p.is_file():
        return False
    if p.name.lower().endswith((".dcm", ".ima", ".dicom")):
        return True
    try:
        with open(p, "rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return len(head) == 132 and head[128:132] == b"DICM"


@contextmanager
def _quiet_itk():
    """Silence ITK's own warnings on stderr (e.g. GDCM's "No Series were found"): the CLI's
    contract is one error line; what went wrong is said by the :class:`ReadError` raised instead."""

    before = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(before)


def _element_header(h: bytes, explicit: bool) -> tuple[int, int, bytes, int, int]:
    """``(group, element, VR, value length, header bytes)`` of the little-endian element header ``h``
    (12 bytes, fewer at the end of a file); VR ``b""`` when implicit or an item/delimiter tag."""
    group, elem = struct.unpack("<HH", h[:4])
    if group == 0xFFFE or not (explicit or group == 2):  # items and delimiters; implicit VR
        return group, elem, b"", struct.unpack("<I", h[4:8])[0], 8
    vr = h[4:6]
    if vr in _LONG_VRS:
        return group, elem, vr, (struct.unpack("<I", h[8:12])[0] if len(h) == 12 else 0xFFFFFFFE), 12
    return group, elem, vr, struct.unpack("<H", h[6:8])[0], 8


def check_dicom_file(path) -> None:
    """Refuse, before GDCM parses it, a DICOM file whose element headers are damaged: an explicit value
    representation that is none of the standard's (PS3.5 Table 6.2-1), or a value length larger than
    what is left of the file. GDCM tries to make sense of such a file and allocates what a length read
    from the wrong bytes says (seconds and gigabytes for a file of a few hundred bytes).

    Walks the element headers only (sequences and items flatly, PS3.5 7.5), up to the pixel data:
    after the ``DICM`` preamble, from byte 132, the file meta information (group 0002) first (PS3.10
    7.1); without it, from byte 0, as explicit VR when a standard VR sits at bytes 4–5, else as implicit
    VR little endian (the default transfer syntax), starting with group 0002 or a data set group (0008
    or above). Big-endian or deflated data sets and sequences of unknown content (UN, undefined length)
    are left to GDCM. tests/fuzz/fuzz_image_dicom.py feeds it damaged files."""
    p = Path(path)
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(132)
        if len(head) < 8:
            return
        if head[128:132] == b"DICM":
            pos, explicit = 132, True
        else:  # no preamble: an explicit-VR element first, else implicit VR (GDCM reads both)
            pos, explicit = 0, head[4:6] in _VRS
        syntax, guessed = None, not explicit and pos == 0  # implicit without preamble: maybe no DICOM at all
        pixel, nested = {}, False  # the image pixel module's numbers (0028,xxxx); inside a sequence yet?
        while pos + 8 <= size:
            fh.seek(pos)
            h = fh.read(12)
            group, elem, vr, length, hdr = _element_header(h, explicit)
            where = (f"{p} is not a readable DICOM image slice: no preamble, and read as implicit VR its element "
                     f"({group:04X},{elem:04X}) at byte {pos}" if guessed else
                     f"{p}: damaged DICOM file: element ({group:04X},{elem:04X}) at byte {pos}")
            if pos == 132 and group != 0x0002:  # PS3.10 7.1: the file meta information follows "DICM"
                raise ReadError(f"{where}: the file meta information (group 0002) must follow the preamble")
            if pos == 0 and group != 0x0002 and group < 0x0008:  # groups 0000-0007 are no file's first
                raise ReadError(f"{p} is not a readable DICOM image slice: no preamble, and its first element "
                                f"({group:04X},{elem:04X}) is neither file meta information (group 0002) nor a "
                                "data set element (group 0008 or above)")
            if vr and vr not in _VRS:
                raise ReadError(f"{where} has no valid value representation ({vr!r})")
            if length == 0xFFFFFFFF:  # undefined length: a sequence or encapsulated pixels, walked into
                if vr == b"UN" or (group, elem) == (0x7FE0, 0x0010):
                    return
                pos += hdr
                continue
            if pos + hdr + length > size:
                raise ReadError(f"{where} claims {length} bytes, {size - pos - hdr} are left")
            if (group, elem) == (0x0002, 0x0010):
                fh.seek(pos + hdr)
                syntax = fh.read(length).rstrip(b"\0 ")
            if group != 2 and syntax in (_BIG_ENDIAN, _DEFLATED):
                return
            if group == 0x0028 and elem in _PIXEL_TAGS and length == 2 and (group, elem) not in pixel:
                fh.seek(pos + hdr)
                pixel[(group, elem)] = struct.unpack("<H", fh.read(2))[0]
                _check_pixel_module(pixel, where)
            if (group, elem) == (0x7FE0, 0x0010):
                if not nested:
                    _check_pixel_length(pixel, length, where)
                return
            nested = nested or vr == b"SQ" or group == 0xFFFE
            if syntax is not None:
                explicit = syntax != _IMPLICIT_LE
            pos += hdr if vr == b"SQ" or group == 0xFFFE else hdr + length  # into sequences and items


#: (0028,0002) SamplesPerPixel, (0028,0010) Rows, (0028,0011) Columns, (0028,0100) BitsAllocated,
#: (0028,0101) BitsStored: the numbers that size the pixel data (PS3.3 C.7.6.3).
_PIXEL_TAGS = (0x0002, 0x0010, 0x0011, 0x0100, 0x0101)


def _check_pixel_module(pixel: dict, where: str) -> None:
    """ReadError (``where`` names the file and element) for BitsAllocated other than 1 or a multiple
    of 8 up to 64 (PS3.5 8.1.1), or BitsStored outside 1…BitsAllocated: GDCM sizes its buffers from
    them, and other values over the pixel data can overrun the heap and kill the process."""
    ba, bs = pixel.get((0x0028, 0x0100)), pixel.get((0x0028, 0x0101))
    if ba is not None and not (ba == 1 or (ba % 8 == 0 and 8 <= ba <= 64)):
        raise ReadError(f"{where}: BitsAllocated is {ba}, not 1 or a multiple of 8 up to 64")
    if ba is not None and bs is not None and not 1 <= bs <= ba:
        raise ReadError(f"{where}: BitsStored is {bs}, not 1…{ba} (BitsAllocated)")


def _check_pixel_length(pixel: dict, length: int, where: str) -> None:
    """ReadError when native pixel data of ``length`` bytes is shorter than one frame of Rows ×
    Columns × SamplesPerPixel × BitsAllocated (when all of them were read)."""
    rows, cols, ba = (pixel.get((0x0028, e)) for e in (0x0010, 0x0011, 0x0100))
    if rows is None or cols is None or ba is None:
        return
    need = (rows * cols * pixel.get((0x0028, 0x0002), 1) * ba + 7) // 8
    if length < need:
        raise ReadError(f"{where} holds {length} bytes of pixel data, and one frame of {rows} × {cols} "
                        f"at {ba} bits needs {need}")


def _series_in(folder: Path) -> list[tuple[str, tuple[str, ...]]]:
    """``[(series UID, file names)]`` of the DICOM series directly in ``folder``, largest first
    (every DICOM file of the folder checked first, :func:`check_dicom_file`)."""

    with os.scandir(folder) as entries:
        for entry in sorted(entries, key=lambda e: e.name):
            if entry.is_file() and is_dicom_file(entry.path):
                check_dicom_file(entry.path)
    reader = sitk.ImageSeriesReader
    with _quiet_itk():
        ids = reader.GetGDCMSeriesIDs(str(folder))
        series = [(sid, tuple(reader.GetGDCMSeriesFileNames(str(folder), sid))) for sid in ids]
    return sorted(series, key=lambda s: -len(s[1]))


def dicom_series_files(path) -> list[str]:
    """The files of the DICOM series that ``path`` names, in slice order.

    ``path`` may be a folder holding the series (the largest series in it is taken, but two or more
    series of that size, e.g. the phases of a 4-D CT, are refused as ambiguous), a parent folder
    whose subfolders hold exactly one series, or one file of the series (its series is read from
    its folder). Raises :class:`ReadError` naming the path when there is no series, or more than
    one to choose from.
    """
    p = Path(path)
    if p.is_file():
        folder = p.parent
        target = p.resolve()
        for sid, files in _series_in(folder):
            if any(Path(f).resolve() == target for f in files):
                return list(files)
        raise ReadError(f"{p}: not a readable DICOM image slice (no DICOM series in {folder} contains it)")
    series = _series_in(p)
    where = p
    if not series:  # a parent folder (patient/study/series exports): look one or more levels down
        found, visited = [], 0
        for root, dirs, _files in os.walk(p):
            dirs.sort()
            if Path(root) != p:
                found += [(Path(root), sid, files) for sid, files in _series_in(Path(root))]
            visited += 1
            if len(found) > 20 or visited > 2000:  # enough to say it is ambiguous; do not crawl a disk
                break
        if not found:
            raise ReadError(f"{p}: no DICOM series in this directory or its subfolders")
        if len(found) > 1:
            listed = "; ".join(f"{d.relative_to(p)} ({len(files)} files)" for d, _, files in found[:6])
            raise ReadError(f"{p}: holds no DICOM series itself, and its subfolders hold {len(found)}"
                            f"{'+' if len(found) > 20 else ''} series ({listed}); give the folder of one")
        where, sid, files = found[0]
        series = [(sid, files)]
    if len(series) > 1 and len(series[1][1]) == len(series[0][1]):
        n_same = sum(len(f) == len(series[0][1]) for _, f in series)
        raise ReadError(f"{where}: holds {len(series)} DICOM series, {n_same} of them with {len(series[0][1])} "
                        "files (e.g. the phases of a 4-D CT): ambiguous; put the series you want in a folder "
                        "of its own")
    return list(series[0][1])


def voxel_limit(max_voxels=None) -> int:
    """The grid-size cap in voxels: ``max_voxels`` when given, else the environment variable
    :data:`MAX_VOXELS_ENV`, else :data:`MAX_VOXELS`; :class:`InputError` naming the one given when it
    is not a positive whole number (``"2e9"`` is one)."""
    source, value = "max_voxels", max_voxels
    if value is None:
        text = os.environ.get(MAX_VOXELS_ENV, "").strip()
        if not text:
            return MAX_VOXELS
        source, value = MAX_VOXELS_ENV, text
    try:
        n = float(value)
    except (TypeError, ValueError):
        n = float("nan")
    if not (np.isfinite(n) and n >= 1 and n == int(n)):
        raise InputError(f"{source} must be a positive whole number of voxels, got {value!r}")
    return int(n)


def check_grid(size, where, max_voxels=None, error: type[Exception] = ReadError) -> None:
    """Refuse a grid of ``size`` voxels per axis over the cap (:func:`voxel_limit`), with ``error``
    (:class:`ReadError` for a read, :class:`InputError` for a write) naming ``where``: checked from
    a header, before any voxel is read or allocated."""
    limit = voxel_limit(max_voxels)
    size = [int(s) for s in size]
    count = int(np.prod(size, dtype=object))
    if count > limit:
        raise error(f"{where}: the image grid {' x '.join(map(str, size))} is {count:,} voxels, over the limit of "
                    f"{limit:,} (raise it with 'lungdeform --max-voxels N' or ${MAX_VOXELS_ENV})")


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
    set) or sform (srow; when its code is set) holds NaN or infinity, before ITK builds its grid."""
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
    with _quiet_itk():
        reader.ReadImageInformation()
    _check_inflate(p, name, head, reader)
    check_grid(reader.GetSize(), p, max_voxels)
    for key, values in (("origin", reader.GetOrigin()), ("spacing", reader.GetSpacing()),
                        ("direction", reader.GetDirection())):
        if not np.isfinite(values).all():
            raise ReadError(f"{p}: the header's {key} {list(values)} is not finite")


def _check_inflate(p: Path, name: str, head: bytes, reader: sitk.ImageFileReader) -> None:
    """Refuse a single-file image whose header (``reader``, information read) claims more voxel
    bytes than the file can hold even deflated at the most (:data:`MAX_INFLATE`)."""
    if not name.endswith((".nii", ".nii.gz", ".mha", ".nrrd")):
        return
    if name.endswith(".mha") and not re.search(rb"ElementDataFile\s*=\s*LOCAL", head):
        return
    if name.endswith(".nrrd") and re.search(rb"^data ?file:", head, re.M | re.I):
        return
    bits = re.search(r"(\d+)-bit", sitk.GetPixelIDValueAsString(reader.GetPixelID()))
    claimed = float(np.prod(reader.GetSize(), dtype=np.float64)) * reader.GetNumberOfComponents() * (
        int(bits.group(1)) // 8 if bits else 1)
    if claimed > MAX_INFLATE * p.stat().st_size:
        raise ReadError(f"{p}: header claims {'x'.join(map(str, reader.GetSize()))} voxels "
                        f"({claimed:.3g} bytes), more than the {p.stat().st_size}-byte file can hold: damaged header")


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


def dicom_series_geometry(files, where, max_voxels=None) -> SliceGeometry:
    """The geometry of one DICOM series (``files``, any order), its files in order along the slice
    normal, after the grid cap (:func:`check_grid`, from the headers) and, for two or more files,
    the checks of :func:`lungdeform.io.slices.check_slices`; :class:`ReadError` naming ``where``
    and the file."""
    reader = sitk.ImageFileReader()
    reader.SetImageIO("GDCMImageIO")
    slices, size, depth = [], (0, 0), 0
    for f in files:
        reader.SetFileName(str(f))
        try:
            with _quiet_itk():
                reader.ReadImageInformation()
        except RuntimeError as exc:
            raise ReadError(f"{where}: {f} is not a readable DICOM image slice") from exc
        slices.append((str(f), {t: reader.GetMetaData(t).strip() if reader.HasMetaDataKey(t) else ""
                                for t in GEOMETRY_TAGS}))
        got = reader.GetSize()
        size = (max(size[0], got[0]), max(size[1], got[1]))
        depth += int(np.prod(got[2:], dtype=np.int64))
        check_grid((*size, depth), where, max_voxels)
    if len(slices) < 2:
        return SliceGeometry(tuple(s for s, _ in slices), np.zeros(len(slices)), 0.0)
    return check_slices(slices, where)


def read_image(path, *, max_voxels=None) -> Image:
    """Read a 3-D image with SimpleITK: NIfTI, MetaImage (.mha/.mhd), NRRD, or a DICOM directory.

    Frame: ITK reports every format in LPS. For NIfTI this means ITK has already negated the
    first two rows of the file's RAS qform/sform; checked on Coronacases_001 (nibabel affine
    ``diag(-0.81, 0.81, 1)``, offset ``(213.1, -206.9, -220.1)`` RAS; ITK direction
    ``diag(1, -1, 1)``, origin ``(-213.1, 206.9, -220.1)`` LPS: the same voxels land on the same
    points), and tested in tests/io/test_image.py. So no conversion is done here.

    DICOM: a folder, a parent folder of one series, or one file of a series
    (:func:`dicom_series_files`), its slices checked (:func:`dicom_series_geometry`: one
    orientation, evenly spaced, no gantry tilt). Every header is checked before any voxel is read:
    a grid over ``max_voxels`` (:func:`voxel_limit`) and grid numbers that are not finite are
    refused. Raises :class:`ReadError` naming the path when it is missing, empty, unreadable,
    ambiguous (several series) or not 3-D scalar.
    """

    p = Path(path)
    if not p.exists():
        raise ReadError(f"{p}: no such file or directory")
    try:
        if not p.is_dir() and p.stat().st_size == 0:
            raise ReadError(f"{p}: file is empty")
        if p.is_dir() or (not p.name.lower().endswith(IMAGE_SUFFIXES) and is_dicom_file(p)):
            reader = sitk.ImageSeriesReader()
            geometry = dicom_series_geometry(dicom_series_files(p), p, max_voxels)
            reader.SetFileNames(list(geometry.files))
            with _quiet_itk():
                img = reader.Execute()
            check_spacing(img.GetSpacing()[2], geometry, p)
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
    return Image(
        array=sitk.GetArrayFromImage(img),
        spacing=np.array(img.GetSpacing()),
        origin=np.array(img.GetOrigin()),
        direction=np.array(img.GetDirection()).reshape(3, 3),
        source=str(p),
    )


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


def resample_image(image: Image, field, *, label: bool = False, default: float | None = None) -> Image:
    """``image`` resampled on its own grid through the displacement field ``field : (z, y, x, 3)`` mm
    LPS on that grid (the ITK resampling convention: output voxel ``y`` takes the input at
    ``y + field(y)``): linear interpolation, or nearest neighbour with ``label`` (labels kept as they
    are); pixel type and grid kept. Outside the image: ``default`` (0 for labels, else the image's
    minimum, e.g. air in a CT)."""
    img = to_sitk(image.array, image.spacing, image.origin, image.direction)
    f = np.asarray(field, np.float64)
    if f.shape != image.array.shape + (3,):
        raise InputError(f"{image.source}: the field has shape {f.shape}, the image {image.array.shape} (+ 3 components)")
    transform = sitk.DisplacementFieldTransform(to_sitk(f, image.spacing, image.origin, image.direction))
    fill = (0.0 if label else float(np.min(image.array))) if default is None else float(default)
    out = sitk.Resample(img, img, transform, sitk.sitkNearestNeighbor if label else sitk.sitkLinear, fill,
                        img.GetPixelID())
    return Image(sitk.GetArrayFromImage(out), image.spacing, image.origin, image.direction, image.source)
