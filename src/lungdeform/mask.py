"""Mask and label images to closed lung surfaces.

Pipeline of :func:`extract_surface` (each step says what it fixes):

1. select the voxels of the requested labels (None = any non-zero);
2. crop to their bounding box (speed only);
3. keep the largest 6-connected component (stray islands would become extra surface pieces);
4. fill internal cavities (vessels or airways left out of a lung mask would become inner
   surfaces; the model needs the outer lung surface only);
5. pad by one background voxel, so that the surface is closed where the mask touches the volume
   border (the ITK example masks touch the cropped medial face);
6. marching cubes (scikit-image, Lewiner, level 0.5) in voxel index space, then index → world mm
   LPS through spacing, direction and origin; faces are flipped if needed so that the signed
   volume is positive (outward), which also covers ``det(direction) < 0``;
7. volume-preserving Taubin smoothing (:func:`taubin_smooth`) against the voxel staircase;
8. optional decimation to a vertex budget (fast-simplification), then cleanup
   (:func:`clean_mesh`): degenerate and duplicate faces removed, duplicate vertices merged,
   non-manifold fins and pinches removed, so that :func:`lungdeform.mesh.check_surface` passes.

Arrays follow SimpleITK: ``array`` is indexed ``[k, j, i]`` = ``[z, y, x]``; spacing, origin and
voxel indices ``ijk`` are ordered ``(x, y, z)``.
"""

from __future__ import annotations

import dataclasses
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
from scipy import sparse

from .errors import InputError, MaskError, MeshError, ReadError, UnitsError
from .mesh import (
    Surface,
    SurfaceReport,
    check_surface,
    edge_face_counts,
    face_areas,
    face_components,
    non_manifold_vertices,
    orientation_consistent,
    signed_volume,
    unique_edges,
)

IMAGE_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")

#: Lobe label maps (coronacases convention): 1 left upper, 2 left lower, 3 right upper,
#: 4 right middle, 5 right lower lobe.
LOBE_LABELS: dict[str, tuple[int, ...]] = {"left": (1, 2), "right": (3, 4, 5)}


# =========================================================================== image
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
    import SimpleITK as sitk

    before = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(before)


def _series_in(folder: Path) -> list[tuple[str, tuple[str, ...]]]:
    """``[(series UID, file names)]`` of the DICOM series directly in ``folder``, largest first."""
    import SimpleITK as sitk

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


def read_image(path) -> Image:
    """Read a 3-D image with SimpleITK: NIfTI, MetaImage (.mha/.mhd), NRRD, or a DICOM directory.

    Frame: ITK reports every format in LPS. For NIfTI this means ITK has already negated the
    first two rows of the file's RAS qform/sform; checked on Coronacases_001 (nibabel affine
    ``diag(-0.81, 0.81, 1)``, offset ``(213.1, -206.9, -220.1)`` RAS; ITK direction
    ``diag(1, -1, 1)``, origin ``(-213.1, 206.9, -220.1)`` LPS: the same voxels land on the same
    points), and tested in tests/test_mask.py. So no conversion is done here.

    DICOM: a folder, a parent folder of one series, or one file of a series
    (:func:`dicom_series_files`). Raises :class:`ReadError` naming the path when it is missing,
    empty, unreadable, ambiguous (several series) or not 3-D scalar.
    """
    import SimpleITK as sitk

    p = Path(path)
    if not p.exists():
        raise ReadError(f"{p}: no such file or directory")
    try:
        if not p.is_dir() and p.stat().st_size == 0:
            raise ReadError(f"{p}: file is empty")
        if p.is_dir() or (not p.name.lower().endswith(IMAGE_SUFFIXES) and is_dicom_file(p)):
            reader = sitk.ImageSeriesReader()
            reader.SetFileNames(dicom_series_files(p))
            with _quiet_itk():
                img = reader.Execute()
        else:
            if not p.name.lower().endswith(IMAGE_SUFFIXES):
                raise ReadError(f"{p}: unknown image format (supported: {', '.join(IMAGE_SUFFIXES)}, "
                                "a DICOM file or folder)")
            img = sitk.ReadImage(str(p))
    except ReadError:
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


