"""The model's motion as a displacement-field image (DVF) on a reference image's grid.

Frames and units: every displacement is mm in the LPS world of the reference image; arrays of a
field are ``(z, y, x, 3) float32`` indexed like SimpleITK's ``[k, j, i]`` (the components stay
``(x, y, z)`` LPS); the grid is :class:`Grid` (spacing, origin and direction as
:class:`lungdeform.io.grid.Image`).

Forward field ``u``: a point at ``x`` in the reference (the model's rest state, end-exhale) is at
``x + u(x)`` at the breathing state: inside lung ``i`` the lung's interior field at its scale,
``s_i · v_i(x)`` (:attr:`lungdeform.model.lung.LungModel.interior`, exactly what
:meth:`~lungdeform.model.lung.LungModel.points_at` and ``lungdeform track`` move points by);
outside every lung the same interpolant continued outward and faded by a smoothstep weight
:func:`fade` from 1 on the surface to 0 at the margin :func:`extension_margin` (the lungs slide
inside the chest wall, so the motion outside decays over a few centimetres; the margin grows with
the largest surface displacement so that the fade can never fold tissue). With two lungs the outside
motion of each is weighted by inverse squared distance, so each lung's surface sees only its own
lung. An optional rigid map (the fit's alignment of scan K, :func:`scan_state`) is composed after:
``x → A⁻¹(x + u(x))``.

Inverse field ``w`` (ITK/elastix resampling convention): for each output point ``y`` the reference
point ``y + w(y)`` it comes from, by fixed-point iteration ``w ← −u(y + w)`` (:func:`invert`).

Speed: the interior field is evaluated only on a coarse lattice of the grid's own voxels (every
``stride`` voxels, about :data:`NODE_SPACING_MM`) inside the lungs' bounding box plus the margin, by
one fused kernel sum per node (:class:`lungdeform.interior.sliding.RadialSum`), then interpolated
trilinearly to every voxel, plus any rigid part, in one fused pass (:func:`upsample`, zero beyond the
box); the Jacobian's range is a second fused pass over the box (:func:`jacobian_range`;
:mod:`lungdeform.playback.voxel`). The lattice error (at most ``Σ_a h_a²/8 · max|∂²u/∂x_a²|`` for node
steps ``h_a``) is measured by :func:`lattice_error` (reported by ``lungdeform dvf``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lungdeform.errors import FoldError, InputError
from lungdeform.geometry.depth import crossing_bound
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.geometry.mesh import inside_by_parity, inside_nodes

from . import voxel as V
from .phases import phase_schedule
from .schedule import MAX_GROWTH, MIN_VOLUME_FRACTION, lung_shares
from .trajectory import above_end_exhale, lung_scales, volumes_in_words

#: Lattice spacing (mm) at which the interior field is evaluated before trilinear interpolation.
NODE_SPACING_MM = 4.0
#: Largest lattice spacing (mm): wider than the smallest fade margin, the lattice misses the lungs' motion.
MAX_NODE_MM = 20.0
#: Most lattice nodes a field is evaluated on (about 3 GB of working memory); a state that moves the
#: lungs so far that the fade margin needs more is refused before anything is allocated.
MAX_LATTICE_NODES = 40_000_000
#: Most phases over one breathing cycle (``--phases`` of warp and track).
MAX_PHASES = 100
#: Smallest fade margin outside the lungs (mm).
BASE_MARGIN_MM = 25.0
#: The margin is at least this many times the largest surface displacement: the smoothstep's
#: steepest slope is 1.5 / margin, so the normal stretch ``1 − 1.5·|u| / margin`` stays ≥ 0.4.
MARGIN_PER_MM = 2.5
#: Radius (mm) about each landmark within which the forward field is evaluated exactly (:func:`refine`).
REFINE_RADIUS_MM = 8.0
#: Fixed-point iterations of :func:`invert`.
INVERSE_ITERATIONS = 8


@dataclass(frozen=True, eq=False)
class Grid:
    """A voxel grid: ``shape`` (z, y, x) voxels, ``spacing`` (3,) mm along (i, j, k), ``origin``
    (3,) mm LPS of voxel (0, 0, 0), ``direction`` (3, 3) columns the index axes in LPS."""

    shape: tuple
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray

    @staticmethod
    def of(image) -> "Grid":
        """The grid of an :class:`lungdeform.io.grid.Image` (or anything with its attributes)."""
        shape = tuple(int(n) for n in (image.shape if hasattr(image, "shape") else image.array.shape))
        return Grid(shape, np.asarray(image.spacing, float), np.asarray(image.origin, float),
                    np.asarray(image.direction, float).reshape(3, 3))

    def world(self, ijk) -> np.ndarray:
        """``ijk : (n, 3)`` or ``(3,)`` (i, j, k) index → ``(n, 3)`` or ``(3,) float`` mm LPS (``einsum``,
        not a BLAS product: an ``(n, 3) × (3, 3)`` product gains nothing from BLAS threads, which spin
        against numba's)."""
        return np.einsum("...a,ra->...r", np.asarray(ijk, float) * self.spacing, self.direction) + self.origin

    def index(self, points) -> np.ndarray:
        """``points : (n, 3)`` or ``(3,)`` mm LPS → the same shape, float, continuous (i, j, k) index."""
        return np.einsum("...r,ra->...a", np.asarray(points, float) - self.origin, self.direction) / self.spacing


@dataclass(frozen=True, eq=False)
class Lattice:
    """Coarse nodes of a grid: voxel index ``lo`` (i, j, k) of node 0, ``stride`` (3,) voxels,
    ``dims`` (3,) nodes along (i, j, k); ``box`` the voxel range ``((i0, j0, k0), (i1, j1, k1))`` it
    covers within the grid."""

    lo: np.ndarray
    stride: np.ndarray
    dims: np.ndarray
    box: tuple

    def ijk(self) -> np.ndarray:
        """``(n, 3) float`` voxel indices of the nodes, ordered [k][j][i] (C order of (z, y, x))."""
        axes = [self.lo[a] + self.stride[a] * np.arange(self.dims[a]) for a in range(3)]
        k, j, i = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        return np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(float)

    def points(self, grid: Grid) -> np.ndarray:
        """``(n, 3) float`` mm LPS of the nodes on ``grid``, ordered as :meth:`ijk`: ``grid.world(ijk)``
        (the same on an axis-aligned grid; on an oblique one to within rounding, 1e-13 mm), summed as
        one term per index axis, without the ``(n, 3) × (3, 3)`` product (serial, 25 ms a lattice of 415k)."""
        t = [((self.lo[a] + self.stride[a] * np.arange(self.dims[a])).astype(float) * grid.spacing[a])[:, None]
             * grid.direction[:, a] for a in range(3)]  # (dims[a], 3) mm along index axis a
        return ((t[0][None, None] + t[1][None, :, None]) + t[2][:, None, None] + grid.origin).reshape(-1, 3)


def lattice(grid: Grid, lo_mm, hi_mm, spacing_mm: float = NODE_SPACING_MM) -> Lattice | None:
    """The :class:`Lattice` over the world box ``[lo_mm, hi_mm]`` (3,) mm LPS; its nodes may lie
    beyond the grid (the field is evaluated there too, so that the inverse is right at the image's
    border), its ``box`` is clipped to the grid; None when the box misses the grid."""
    corners = np.array([[x, y, z] for x in (lo_mm[0], hi_mm[0]) for y in (lo_mm[1], hi_mm[1])
                        for z in (lo_mm[2], hi_mm[2])])
    idx = grid.index(corners)
    size = np.array(grid.shape[::-1])
    lo = np.floor(idx.min(axis=0)).astype(int)
    hi = np.ceil(idx.max(axis=0)).astype(int) + 1
    box_lo, box_hi = np.clip(lo, 0, size), np.clip(hi, 0, size)
    if np.any(box_hi <= box_lo):
        return None
    stride = np.maximum(np.round(spacing_mm / grid.spacing).astype(int), 1)
    dims = (hi - 1 - lo + stride - 1) // stride + 1  # the last node at or past hi - 1
    return Lattice(lo, stride, dims, (tuple(int(x) for x in box_lo), tuple(int(x) for x in box_hi)))


def fade(d, margin: float) -> np.ndarray:
    """Smoothstep weight ``(n,) float``: 1 at distance ``d`` = 0 mm, 0 from ``margin`` mm on, C¹."""
    t = np.clip(np.asarray(d, float) / margin, 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def extension_margin(peak_mm: float, base_mm: float = BASE_MARGIN_MM) -> float:
    """The fade margin (mm): ``max(base_mm, 2.5 × peak_mm)`` for a largest surface motion ``peak_mm``."""
    return max(float(base_mm), MARGIN_PER_MM * float(peak_mm))


def inside_lattice(surface, grid: Grid, lat: Lattice) -> np.ndarray:
    """``(nz, ny, nx) bool``: lattice nodes inside a closed ``surface`` (mm LPS), by the parity of a
    ray along each lattice row (index axis i) crossing the triangles
    (:func:`lungdeform.geometry.mesh.inside_nodes`)."""
    return inside_nodes((grid.index(surface.vertices) - lat.lo) / lat.stride, surface.faces, lat.dims)


def outside_distance(surface, points, inside: np.ndarray, node_mm, reach_mm: float) -> np.ndarray:
    """``(n,) float`` mm: 0 inside, the exact distance to ``surface`` for outside lattice ``points :
    (n, 3)`` within about ``reach_mm`` of it (``inside : (nz, ny, nx) bool``, nodes ``node_mm`` (3,) mm
    apart along (i, j, k)), inf farther (found from the distance to the nearest inside node, which also
    bounds the search: the segment to it crosses the surface)."""
    if not inside.any():
        return np.full(len(points), np.inf)
    sampling = np.asarray(node_mm, float)[::-1]
    reach = reach_mm + float(np.max(node_mm))
    # the transform only over the inside nodes' box plus the reach: every node beyond is farther
    pad = np.ceil(reach / sampling).astype(int)
    idx = np.nonzero(inside)
    crop = tuple(slice(max(int(a.min()) - p, 0), int(a.max()) + p + 1) for a, p in zip(idx, pad))
    near = np.full(inside.shape, np.inf)
    near[crop] = ndimage.distance_transform_edt(~inside[crop], sampling=sampling)
    near = near.ravel()
    band = (near > 0) & (near < reach)
    d = np.where(inside.ravel(), 0.0, np.inf)
    if band.any():
        d[band] = SurfaceDistance(surface.vertices, surface.faces).distance(points[band], crossing_bound(near[band]))
    return d


def blended_field(fields, inside, distance, margin: float) -> np.ndarray:
    """``u : (n, 3) float`` mm from per-lung displacements ``fields : list of (n, 3)`` mm, ``inside``
    and ``distance`` (list of (n,)): a lung's own field inside it; outside every lung each faded
    (:func:`fade`) and weighted by inverse squared distance, so the field is continuous at each surface."""
    d = np.stack([np.asarray(x, float) for x in distance])  # (L, n)
    f = np.stack([np.asarray(x, float) for x in fields])
    return V.blend_nodes(f, np.stack(inside).astype(bool), d, float(margin), np.empty((d.shape[1], 3)))


def state_scales(model, delta_ml: float) -> dict[str, float]:
    """Per lung the scale ``s`` (units) of a state ``delta_ml`` mL of both lungs above end-exhale:
    each lung's exact share (:func:`lungdeform.playback.trajectory.lung_scales`, as ``track``)."""
    return {name: float(s[0]) for name, s in lung_scales(model, [float(delta_ml)]).items()}


def surface_peak(model, scales: dict) -> float:
    """The largest interior-field displacement (mm) on any lung's end-exhale surface at ``scales``
    (:attr:`~lungdeform.model.lung.LungModel.surface_interior`, computed once a lung)."""
    return max(float(np.linalg.norm(scales[n] * lung.surface_interior, axis=1).max())
               for n, lung in model.lungs.items())


def active_values(interior, grid: Grid, lat: Lattice, active: np.ndarray) -> np.ndarray:
    """``(n, 3) float`` mm per unit, the lattice's nodes in C order: the ``interior`` field's displacement
    at the nodes where ``active : (nz, ny, nx) bool``, zero elsewhere; each lattice row evaluated as
    one straight row from its first to its last active node
    (:meth:`~lungdeform.interior.field.InteriorField.along_rows`)."""
    nz, ny, nx = active.shape
    k, j = np.nonzero(active.any(axis=2))
    first = np.argmax(active[k, j], axis=1)
    counts = nx - np.argmax(active[k, j, ::-1], axis=1) - first
    starts = grid.world(np.stack([first, j, k], axis=1) * lat.stride + lat.lo)
    step = grid.direction[:, 0] * (grid.spacing[0] * lat.stride[0])
    out = np.zeros((nz * ny * nx, 3))
    if len(k):
        rank = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        out[np.repeat((k * ny + j) * nx + first, counts) + rank] = interior.along_rows(starts, step, counts)
        out[~active.ravel()] = 0.0
    return out


def lattice_field(model, grid: Grid, scales: dict, *, spacing_mm: float = NODE_SPACING_MM,
                  base_margin_mm: float = BASE_MARGIN_MM, reach_mm: float = 0.0):
    """The forward deformation on the lattice: ``(Lattice, u (z, y, x, 3) float mm, info)`` over the
    lungs' bounding box plus the fade margin plus ``reach_mm`` (room for a rigid shift), the interior
    field evaluated only on nodes inside a lung or within the margin of it (module docstring)."""
    margin = extension_margin(surface_peak(model, scales), base_margin_mm)
    v = np.concatenate([lung.surface.vertices for lung in model.lungs.values()])
    pad = margin + reach_mm + 2.0 * spacing_mm
    lat = lattice(grid, v.min(axis=0) - pad, v.max(axis=0) + pad, spacing_mm)
    if lat is None:
        raise InputError("the reference image does not overlap the model's lungs: are they in the same frame "
                         "(mm, LPS of the end-exhale scan)?")
    nodes = int(np.prod(np.asarray(lat.dims, dtype=float)))
    if nodes > MAX_LATTICE_NODES:
        raise InputError(f"the field would take {nodes:.3g} lattice nodes (at most {MAX_LATTICE_NODES:.3g}): the "
                         f"state moves the lungs so far that the fade margin is {margin:.0f} mm; give a volume "
                         f"nearer the model's range or a coarser node spacing")
    pts = lat.points(grid)
    shape3 = tuple(int(n) for n in lat.dims[::-1])
    node_mm = grid.spacing * lat.stride
    fields, inside, dist, evaluated = [], [], [], 0
    for name, lung in model.lungs.items():
        ins3 = inside_lattice(lung.surface, grid, lat)
        d = outside_distance(lung.surface, pts, ins3, node_mm, margin)
        ins = ins3.ravel()
        active = ins | (d < margin)
        fields.append(scales[name] * active_values(lung.interior, grid, lat, active.reshape(shape3)))
        inside.append(ins)
        dist.append(d)
        evaluated += int(active.sum())
    u = blended_field(fields, inside, dist, margin).reshape(*shape3, 3)
    info = {"margin_mm": margin, "nodes": int(len(pts)), "nodes_evaluated": evaluated,
            "node_spacing_mm": (grid.spacing * lat.stride).tolist()}
    return lat, u, info


def _affine_steps(grid: Grid, matrix) -> tuple[np.ndarray, np.ndarray]:
    """The displacement ``x → M x − x`` of a 4×4 ``matrix`` (mm, LPS) on ``grid`` as ``const + steps @
    (i, j, k)``: ``(const (3,) mm, steps (3, 3) mm per voxel)``; zero for None."""
    if matrix is None:
        return np.zeros(3), np.zeros((3, 3))
    m = np.asarray(matrix, float)
    b = m[:3, :3] - np.eye(3)
    return b @ grid.origin + m[:3, 3], (b @ grid.direction) * grid.spacing


def upsample(lat: Lattice, values: np.ndarray, grid: Grid, matrix=None, spans=None) -> np.ndarray:
    """``(z, y, x, 3) float32`` on the whole ``grid``: lattice ``values : (nz, ny, nx, 3)`` interpolated
    trilinearly over the lattice's box, zero beyond, plus (``matrix``, 4×4 mm LPS) the displacement
    ``x → M x − x`` at every voxel; one fused pass (:func:`lungdeform.playback.voxel.fill_field`), which
    records in ``spans`` (:func:`lungdeform.playback.voxel.no_spans`, if given) the voxels it wrote."""
    (i0, j0, k0), (i1, j1, k1) = lat.box
    c = np.ascontiguousarray(values, np.float32)
    axes = [V.axis_weights(grid.shape[2 - a], int(lat.lo[a]), int(lat.stride[a]), int(lat.dims[a]),
                           lat.box[0][a], lat.box[1][a]) for a in (2, 1, 0)]  # k, j, i
    const, steps = _affine_steps(grid, matrix)
    out = V.zeroed(tuple(grid.shape) + (3,))
    nz, ny, nx = grid.shape
    ranges = np.array([k0, k1, j0, j1, i0, i1] if matrix is None else [0, nz, 0, ny, 0, nx], np.int64)
    return V.fill_field(out, c, (axes[0], axes[1], axes[2]), (const, steps), ranges,
                        V.no_spans(grid.shape) if spans is None else spans, True)


def sample(lat: Lattice, values: np.ndarray, grid: Grid, points) -> np.ndarray:
    """Lattice ``values : (nz, ny, nx, 3)`` interpolated trilinearly at ``points : (n, 3)`` mm LPS,
    ``(n, 3) float``; zero outside the lattice."""
    idx = (grid.index(points) - lat.lo) / lat.stride  # (n, 3) lattice (i, j, k)
    coords = idx[:, ::-1].T  # (k, j, i) rows, the array's axis order
    return np.stack([ndimage.map_coordinates(values[..., c], coords, order=1, mode="constant", cval=0.0)
                     for c in range(3)], axis=1)


def invert(lat: Lattice, u: np.ndarray, grid: Grid, iterations: int = INVERSE_ITERATIONS):
    """The inverse deformation on the lattice, ``(w (z, y, x, 3) float mm, residual_mm)``: ``w(y) =
    −u(y + w(y))`` by fixed-point iteration, ``u`` interpolated trilinearly between nodes;
    ``residual_mm`` the largest ``|w(y) + u(y + w(y))|`` left at any node."""
    y = lat.points(grid)
    w = np.zeros_like(y)
    for _ in range(int(iterations)):
        w = -sample(lat, u, grid, y + w)
    residual = float(np.linalg.norm(w + sample(lat, u, grid, y + w), axis=1).max()) if len(y) else 0.0
    return w.reshape(u.shape), residual


def add_affine(field: np.ndarray, grid: Grid, matrix) -> np.ndarray:
    """Add, in place, the displacement ``x → M x − x`` of a 4×4 ``matrix`` (mm, LPS) at every voxel of
    ``field : (z, y, x, 3) float32`` on ``grid`` (the pass of :func:`upsample`, no lattice). Returns ``field``."""
    nz, ny, nx = grid.shape
    none = [(np.full(n, -1, np.int64), np.zeros(n, np.float32)) for n in (nz, ny, nx)]
    const, steps = _affine_steps(grid, matrix)
    return V.fill_field(field, np.zeros((1, 1, 1, 3), np.float32), (none[0], none[1], none[2]),
                        (const, steps), np.array([0, nz, 0, ny, 0, nx], np.int64), V.no_spans(grid.shape))


def _inverse_axes(spacing, direction) -> np.ndarray:
    """``(3, 3)``: ``[r, a] = ∂index_a / ∂x_r = D[r, a] / s_a`` (a = i, j, k)."""
    return np.ascontiguousarray(np.asarray(direction, float).reshape(3, 3) / np.asarray(spacing, float))


def jacobian_determinant(field: np.ndarray, spacing, direction) -> np.ndarray:
    """``(z, y, x) float32``: ``det(I + ∇u)`` of ``x → x + u(x)`` for ``field : (z, y, x, 3)`` mm,
    central differences in physical units (one-sided at the array's edges; each axis needs ≥ 2 voxels)."""
    f = np.ascontiguousarray(field, np.float32)
    nz, ny, nx = f.shape[:3]
    out = np.empty((nz, ny, nx), np.float32)
    ranges = np.array([0, nz, 0, ny, 0, nx], np.int64)
    V.jacobian_pass(f, _inverse_axes(spacing, direction), ranges, out, V.row_spans(f, ranges))
    return out


def jacobian_range(field: np.ndarray, grid: Grid, box=None, spans=None) -> tuple[float, float, int]:
    """``(min, max, folded voxels)`` of :func:`jacobian_determinant` over ``field`` on ``grid`` (only the
    voxel ``box`` ``((i0, j0, k0), (i1, j1, k1))`` when given: a rigid field elsewhere), in one fused
    pass without the determinant image. ``spans``: the voxels written per row, as :func:`upsample`
    records them (:func:`lungdeform.playback.voxel.jacobian_pass`); measured from ``field`` if None."""
    (i0, j0, k0), (i1, j1, k1) = box if box is not None else ((0, 0, 0), tuple(grid.shape[::-1]))
    f = np.ascontiguousarray(field, np.float32)
    ranges = np.array([k0, k1, j0, j1, i0, i1], np.int64)
    rows = V.jacobian_pass(f, _inverse_axes(grid.spacing, grid.direction), ranges, np.empty((0, 0, 0), np.float32),
                           V.row_spans(f, ranges) if spans is None else spans)
    if not len(rows):
        return 1.0, 1.0, 0
    return float(rows[:, 0].min()), float(rows[:, 1].max()), int(rows[:, 2].sum())


def lattice_error(model, lat: Lattice, u: np.ndarray, grid: Grid, scales: dict, rng_seed: int = 0,
                  n: int = 2000) -> float:
    """Largest difference (mm) between the trilinear lattice field and the exact interior field
    (:meth:`~lungdeform.model.lung.LungModel.points_at`) at up to ``n`` seeded random points inside the lungs."""
    rng = np.random.default_rng(rng_seed)
    worst = 0.0
    for name, lung in model.lungs.items():
        v = lung.surface.vertices
        q = rng.uniform(v.min(axis=0), v.max(axis=0), size=(n, 3))
        q = q[inside_by_parity(q, v, lung.surface.faces)]
        if len(q):
            exact = lung.points_at(q, scale=scales[name]) - q
            worst = max(worst, float(np.linalg.norm(sample(lat, u, grid, q) - exact, axis=1).max()))
    return worst


def near_landmarks(model, grid: Grid, radius_mm: float = REFINE_RADIUS_MM):
    """Voxels near each lung's landmarks (the anchors of its landmark correction, whose biharmonic
    kernel has a kink there that a lattice cannot follow): per lung ``(flat voxel index (p,), world
    (p, 3) mm, weight (p,))``, weight 1 within half the radius of a landmark, a smoothstep to 0 at the
    radius; the radius shrinks to the landmark's depth so that every voxel lies inside its lung."""
    out = {}
    size = np.array(grid.shape[::-1])
    for name, lung in model.lungs.items():
        if lung.landmarks is None or not lung.interior.corrected:
            continue
        lmk = np.asarray(lung.landmarks, float)
        depth = SurfaceDistance(lung.surface.vertices, lung.surface.faces).distance(lmk)
        flat, weight = [], []
        for p, r_max in zip(lmk, np.minimum(radius_mm, depth)):
            corners = grid.index(np.array([[p[0] + a, p[1] + b, p[2] + c] for a in (-r_max, r_max)
                                           for b in (-r_max, r_max) for c in (-r_max, r_max)]))
            lo = np.clip(np.floor(corners.min(axis=0)), 0, size - 1).astype(int)
            hi = np.clip(np.ceil(corners.max(axis=0)), 0, size - 1).astype(int)
            i, j, k = (g.ravel() for g in np.meshgrid(*[np.arange(lo[a], hi[a] + 1) for a in range(3)], indexing="ij"))
            r = np.linalg.norm(grid.world(np.stack([i, j, k], axis=1)) - p, axis=1)
            keep = r < r_max
            flat.append(np.ravel_multi_index((k[keep], j[keep], i[keep]), grid.shape))
            weight.append(fade(np.maximum(2.0 * r[keep] / max(r_max, 1e-9) - 1.0, 0.0), 1.0))
        if flat:
            f, w = np.concatenate(flat), np.concatenate(weight)
            order = np.argsort(-w, kind="stable")
            f, first = np.unique(f[order], return_index=True)
            w = w[order][first]
            ijk = np.stack(np.unravel_index(f, grid.shape)[::-1], axis=1)
            out[name] = (f, grid.world(ijk), w)
    return out


def refine(field: np.ndarray, model, grid: Grid, lat: Lattice, u: np.ndarray, scales: dict, rotation) -> np.ndarray:
    """Replace, in place, the lattice field near the landmarks (:func:`near_landmarks`) by the exact
    interior field (blended by the weight), rotated by ``rotation`` (3, 3) as the rest of ``field``.
    Returns the flat voxel indices (z, y, x) it changed, ``(p,) int``."""
    flat_field = field.reshape(-1, 3)
    touched = [np.zeros(0, np.int64)]
    for name, (flat, pts, w) in near_landmarks(model, grid).items():
        exact = scales[name] * model.lungs[name].interior.displacement(pts)
        delta = (exact - sample(lat, u, grid, pts)) * w[:, None]
        flat_field[flat] += (delta @ np.asarray(rotation, float).T).astype(np.float32)
        touched.append(np.asarray(flat, np.int64))
    return np.concatenate(touched)


@dataclass(frozen=True, eq=False)
class FieldResult:
    """A displacement-field image: ``field : (z, y, x, 3) float32`` mm LPS on the grid; ``inverse``
    whether it is the resampling field; ``jacobian_min``/``jacobian_max`` of ``x → x + field(x)``;
    ``info`` the margin, lattice, lattice error and (inverse) the inversion residual (mm)."""

    field: np.ndarray
    inverse: bool
    jacobian_min: float
    jacobian_max: float
    info: dict


def _reach(model, matrix) -> float:
    """How far (mm) the rigid ``matrix`` moves any corner of the lungs' bounding box."""
    if matrix is None:
        return 0.0
    v = np.concatenate([lung.surface.vertices for lung in model.lungs.values()])
    lo, hi = v.min(axis=0), v.max(axis=0)
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    m = np.asarray(matrix, float)
    return float(np.linalg.norm(c @ m[:3, :3].T + m[:3, 3] - c, axis=1).max())


def displacement_field(model, grid: Grid, delta_ml: float, *, alignment=None, inverse: bool = False,
                       spacing_mm: float = NODE_SPACING_MM, base_margin_mm: float = BASE_MARGIN_MM) -> FieldResult:
    """The model's motion at ``delta_ml`` mL (both lungs, above end-exhale) as a field on ``grid``
    (module docstring): forward ``x → A⁻¹(x + u(x))`` or, with ``inverse``, its resampling inverse.
    ``alignment`` : 4×4 rigid map, mm LPS, from the scan's frame to the model's (the fit's ``applied``
    alignment), or None. Raises :class:`FoldError` when the field folds (Jacobian ≤ 0)."""
    if not (np.isfinite(spacing_mm) and 0 < spacing_mm <= MAX_NODE_MM):
        raise InputError(f"node spacing must be a finite number in (0, {MAX_NODE_MM:g}] mm, got {spacing_mm:g}")
    scales = state_scales(model, delta_ml)
    a = None if alignment is None else np.asarray(alignment, float).reshape(4, 4)
    lat, u, info = lattice_field(model, grid, scales, spacing_mm=spacing_mm, base_margin_mm=base_margin_mm,
                                 reach_mm=_reach(model, None if a is None else np.linalg.inv(a)))
    info["lattice_error_mm"] = lattice_error(model, lat, u, grid, scales)
    info["scales"] = scales
    spans = V.no_spans(grid.shape)  # the voxels written, so that the Jacobian's pass reads only those
    if inverse:
        w, info["inversion_residual_mm"] = invert(lat, u, grid)
        nodes = lat.points(grid)
        rigid = np.eye(4) if a is None else a
        part = sample(lat, w, grid, nodes @ rigid[:3, :3].T + rigid[:3, 3]).reshape(u.shape)
        field = upsample(lat, part, grid, a, spans)
    else:
        rot = np.eye(3) if a is None else np.linalg.inv(a)[:3, :3]
        part = u if a is None else np.einsum("...b,ab->...a", u, rot)  # not BLAS: (n, 3) × (3, 3) (Grid.world)
        field = upsample(lat, part, grid, None if a is None else np.linalg.inv(a), spans)
        V.widen_spans(spans, refine(field, model, grid, lat, u, scales, rot), grid.shape)
    lo, hi, folded = jacobian_range(field, grid, lat.box, spans)
    if folded:
        raise FoldError(f"the displacement field folds at {folded} voxel(s) (Jacobian determinant down to "
                        f"{lo:.3g}); not written")
    return FieldResult(field, inverse, lo, hi, info)


@dataclass(frozen=True, eq=False)
class State:
    """A breathing state: ``delta_ml`` mL of both lungs above end-exhale; ``alignment`` the 4×4 rigid
    map (mm, LPS) from that scan's frame to the model's, or None; ``source`` in words."""

    delta_ml: float
    alignment: np.ndarray | None
    source: str


def volume_state(model, volume_ml: float) -> State:
    """The state at an absolute volume ``volume_ml`` (mL, both lungs together), in the model's frame;
    its ``delta_ml`` above end-exhale, wherever the model's scan lies (:mod:`lungdeform.model.scan_state`)."""
    if not (np.isfinite(volume_ml) and volume_ml > 0):
        raise InputError(f"--volume-ml must be > 0 mL, got {volume_ml}")
    delta = above_end_exhale(model, volume_ml)
    for side, share in lung_shares(model).items():
        ee = model.lungs[side].volume_ee_ml - share * model.scan.above_ee_ml  # the lung's own end-exhale
        lung_ml = ee + share * delta
        if not MIN_VOLUME_FRACTION * ee <= lung_ml <= MAX_GROWTH * ee:
            raise InputError(f"--volume-ml {volume_ml:g} mL takes the {side} lung to {lung_ml:.0f} mL, outside "
                             f"{MIN_VOLUME_FRACTION:g} to {MAX_GROWTH:g} times its end-exhale {ee:.0f} mL: no lung "
                             f"reaches that (the model's lungs together: {volumes_in_words(model)})")
    return State(delta, None, f"volume {volume_ml:g} mL ({delta:+.0f} mL above end-exhale; {volumes_in_words(model)})")


def scan_state(model, scan: int) -> State:
    """Input scan ``scan`` of the fit that wrote ``model`` (0 = the rest scan): its volume change from
    the rest scan (the provenance's ``volumes_ml``) and, where the fit aligned it (apex or joint
    translation), the alignment's ``applied`` matrix (scan → model frame), so the state lies in that
    scan's frame. :class:`InputError` for a model without that provenance or a scan it does not have."""
    prov = model.provenance or {}
    vols = prov.get("volumes_ml")
    if not vols:
        raise InputError("--scan: the model records no fitted scans (volumes_ml); it was not written by "
                         "'lungdeform fit'; give --volume-ml")
    if not 0 <= int(scan) < len(vols):
        raise InputError(f"--scan must be 0 to {len(vols) - 1} (the model was fitted to {len(vols)} scans), got {scan}")
    k = int(scan)
    matrix = None
    if k > 0:
        applied = (prov.get("alignment") or [{}] * k)[k - 1].get("applied") or {}
        if "matrix" in applied:
            matrix = np.asarray(applied["matrix"], float).reshape(4, 4)
            matrix = None if np.allclose(matrix, np.eye(4), atol=1e-12) else matrix
    delta = float(vols[k]) - float(vols[0])
    moved = "" if matrix is None else f", its alignment {np.round(matrix[:3, 3], 2).tolist()} mm undone"
    return State(delta + model.scan.above_ee_ml, matrix,
                 f"scan {k} of the fit ({vols[k]:.0f} mL, {delta:+.0f} mL from scan 0{moved})")


def check_phases(phases: int) -> None:
    """Refuse a number of phases outside 1 to :data:`MAX_PHASES` (``--phases``)."""
    if not 1 <= int(phases) <= MAX_PHASES:
        raise InputError(f"--phases must be 1 to {MAX_PHASES} (states over one breathing cycle), got {phases}")


def phase_states(trace, phases: int, zero: str = "end-inhale") -> tuple[list[State], float]:
    """``phases`` states evenly over one breathing cycle of a volume ``trace``
    (:class:`~lungdeform.playback.schedule.VolumeTrace`, mL above end-exhale), phase 0 at ``zero``
    (end-inhale by default, as 4-D CT numbers phases: :func:`lungdeform.playback.phases.phase_schedule`).
    Returns ``(states, period_s)``."""
    check_phases(phases)
    sched = phase_schedule(trace, phases, zero)
    states = [State(float(v), None, f"phase {i} of {phases} ({sched.percent(i)} %) at t = {ti:.3g} s "
                                    f"({v:+.0f} mL above end-exhale)")
              for i, (ti, v) in enumerate(zip(sched.t_s, sched.delta_ml))]
    return states, sched.period_s