# =========================================================================== labels
def side_mask(image: Image, side: str) -> Image:
    """The ``side`` lung of a lobe label map as a 0/1 image; other images are returned unchanged.

    A lobe map (non-zero labels within 1–5, more than one of them: the coronacases convention of
    :data:`LOBE_LABELS`) gives the voxels of ``LOBE_LABELS[side]``. The convention is checked in
    the world frame (LPS: the left lung lies at larger x): when the chosen lobes' centroid is not on
    ``side`` of the other lobes' centroid, :class:`MaskError` is raised naming the file, rather than
    returning the wrong lung. A binary mask or a single label is returned as it is.
    """
    if side not in LOBE_LABELS:
        raise InputError(f"side must be 'left' or 'right', got {side!r}")
    a = np.asarray(image.array)
    values = np.unique(a[a != 0]) if a.size else np.zeros(0)
    if values.size < 2 or not np.all(np.isin(values, np.arange(1, 6))):
        return image
    want = np.isin(a, LOBE_LABELS[side])
    other = (a != 0) & ~want
    if not want.any():
        raise MaskError(f"{image.source}: lobe labels {sorted(int(v) for v in values)}: none of the {side} lobes "
                        f"{list(LOBE_LABELS[side])}")
    if other.any():
        from scipy import ndimage

        cw = image.index_to_world(np.array([ndimage.center_of_mass(want)[::-1]]))[0]
        co = image.index_to_world(np.array([ndimage.center_of_mass(other)[::-1]]))[0]
        if (cw[0] - co[0]) * (1 if side == "left" else -1) <= 0:
            raise MaskError(f"{image.source}: labels {list(LOBE_LABELS[side])} ({side} lobes in the coronacases "
                            f"convention) lie on the other side (LPS x {cw[0]:.0f} mm vs {co[0]:.0f} mm): "
                            "not a left/right lobe map in that convention")
    return Image(want.astype(np.uint8), image.spacing, image.origin, image.direction,
                 f"{image.source} ({side} lobes {','.join(map(str, LOBE_LABELS[side]))})")


def label_groups(spec) -> dict[str, tuple[int, ...] | None]:
    """Normalise a label selection to ``{group name: labels}``.

    - ``None`` -> ``{"": None}``: one surface of all non-zero voxels;
    - an int or a sequence of ints -> one group, e.g. ``{"labels 1,2": (1, 2)}``;
    - a mapping ``{"left": (1, 2), ...}`` -> as given;
    - a string (CLI form): groups separated by ``;``; a group is ``name=1,2``, a list of
      :data:`LOBE_LABELS` names (``"left,right"`` gives two groups; ``"lungs"`` = both), or a
      comma-separated list of ints (one group).
    """
    if spec is None:
        return {"": None}
    if isinstance(spec, Mapping):
        return {str(k): _as_labels(v, f"labels[{k!r}]") for k, v in spec.items()}
    if isinstance(spec, (int, np.integer)):
        return {f"label {int(spec)}": (int(spec),)}
    if isinstance(spec, str):
        groups: dict[str, tuple[int, ...] | None] = {}
        for part in (s.strip() for s in spec.split(";")):
            if not part:
                continue
            if "=" in part:
                name, values = part.split("=", 1)
                groups[name.strip()] = _parse_ints(values, spec)
                continue
            tokens = [t.strip().lower() for t in part.split(",") if t.strip()]
            if tokens == ["lungs"]:
                groups.update(LOBE_LABELS)
            elif all(t in LOBE_LABELS for t in tokens):
                groups.update({t: LOBE_LABELS[t] for t in tokens})
            else:
                values = _parse_ints(part, spec)
                groups["labels " + ",".join(map(str, values))] = values
        if not groups:
            raise InputError(f"labels: empty selection {spec!r}")
        return groups
    values = _as_labels(spec, "labels")
    return {"labels " + ",".join(map(str, values)): values}


def _parse_ints(text: str, spec: str) -> tuple[int, ...]:
    try:
        values = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise InputError(
            f"labels: cannot read {spec!r}; use names ({', '.join(LOBE_LABELS)}, lungs), "
            "integers '1,2', or 'name=1,2;other=3'"
        ) from None
    if not values:
        raise InputError(f"labels: empty group in {spec!r}")
    return values


def _as_labels(value, name: str) -> tuple[int, ...]:
    arr = np.atleast_1d(np.asarray(value))
    if arr.size == 0 or arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"{name} must be a non-empty sequence of integer labels, got {value!r}")
    return tuple(int(x) for x in arr)


# =========================================================================== pipeline
@dataclass(frozen=True)
class MaskSurface:
    """Result of :func:`extract_surface`.

    ``surface`` passed :func:`check_surface`; ``report`` is that check's report with ``notes``
    (what the pipeline changed) as its repairs; ``timings`` are seconds per stage (mask,
    marching_cubes, smooth, decimate, check).
    """

    surface: Surface
    report: SurfaceReport
    notes: tuple[str, ...]
    components_dropped: int
    voxels_filled: int
    timings: dict[str, float] = field(default_factory=dict)


def mask_to_surface(
    image: Image,
    labels=None,
    *,
    smooth_iterations: int = 10,
    target_vertices: int | None = None,
    name: str | None = None,
) -> Surface:
    """Closed, outward, manifold surface (mm LPS) of ``labels`` in ``image``.

    One-shot form of :func:`extract_surface` (see the module docstring for the steps).
    Raises :class:`MaskError` naming the file and labels when there is no foreground.
    """
    return extract_surface(
        image, labels, smooth_iterations=smooth_iterations,
        target_vertices=target_vertices, name=name,
    ).surface


def extract_surface(
    image: Image,
    labels=None,
    *,
    smooth_iterations: int = 10,
    target_vertices: int | None = None,
    name: str | None = None,
) -> MaskSurface:
    """Surface of the selected labels, with a record of what the pipeline changed.

    ``labels``: None (any non-zero voxel) or a sequence of ints. ``target_vertices``: decimate
    to about this many vertices (None: keep the marching-cubes resolution).
    """
    from scipy import ndimage
    from skimage.measure import marching_cubes

    what = "any non-zero label" if labels is None else f"labels {list(_as_labels(labels, 'labels'))}"
    source = image.source
    name = name or Path(source).name
    if smooth_iterations < 0:
        raise InputError(f"smooth_iterations must be >= 0, got {smooth_iterations}")
    if target_vertices is not None and target_vertices < 100:
        raise InputError(f"target_vertices must be at least 100, got {target_vertices}")
    t = {}
    t0 = time.perf_counter()
    a = image.array
    if labels is None:
        if np.issubdtype(a.dtype, np.floating) or (a.size and a.min() < 0):
            lo, hi = a.min(), a.max()
            if lo < -100:  # a CT in HU, not a mask
                raise MaskError(
                    f"{source}: values {lo:g}..{hi:g} look like a CT, not a mask or label image; "
                    "segment the lungs first"
                )
        fg = a != 0
    else:
        fg = np.isin(a, _as_labels(labels, "labels"))
    if not fg.any():
        raise MaskError(f"{source}: no foreground voxels for {what}")
    notes: list[str] = []
    # crop to the foreground bounding box
    idx = np.nonzero(fg.any(axis=(1, 2)))[0], np.nonzero(fg.any(axis=(0, 2)))[0], np.nonzero(fg.any(axis=(0, 1)))[0]
    lo = np.array([x[0] for x in idx])
    hi = np.array([x[-1] for x in idx]) + 1
    fg = fg[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    # largest 6-connected component
    lab, n = ndimage.label(fg)
    dropped = 0
    if n > 1:
        sizes = np.bincount(lab.ravel())[1:]
        keep = int(np.argmax(sizes)) + 1
        fg = lab == keep
        dropped = n - 1
        notes.append(
            f"kept the largest of {n} mask components; dropped {dropped} "
            f"({int(sizes.sum() - sizes[keep - 1])} voxels)"
        )
    del lab
    filled = ndimage.binary_fill_holes(fg)
    n_filled = int(filled.sum() - fg.sum())
    if n_filled:
        notes.append(f"filled {n_filled} voxels of internal cavities")
    fg = np.pad(filled, 1)
    t["mask"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    try:
        verts_zyx, faces, _, _ = marching_cubes(fg.astype(np.float32), level=0.5, allow_degenerate=False)
    except (ValueError, RuntimeError) as exc:
        raise MaskError(f"{source}: marching cubes failed for {what} ({exc})") from exc
    del fg
    # padded cropped index (z, y, x) -> full-volume index (i, j, k) = (x, y, z)
    ijk = verts_zyx[:, ::-1].astype(np.float64) - 1.0 + lo[::-1]
    v = index_to_world(ijk, image.spacing, image.origin, image.direction)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    v, f, extra = _largest_surface_piece(v, f)
    if extra:
        notes.append(f"dropped {extra} small surface pieces")
    if signed_volume(v, f) < 0:  # index->world flips handedness when det(direction) < 0, etc.
        f = np.ascontiguousarray(f[:, ::-1])
    t["marching_cubes"] = time.perf_counter() - t0
    n_mc = len(v)

    t0 = time.perf_counter()
    if smooth_iterations:
        v = taubin_smooth(v, f, smooth_iterations)
        notes.append(f"Taubin-smoothed ({smooth_iterations} iterations)")
    t["smooth"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if target_vertices is not None and target_vertices < len(v):
        try:
            v, f, cleaned = decimate(v, f, target_vertices)
        except MeshError as exc:
            raise MeshError(f"{name or image.source}: {exc}") from exc
        notes.append(f"decimated {n_mc} -> {len(v)} vertices")
        notes.extend(cleaned)
    t["decimate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        try:
            v, f, report = check_surface(v, f, source=f"{source} ({what})")
        except UnitsError:
            raise
        except MeshError:
            # an undecimated surface has not been cleaned: marching cubes on a real mask can leave
            # fins and sheets touching along an edge (voxels that share only an edge). Clean it only
            # when needed, so that surfaces that pass as they are stay bit-identical.
            v, f, cleaned = clean_mesh(v, f)
            notes.extend(cleaned)
            v, f, report = check_surface(v, f, source=f"{source} ({what})")
    except UnitsError as exc:  # image spacing is in mm: a wrong size is the mask's, not the units'
        size = float(np.linalg.norm(np.ptp(v, axis=0)))
        raise MaskError(
            f"{source}: the surface of {what} is {size:.4g} mm across, not the size of a lung "
            "(check the voxel spacing in the image header)"
        ) from exc
    except MeshError as exc:  # a defect of this pipeline, not of the input: say so
        raise MeshError(f"{exc} [after mask_to_surface; try other smoothing/decimation settings]") from exc
    t["check"] = time.perf_counter() - t0
    report = dataclasses.replace(report, repairs=tuple(notes))
    return MaskSurface(Surface(v, f, name), report, tuple(notes), dropped, n_filled, t)


def _largest_surface_piece(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    n, labels = face_components(f)
    if n > 1:
        f = f[labels == np.argmax(np.bincount(labels))]
    used, inverse = np.unique(f, return_inverse=True)
    return np.ascontiguousarray(v[used]), inverse.reshape(f.shape).astype(np.int64), n - 1


# =========================================================================== smoothing
def umbrella_operator(n_vertices: int, faces: np.ndarray) -> sparse.csr_matrix:
    """Sparse ``(n, n)`` umbrella Laplacian ``L = D⁻¹A − I`` (uniform weights over edge neighbours)."""
    f = np.asarray(faces, dtype=np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    adj = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices))
    adj.data[:] = 1.0  # an edge shared by two faces was summed twice
    deg = np.asarray(adj.sum(axis=1)).ravel()
    inv = sparse.diags(1.0 / np.where(deg > 0, deg, 1.0))
    return (inv @ adj - sparse.diags((deg > 0).astype(float))).tocsr()


def taubin_smooth(
    vertices: np.ndarray, faces: np.ndarray, iterations: int, lam: float = 0.5, mu: float = -0.53
) -> np.ndarray:
    """Taubin λ|μ smoothing: ``v += λ L v`` then ``v += μ L v``, ``iterations`` times.

    Removes high-frequency noise (voxel staircases) while keeping low frequencies, so the volume
    stays nearly constant (plain Laplacian smoothing, μ = 0, shrinks the surface).
    ``vertices : (n, 3) float`` mm; returns a new ``(n, 3) float`` array.
    """
    if not 0 < lam < -mu:
        raise InputError(f"Taubin smoothing needs 0 < lam < -mu, got lam={lam}, mu={mu}")
    return _smooth(vertices, faces, iterations, (lam, mu))


def laplacian_smooth(vertices: np.ndarray, faces: np.ndarray, iterations: int, lam: float = 0.5) -> np.ndarray:
    """Plain umbrella smoothing ``v += λ L v`` (shrinks; kept for comparison and tests)."""
    return _smooth(vertices, faces, iterations, (lam,))


def _smooth(vertices, faces, iterations, factors) -> np.ndarray:
    v = np.array(vertices, dtype=np.float64)
    lap = umbrella_operator(len(v), np.asarray(faces, dtype=np.int64))
    for _ in range(int(iterations)):
        for k in factors:
            v += k * (lap @ v)
    return v


# =========================================================================== decimation
def decimate(
    vertices: np.ndarray, faces: np.ndarray, target_vertices: int
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Quadric decimation (fast-simplification) to about ``target_vertices``, then :func:`clean_mesh`.

    A closed surface of genus g has ``F = 2V + 4g - 4`` faces, so the face target is
    ``2 * target_vertices``. fast-simplification now and then folds two sheets onto one edge
    (edges with 4 faces) that cleanup cannot undo without opening the surface; the result is
    then checked with :func:`check_surface` and, if it fails, decimation is rerun with the
    target nudged by 1 %, 2 %, ... 6 % and then with aggressiveness 5, then with targets 10–30 %
    smaller (deterministic; at most 26 tries; one is enough for most targets). Returns
    ``(vertices, faces, notes)``; raises :class:`MeshError` if no try gives a valid surface.
    """
    import fast_simplification

    n_faces = len(faces)
    if 2 * int(target_vertices) >= n_faces:
        return vertices, faces, []
    v64 = np.array(vertices, dtype=np.float64, order="C")  # writable copies: the binding refuses
    f32 = np.array(faces, dtype=np.int32, order="C")  # read-only arrays (Surface's)
    errors = []
    # then coarser targets (a slit hole a few percent either side can persist; measured on the
    # POPI right lung, 162k vertices: every target from 18,000 to 22,000 failed, 17,000 passed)
    tries = [(nudge, agg) for agg in (7, 5) for nudge in (0, 1, -1, 2, -2, 3, -3, 4, -4, 6, -6)]
    tries += [(nudge, 7) for nudge in (-10, -15, -20, -30)]
    for nudge, agg in tries:
        target = int(round(target_vertices * (1 + nudge / 100)))
        v, f = fast_simplification.simplify(
            v64, f32, target_reduction=1.0 - 2 * target / n_faces, agg=agg
        )
        try:
            v, f, notes = clean_mesh(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64))
            check_surface(v, f, source="decimated surface")
        except MeshError as exc:
            errors.append(str(exc))
            continue
        if errors:
            notes.insert(0, f"decimation retried with a {target}-vertex target, aggressiveness {agg} "
                            f"({len(errors)} tries failed cleanup)")
        return v, f, notes
    raise MeshError(f"decimation to {target_vertices} vertices gave no valid surface ({errors[0]})")


def clean_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Repair what decimation leaves behind, keeping the surface closed.

    Vertices at identical positions are merged first. Then, in a loop until nothing changes:
    faces with a repeated corner (removed: their real edges cancel); zero-area faces (a cap is
    fixed by flipping its longest edge, a needle by collapsing its shortest edge); duplicate
    faces (a two-sided fin: every copy removed, which keeps the rest closed); edges with 4+ faces
    (two sheets touching along an edge: each sheet gets its own copies of the edge's ends);
    pinched vertices (split into one vertex per fan). Finally tiny holes are fanned shut and
    all but the largest piece dropped; the split copies share positions but not topology.
    Returns ``(vertices, faces, notes)``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    counts = {"degenerate": 0, "flat": 0, "merged": 0, "fin": 0, "nonmanifold": 0, "pinched": 0}
    # merge identical positions (once: splitting pinches below makes deliberate copies)
    uniq, inverse = np.unique(v + 0.0, axis=0, return_inverse=True)
    if len(uniq) < len(v):
        counts["merged"] += len(v) - len(uniq)
        v, f = uniq, inverse.reshape(-1)[f]
    for _ in range(5):
        v, f = _clean_pass(v, f, counts)
        # keep the largest piece; removing fins may have opened small holes: fan them shut and
        # run the pass again (a fan over a straight boundary can itself be flat)
        v, f, _ = _largest_surface_piece(v, f)
        if not (edge_face_counts(f)[1] == 1).any():
            break
        f = _fill_small_holes(v, f)
    if not orientation_consistent(f):
        raise MeshError("decimation produced an inconsistently oriented surface")
    labels = {"degenerate": "faces with a repeated corner removed",
              "flat": "zero-area faces fixed by an edge flip or collapse", "merged": "duplicate vertices merged",
              "fin": "duplicate (fin) faces removed", "nonmanifold": "vertices split where two sheets touched along an edge",
              "pinched": "pinched vertices split"}
    notes = [f"cleanup: {n} {labels[k]}" for k, n in counts.items() if n]
    return np.ascontiguousarray(v), np.ascontiguousarray(f), notes


def _clean_pass(v: np.ndarray, f: np.ndarray, counts: dict) -> tuple[np.ndarray, np.ndarray]:
    """One round of :func:`clean_mesh`'s local fixes, repeated until nothing changes."""
    for _ in range(200):
        changed = False
        # faces with a repeated corner: their two real edges cancel, so removing them keeps it closed
        bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
        if bad.any():
            counts["degenerate"] += int(bad.sum())
            f = f[~bad]
            changed = True
        # zero-area faces: removing them would open holes; flip or collapse instead
        scale = float(np.ptp(v, axis=0).max()) ** 2 if len(v) else 1.0
        flat = np.nonzero(face_areas(v, f) <= 1e-12 * max(scale, 1.0))[0]
        if len(flat):
            f = _fix_flat_face(v, f, int(flat[0]))
            counts["flat"] += 1
            changed = True
            continue
        # duplicate faces (same three vertices): remove every copy
        key = np.sort(f, axis=1)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        dup = cnt[inv.reshape(-1)] > 1
        if dup.any():
            counts["fin"] += int(dup.sum())
            f = f[~dup]
            changed = True
        # edges with 4+ faces (two sheets touching along an edge): give each sheet its own copy
        # of the edge's end vertices (fans around a vertex are linked through 2-face edges only)
        edges, face_edges = unique_edges(f)
        ecount = np.bincount(face_edges.ravel(), minlength=len(edges))
        heavy = ecount > 2
        if heavy.any():
            heavy_set = {(int(a), int(b)) for a, b in edges[heavy]}
            ends = np.unique(edges[heavy])
            n_before = len(v)
            v, f = _split_pinched(v, f, ends, heavy_set)
            counts["nonmanifold"] += len(v) - n_before
            changed = len(v) > n_before
            if not changed:  # odd number of faces on an edge: not two sheets; drop them
                drop = heavy[face_edges].any(axis=1)
                f = f[~drop]
                changed = True
        if not changed:
            pinched = non_manifold_vertices(f, len(v))
            if len(pinched):
                v, f = _split_pinched(v, f, pinched)
                counts["pinched"] += len(pinched)
                changed = True
        if not changed:
            break
    return v, f


def _fix_flat_face(v: np.ndarray, f: np.ndarray, i: int) -> np.ndarray:
    """Remove zero-area face ``i`` without opening the surface.

    A needle (two corners together) is collapsed: the odd corner is merged into its nearest
    neighbour, and the faces that become degenerate are removed on the next pass. A cap (a
    corner on the opposite edge a-b) is fixed by flipping a-b with the face across it.
    """
    f = f.copy()
    tri = f[i]
    lengths = np.array([np.linalg.norm(v[tri[(k + 1) % 3]] - v[tri[k]]) for k in range(3)])
    k = int(np.argmax(lengths))  # longest edge runs tri[k] -> tri[k+1]
    a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
    if lengths.min() <= 1e-9 * max(lengths.max(), 1e-30) or lengths.max() == 0:
        ks = int(np.argmin(lengths))
        keep, drop = tri[ks], tri[(ks + 1) % 3]
        f[f == drop] = keep
        return f
    # neighbour across a-b holds the directed edge b -> a
    rolled = np.roll(f, -1, axis=1)
    hit = np.nonzero(((f == b) & (rolled == a)).any(axis=1))[0]
    hit = hit[hit != i]
    if len(hit) != 1:
        f[f == c] = a if np.linalg.norm(v[c] - v[a]) < np.linalg.norm(v[c] - v[b]) else b
        return f
    j = int(hit[0])
    d = int(next(x for x in f[j] if x != a and x != b))
    shares_cd = ((f == c).any(axis=1) & (f == d).any(axis=1)).any()
    if shares_cd:  # the flipped edge exists already: collapse instead
        f[f == c] = a if np.linalg.norm(v[c] - v[a]) < np.linalg.norm(v[c] - v[b]) else b
        return f
    f[i] = (a, d, c)
    f[j] = (b, c, d)
    return f


def _split_pinched(v: np.ndarray, f: np.ndarray, pinched: np.ndarray, heavy: set | frozenset = frozenset()):
    """Give each extra fan of faces around a vertex its own copy of the vertex.

    Faces around ``p`` are linked when they share an edge ``(p, q)`` that is not in ``heavy``
    (sorted vertex pairs of edges with more than two faces).
    """
    from scipy.sparse.csgraph import connected_components

    v = list(v)
    f = f.copy()
    for p in pinched:
        p = int(p)
        rows = np.nonzero((f == p).any(axis=1))[0]
        others = [set(int(x) for x in f[r]) - {p} for r in rows]
        link = sparse.lil_matrix((len(rows), len(rows)))
        for a in range(len(rows)):
            for b in range(a + 1, len(rows)):
                common = [q for q in others[a] & others[b] if (min(p, q), max(p, q)) not in heavy]
                if common:
                    link[a, b] = 1
        n, lab = connected_components(link.tocsr(), directed=False)
        for c in range(1, n):
            new = len(v)
            v.append(v[p])
            for r in rows[lab == c]:
                f[r][f[r] == p] = new
    return np.array(v), f


def _fill_small_holes(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Close each boundary loop with a fan (used only on the few tiny holes cleanup can open)."""
    directed = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)
    keys = {(int(a), int(b)) for a, b in directed}
    boundary = [(a, b) for a, b in keys if (b, a) not in keys]
    nxt = {}
    for a, b in boundary:
        nxt.setdefault(b, []).append(a)  # the hole is walked opposite to the faces' edges
    new = []
    seen = set()
    for start in list(nxt):
        if start in seen:
            continue
        loop, cur = [], start
        while cur not in seen and cur in nxt and len(nxt[cur]) == 1:
            seen.add(cur)
            loop.append(cur)
            cur = nxt[cur][0]
        if cur == start and 3 <= len(loop) <= 12:
            new += [(loop[0], loop[k], loop[k + 1]) for k in range(1, len(loop) - 1)]
    if not new:
        return f
    return np.vstack([f, np.array(new, dtype=np.int64)])
