"""Sliding interpolation: the interior motion implied by the *normal* motion of a lung's surface.

A lung slides along the chest wall, the diaphragm and the mediastinum (the pleural space), so only
the normal component ``g_i = n_i · u_i`` of a surface displacement says how the tissue inside moves;
the tangential component of a model's (or a registration's) surface correspondence is arbitrary.
The sliding interpolant is the smoothest vector field that matches the surface's normal motion:

    v(x) = Σ_j α_j φ(|x − p_j|) n_j + A x̂ + b,      φ(r) = −r  (the 3-D biharmonic kernel),

with ``x̂`` the centred, scaled position, fitted by ``n_i · v(p_i) + λ α_i = g_i`` and
``Σ_j α_j n_j x̂_j^T = 0``, ``Σ_j α_j n_j = 0`` (a Hermite–Birkhoff radial-basis interpolant of the
functionals ``u ↦ n_i · u(p_i)``). The field minimises the 3-D bending energy of each component
among all fields with that normal motion (smoothed by ``λ``, mm). Any affine displacement is
reproduced exactly (the polynomial part), except linear flows that (nearly) map the surface onto
itself, which its normals cannot see: a sphere's rotations, or an ellipsoid's three "elliptic
rotations" ``x ↦ E R E⁻¹ x``. Those directions of the polynomial part (relative singular value
below :data:`POLY_TOLERANCE`, after the translations, which are always kept, are projected out) are
left out, so such a flow gives no motion. Real lungs keep all twelve (the ITK right lung's weakest
direction: 0.13).

Why this reading (measured on the ITK right-lung pair, 51 landmarks, the model's surface field,
``λ`` = 100 mm): the landmarks move with a mean error of 3.8 mm, against 4.6 mm for the thin-plate
spline of the full surface displacement (:mod:`lungdeform.interior.interpolate`) and 4.2 mm for the full
biharmonic spline with the same smoothing; with the interior landmark correction
(:mod:`lungdeform.interior.field`, crop faces left out; the thin-plate correction of 0.3) 2.00–2.25 mm
(mean 2.08) over ten 5-fold splits and 2.02 mm leave-one-out, against 2.51–2.68 mm (five splits)
and 2.48 mm leave-one-out with the thin-plate surface field; with :func:`sliding_correction` as the landmark correction 1.90–2.07 mm
(mean 1.97) and 1.92 mm leave-one-out. The reading and ``λ`` were chosen on that pair (0: 4.1 mm,
100: 3.8, 1000: 3.9, 10⁴: 4.6 mm), with the same landmarks that measure it: the figures are
optimistic by an unknown amount until measured on another subject.

:func:`sliding_correction` adds interior *anchors* (landmarks) whose whole displacement the field
matches, with zero normal data on the surface: a correction that leaves the boundary where a
surface-driven field put it; :class:`CorrectionSolver` cross-validates it cheaply.

The interpolant is linear in the displacement, so :func:`sliding_weights` returns it as an operator
``W`` with ``W @ u`` for any surface field ``u : (k, 3)``, like
:func:`lungdeform.interior.interpolate.interpolation_weights`; :func:`sliding_field` returns it as a field.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np
from scipy.linalg import lapack, solve_triangular
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import as_vertices, thinned

#: Default smoothing ``λ`` (mm) of the sliding interpolant.
SMOOTHING_MM = 100.0
#: More surface points than this use a seeded subset (the dense solve is O(k³)).
MAX_POINTS = 4000
#: Linear directions whose normal footprint (beyond what translations explain) has a singular value
#: below this fraction of the whole polynomial block's largest are left out (a sphere's rotations:
#: 0.004; the ITK right lung's weakest direction: about 0.1).
POLY_TOLERANCE = 1e-2


@numba.njit(cache=True, parallel=True, fastmath=True)
def _radial_sum(query, centres, weights):
    """``(q, 3) float``: ``Σ_j −|query_i − c_j| · w_j`` for ``query : (q, 3)`` mm, ``centres : (3, c)``
    mm and ``weights : (3, c)`` (rows x, y, z: contiguous, so the inner loop vectorises), in float64,
    one query per parallel iteration (no ``(q, c)`` temporaries)."""
    out = np.empty((query.shape[0], 3))
    cx, cy, cz = centres[0], centres[1], centres[2]
    wx, wy, wz = weights[0], weights[1], weights[2]
    for i in numba.prange(query.shape[0]):
        x, y, z = query[i, 0], query[i, 1], query[i, 2]
        sx = sy = sz = 0.0
        for j in range(cx.shape[0]):
            dx, dy, dz = x - cx[j], y - cy[j], z - cz[j]
            r = np.sqrt(dx * dx + dy * dy + dz * dz)
            sx -= r * wx[j]
            sy -= r * wy[j]
            sz -= r * wz[j]
        out[i, 0], out[i, 1], out[i, 2] = sx, sy, sz
    return out


@numba.njit(cache=True, parallel=True)
def _normal_kernel(p, n, out):  # pragma: no cover - compiled
    """Fill ``out[:k, :k]`` with the sliding kernel ``−|p_i − p_j| (n_i · n_j)`` of ``p, n : (k, 3)``
    (mm, unit normals): one row per parallel iteration, no ``(k, k)`` temporaries."""
    for i in numba.prange(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        u, v, w = n[i, 0], n[i, 1], n[i, 2]
        for j in range(p.shape[0]):
            dx, dy, dz = x - p[j, 0], y - p[j, 1], z - p[j, 2]
            out[i, j] = -np.sqrt(dx * dx + dy * dy + dz * dz) * (u * n[j, 0] + v * n[j, 1] + w * n[j, 2])


def _check(points, normals):
    p = as_vertices(points, "points")
    n = as_vertices(normals, "normals")
    if p.shape != n.shape:
        raise InputError(f"points {p.shape} and normals {n.shape} must have the same shape")
    if len(p) < 13:
        raise InputError(f"a sliding interpolation needs at least 13 points, got {len(p)}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
        raise InputError("points and normals must be finite")
    length = np.linalg.norm(n, axis=1)
    if not np.allclose(length, 1.0, atol=1e-6):
        raise InputError("normals must have unit length (vertex normals of a closed surface)")
    return p, n


def _check_smoothing(smoothing) -> float:
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise InputError(f"smoothing must be >= 0 mm, got {smoothing!r}")
    return float(smoothing)


def _system(p: np.ndarray, n: np.ndarray, smoothing: float):
    """The (k + r)² saddle matrix, the centre and scale of the polynomial coordinates, and the
    ``(12, r)`` basis of the affine directions the normals see."""

    k = len(p)
    center = p.mean(axis=0)
    scale = float(np.abs(p - center).max()) or 1.0
    a = np.empty((k + 12, k + 12))
    _normal_kernel(p, n, a)
    a[np.arange(k), np.arange(k)] += smoothing
    x = np.hstack([np.ones((k, 1)), (p - center) / scale])  # (k, 4)
    poly = (n[:, :, None] * x[:, None, :]).reshape(k, 12)  # column 4c + l: n_c · x_l
    # translations are always kept; linear directions only where their footprint, beyond what the
    # translations explain, is not negligible (a rotation of a body of revolution is left out)
    shift, linear = [0, 4, 8], [1, 2, 3, 5, 6, 7, 9, 10, 11]
    pt = poly[:, shift]
    rest = poly[:, linear] - pt @ np.linalg.lstsq(pt, poly[:, linear], rcond=None)[0]
    _, sv, vt = np.linalg.svd(rest, full_matrices=False)
    top = np.linalg.norm(poly, 2)
    basis = np.zeros((12, 3 + int((sv > POLY_TOLERANCE * top).sum())))
    basis[shift, [0, 1, 2]] = 1.0
    basis[np.ix_(linear, np.arange(3, basis.shape[1]))] = vt[sv > POLY_TOLERANCE * top].T  # (12, r)
    r = basis.shape[1]
    a = a[:k + r, :k + r]
    a[:k, k:] = poly @ basis
    a[k:, :k] = a[:k, k:].T
    a[k:, k:] = 0.0
    return a, center, scale, basis


def _design(p: np.ndarray, n: np.ndarray, query: np.ndarray, center, scale, basis, anchors=None) -> np.ndarray:
    """``(3, q, k + 3a + r)``: component ``c`` of ``v(query)`` is ``design[c] @ coefficients``
    (coefficients: ``k`` normal weights, ``3a`` anchor weights by component, ``r`` polynomial)."""

    k, m = len(p), len(query)
    a = 0 if anchors is None else len(anchors)
    kq = -cdist(query, p)
    xq = np.hstack([np.ones((m, 1)), (query - center) / scale])
    out = np.zeros((3, m, k + 3 * a + basis.shape[1]))
    ka = -cdist(query, anchors) if a else None
    for c in range(3):
        out[c, :, :k] = kq * n[:, c]
        if a:
            out[c, :, k + c * a:k + (c + 1) * a] = ka
        out[c, :, k + 3 * a:] = xq @ basis[4 * c:4 * c + 4]
    return out


def _anchor_blocks(p, n, anchors, center, scale, basis):
    """The saddle matrix's anchor blocks: ``(k + r, 3a)`` against the surface functionals and the
    polynomial part, and ``(3a, 3a)`` between anchors (point values, by component): the anchors'
    point values applied to every basis function, i.e. :func:`_design` at the anchors."""
    k, a = len(p), len(anchors)
    d = _design(p, n, anchors, center, scale, basis, anchors).reshape(3 * a, -1)  # row c·a + i
    return np.hstack([d[:, :k], d[:, k + 3 * a:]]).T, d[:, k:k + 3 * a]


def _prepared(points, normals, smoothing, max_points: int, seed: int):
    """Checked ``points``, ``normals`` (all of them), the indices of the seeded subset used
    (:func:`lungdeform.geometry.mesh.thinned`), and that subset's saddle system (:func:`_system`)."""
    p, n = _check(points, normals)
    idx = thinned(len(p), max_points, seed)
    return p, n, idx, _system(p[idx], n[idx], _check_smoothing(smoothing))


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(a, b)
    except np.linalg.LinAlgError as exc:
        raise InputError("the sliding interpolation is singular (repeated points or a flat surface?)") from exc


@dataclass(frozen=True, eq=False)
class SlidingWeights:
    """The sliding interpolant from ``k`` surface points to ``m`` query points, as a linear map.

    Attributes
    ----------
    weights : (3, m, k) float
        Component ``c`` of the displacement at query ``i`` is ``weights[c, i] @ g`` with
        ``g = (normals * u).sum(1)`` the normal motion, mm.
    normals : (k, 3) float
        Unit outward normals at the surface points.
    """

    weights: np.ndarray
    normals: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """``(m, k)``: queries, surface points (as the matrix of the thin-plate interpolation)."""
        return self.weights.shape[1], self.weights.shape[2]

    def __matmul__(self, displacement) -> np.ndarray:
        """``(m, 3) float`` mm at the queries for ``displacement : (k, 3)`` mm at the surface points."""
        u = np.asarray(displacement, float)
        if u.shape != self.normals.shape:
            raise InputError(f"displacement has shape {u.shape}, expected {self.normals.shape}")
        g = np.einsum("kc,kc->k", self.normals, u)
        return np.ascontiguousarray((self.weights @ g).T)

    def __getitem__(self, rows) -> "SlidingWeights":
        """The same map for a subset of the queries (an index, a slice, an index array or a mask;
        a single index keeps its query axis: shape ``(1, k)``)."""
        if isinstance(rows, tuple):
            raise InputError("a SlidingWeights operator selects queries (rows) only")
        if isinstance(rows, (int, np.integer)):
            rows = [rows]
        return SlidingWeights(self.weights[:, rows], self.normals)

    def __array__(self, dtype=None, copy=None):
        raise InputError("a SlidingWeights operator is not a matrix: apply it as W @ u, u : (k, 3)")


def sliding_weights(points, normals, query, *, smoothing: float = SMOOTHING_MM, max_points: int = MAX_POINTS,
                    seed: int = 0) -> SlidingWeights:
    """The sliding interpolant through ``points : (k, 3)`` mm with unit ``normals : (k, 3)``,
    evaluated at ``query : (m, 3)`` mm, as a :class:`SlidingWeights` operator (one dense solve of
    size ``k + 12`` at most). More than ``max_points`` points: the same seeded subset as
    :func:`sliding_field` (the others get zero weight), so both are one interpolant."""
    p, n, idx, (a, center, scale, basis) = _prepared(points, normals, smoothing, max_points, seed)
    q = as_vertices(query, "query")
    if not np.all(np.isfinite(q)):
        raise InputError("query points contain NaN or infinity")
    ps, ns = p[idx], n[idx]
    design = _design(ps, ns, q, center, scale, basis).reshape(3 * len(q), -1)
    w = _solve(a, design.T)[:len(ps)].T  # a is symmetric: design @ a⁻¹ = (a⁻¹ designᵀ)ᵀ
    full = np.zeros((3, len(q), len(p)))
    full[:, :, idx] = w.reshape(3, len(q), len(ps))
    return SlidingWeights(full, n)


@dataclass(frozen=True, eq=False)
class RadialSum:
    """A field ``v(x) = Σ_j −|x − c_j| w_j + [1, x] @ affine`` (mm): the form of every sliding field.

    Attributes
    ----------
    centres : (3, c) float
        Kernel centres, mm, rows x, y, z.
    weights : (3, c) float
        Their vector weights, rows x, y, z.
    affine : (4, 3) float
        The polynomial part on ``[1, x, y, z]`` (world mm).
    """

    centres: np.ndarray
    weights: np.ndarray
    affine: np.ndarray

    def __call__(self, query) -> np.ndarray:
        """``(m, 3) float`` at ``query : (m, 3)`` mm (:func:`_radial_sum`, parallel)."""
        q = as_vertices(query, "query")
        if not np.all(np.isfinite(q)):
            raise InputError("query points contain NaN or infinity")
        q = np.ascontiguousarray(q, dtype=float)
        return _radial_sum(q, self.centres, self.weights) + q @ self.affine[1:] + self.affine[0]

    def __add__(self, other: "RadialSum") -> "RadialSum":
        """The sum of two fields, centres they share merged (a surface field and its landmark
        correction share every surface point: one kernel sum instead of two)."""
        c = np.concatenate([self.centres, other.centres], axis=1)
        unique, inverse = np.unique(c.T, axis=0, return_inverse=True)
        w = np.zeros((len(unique), 3))
        np.add.at(w, inverse.ravel(), np.concatenate([self.weights, other.weights], axis=1).T)
        return RadialSum(unique.T.copy(), w.T.copy(), self.affine + other.affine)


@dataclass(frozen=True, eq=False)
class SlidingField:
    """The sliding interpolant of one surface displacement, as a field ``R³ → R³``.

    Attributes
    ----------
    points, normals : (k, 3) float
        Surface points (mm) and their unit outward normals.
    displacements : (k, 3) float
        The surface displacement at the points, mm (only its normal part is used).
    anchors : (a, 3) float or None
        Interior points whose whole displacement the field also matches (:func:`sliding_correction`).
    """

    points: np.ndarray
    normals: np.ndarray
    displacements: np.ndarray
    coefficients: np.ndarray
    center: np.ndarray
    scale: float
    basis: np.ndarray
    anchors: np.ndarray | None = None

    def __call__(self, query) -> np.ndarray:
        """Displacement ``(m, 3) float`` mm at ``query : (m, 3)`` mm (:attr:`radial`)."""
        return self.radial(query)

    @cached_property
    def radial(self) -> "RadialSum":
        """This field as a :class:`RadialSum`: the coefficients regrouped per centre (surface points,
        then anchors), the polynomial part in world coordinates; equal to :func:`_design` ``@
        coefficients`` up to rounding, without its ``(3, m, k)`` matrix."""
        k, a = len(self.points), 0 if self.anchors is None else len(self.anchors)
        coef = np.asarray(self.coefficients, float)
        weights, centres = [coef[:k, None] * self.normals], [self.points]
        if a:
            weights.append(coef[k:k + 3 * a].reshape(3, a).T)
            centres.append(self.anchors)
        tail = coef[k + 3 * a:]
        poly = np.stack([self.basis[4 * c:4 * c + 4] @ tail for c in range(3)], axis=1)  # on [1, x̂]
        linear = poly[1:] / self.scale  # x̂ = (x − center) / scale
        affine = np.vstack([poly[:1] - self.center @ linear, linear])
        return RadialSum(np.concatenate(centres).T.copy(), np.concatenate(weights).T.copy(), affine)

    def move(self, query) -> np.ndarray:
        """``query + displacement(query)`` (mm)."""
        q = as_vertices(query, "query")
        return q + self(q)


def sliding_field(points, normals, displacements, *, smoothing: float = SMOOTHING_MM,
                  max_points: int = MAX_POINTS, seed: int = 0) -> SlidingField:
    """Fit the sliding interpolant to ``displacements : (k, 3)`` mm at ``points : (k, 3)`` mm with
    unit ``normals``. More than ``max_points`` points are thinned to a seeded random subset (the
    dense solve is O(k³))."""
    p, n, idx, (a, center, scale, basis) = _prepared(points, normals, smoothing, max_points, seed)
    u = as_vertices(displacements, "displacements")
    if u.shape != p.shape or not np.all(np.isfinite(u)):
        raise InputError(f"displacements must be finite with shape {p.shape}, got {u.shape}")
    p, n, u = p[idx], n[idx], u[idx]
    g = np.einsum("kc,kc->k", n, u)
    coef = _solve(a, np.concatenate([g, np.zeros(basis.shape[1])]))
    return SlidingField(p, n, u, coef, center, scale, basis)


def surface_weights(surface, query, keep=None, *, smoothing: float = SMOOTHING_MM) -> SlidingWeights:
    """:func:`sliding_weights` from the vertices of a closed ``surface`` (a
    :class:`~lungdeform.geometry.mesh.Surface`; its outward vertex normals), or only those marked in
    ``keep : (n,) bool`` (crop faces carry no data), to ``query : (m, 3)`` mm."""
    kept = np.ones(surface.n_vertices, bool) if keep is None else np.asarray(keep, bool)
    return sliding_weights(surface.vertices[kept], surface.vertex_normals[kept], query, smoothing=smoothing)


def checked_operator(matrix, shape: tuple[int, int], name: str = "landmark_matrix"):
    """``matrix`` (a :class:`SlidingWeights` or an ``(m, k)`` array) if it has ``shape`` (landmarks,
    kept vertices); else :class:`~lungdeform.errors.InputError` naming ``name``."""
    op = matrix if isinstance(matrix, SlidingWeights) else np.asarray(matrix, float)
    if tuple(op.shape) != tuple(shape):
        raise InputError(f"{name} has shape {tuple(op.shape)}, expected {tuple(shape)} (landmarks, kept vertices)")
    return op


def _check_anchors(anchors, values=None):
    q = as_vertices(anchors, "anchors")
    if len(q) < 1 or not np.all(np.isfinite(q)):
        raise InputError(f"anchors must be finite (a, 3) mm with a >= 1, got {q.shape}")
    close = sorted(cKDTree(q).query_pairs(1e-3))
    if close:  # an exact interpolant cannot pass one point twice
        i, j = close[0]
        raise InputError(f"anchors (landmarks) {i + 1} and {j + 1} coincide (within 0.001 mm): drop the repeated one")
    if values is None:
        return q
    v = as_vertices(values, "values")
    if v.shape != q.shape or not np.all(np.isfinite(v)):
        raise InputError(f"values must be finite with the anchors' shape {q.shape}, got {v.shape}")
    return q, v


def sliding_correction(points, normals, anchors, values, *, smoothing: float = SMOOTHING_MM,
                       max_points: int = MAX_POINTS, seed: int = 0) -> SlidingField:
    """The smoothest field that moves ``anchors : (a, 3)`` mm by ``values : (a, 3)`` mm exactly and
    leaves the *normal* motion of the surface ``points`` (unit ``normals``) unchanged, softly
    (smoothing ``λ`` mm, as in :func:`sliding_field`): a correction added to a surface-driven field
    that keeps the lung's boundary where that field put it. It is the sliding interpolant of zero
    normal motion plus the anchors' point values (kernel ``−|x − q_i|`` per component), with the
    same polynomial part. Solved once, densely (``k + 3a + 12`` unknowns at most)."""
    p, n, idx, (m, center, scale, basis) = _prepared(points, normals, smoothing, max_points, seed)
    q, v = _check_anchors(anchors, values)
    p, n = p[idx], n[idx]
    cross, between = _anchor_blocks(p, n, q, center, scale, basis)
    k, r = len(p), basis.shape[1]
    a = np.block([[m, cross], [cross.T, between]])
    order = np.r_[np.arange(k), k + r + np.arange(3 * len(q)), k + np.arange(r)]  # [normal | anchors | poly]
    rhs = np.concatenate([np.zeros(k + r), v.T.ravel()])
    coef = _solve(a, rhs)[order]
    return SlidingField(p, n, np.zeros_like(p), coef, center, scale, basis, q)


@dataclass(frozen=True, eq=False)
class _Projected:
    """The saddle system ``[[K + λI, B], [Bᵀ, 0]] [x; μ] = [C; D]`` (:func:`_system`'s, against the
    anchor columns of :func:`_anchor_blocks`), solved through the null space of ``Bᵀ`` (``k × r``,
    ``B = Q R``, reduced QR, ``P = I − Q Qᵀ``): ``x = Q y₁ + z`` with ``y₁ = R⁻ᵀ D`` and ``z = P z``,
    ``P (K + λI) P z = d = P (C − K Q y₁)``. ``A(λ) = P K P + λ P + Q Qᵀ`` is positive definite (the
    kernel ``−r`` is conditionally positive definite on the fields that the translations' constraint
    ``Σ α_j n_j = 0`` annihilates, which ``P`` ensures; ``Q Qᵀ`` is the identity on ``B``'s range) and
    maps both subspaces to themselves, so ``z = A(λ)⁻¹ d``: one Cholesky per smoothing, half the flops
    of the saddle matrix's LU. The anchor block ``[C; D]ᵀ [x; μ] = e₁ᵀy₁ + y₁ᵀe₁ − y₁ᵀ(QᵀKQ + λI)y₁ +
    GᵀG`` with ``e₁ = QᵀC`` and ``G = L⁻¹ d`` (``L Lᵀ = A(λ)``): one triangular solve for the Schur
    complement, a second only for :meth:`CorrectionSolver.surface_weights` (``z = L⁻ᵀ G``)."""

    kernel: np.ndarray
    basis: np.ndarray
    t11: np.ndarray
    e1: np.ndarray
    y1: np.ndarray
    d: np.ndarray

    @staticmethod
    def of(saddle: np.ndarray, cross: np.ndarray, k: int) -> "_Projected":
        q, r = np.linalg.qr(saddle[:k, k:])
        kq = saddle[:k, :k] @ q  # (k, r)
        y1 = solve_triangular(r, cross[k:], trans="T")  # Rᵀ y₁ = D
        c = cross[:k] - kq @ y1
        return _Projected(saddle[:k, :k], np.hstack([q, kq]), q.T @ kq, q.T @ cross[:k], y1, c - q @ (q.T @ c))

    def factor(self, smoothing: float) -> np.ndarray:
        """``L`` (lower) with ``L Lᵀ = A(λ) = K + λI + U W Uᵀ``, ``U = [Q, KQ]``,
        ``W = [[QᵀKQ + (1 − λ)I, −I], [−I, 0]]`` (one rank-2r product: ``P K P + λ P + Q Qᵀ``)."""
        r = len(self.t11)
        w = np.zeros((2 * r, 2 * r))
        w[:r, :r] = self.t11 + (1.0 - smoothing) * np.eye(r)
        w[:r, r:] = w[r:, :r] = -np.eye(r)
        a = self.kernel + (self.basis @ w) @ self.basis.T
        a[np.diag_indices_from(a)] += smoothing
        chol, info = lapack.dpotrf(a, lower=1, overwrite_a=1, clean=0)
        if info != 0:
            raise InputError("the sliding interpolation is singular (repeated points or a flat surface?)")
        return chol

    def quadratic(self, g: np.ndarray, smoothing: float) -> np.ndarray:
        """``[C; D]ᵀ [x; μ]``, ``(3a, 3a)``, from ``G = L⁻¹ d`` (class docstring)."""
        cross = self.e1.T @ self.y1
        t11 = self.t11 + smoothing * np.eye(len(self.t11))
        return cross + cross.T - self.y1.T @ t11 @ self.y1 + g.T @ g

    def surface(self, chol: np.ndarray, g: np.ndarray) -> np.ndarray:
        """``x : (k, 3a)``, the surface unknowns: ``Q y₁ + L⁻ᵀ G``."""
        r = len(self.t11)
        return self.basis[:, :r] @ self.y1 + solve_triangular(chol, g, lower=True, trans="T", check_finite=False)


@dataclass(frozen=True, eq=False)
class _CorrectionBlocks:
    """What a :class:`CorrectionSolver` needs that does not depend on the smoothing: the seeded subset
    ``index`` of the surface points (all ``normals`` kept), the saddle system without smoothing in its
    projected form (:class:`_Projected`), the anchor-anchor block (:func:`_anchor_blocks`) and the
    checked ``anchors``."""

    index: np.ndarray
    normals: np.ndarray
    projected: _Projected
    between: np.ndarray
    anchors: np.ndarray

    @staticmethod
    def of(points, normals, anchors, max_points: int, seed: int) -> "_CorrectionBlocks":
        p, n = _check(points, normals)
        idx = thinned(len(p), max_points, seed)
        q = _check_anchors(anchors)
        kernel, center, scale, basis = _system(p[idx], n[idx], 0.0)
        cross, between = _anchor_blocks(p[idx], n[idx], q, center, scale, basis)  # (k + r, 3a), (3a, 3a)
        return _CorrectionBlocks(idx, n, _Projected.of(kernel, cross, len(idx)), between, q)


class CorrectionSolver:
    """:func:`sliding_correction` through any subset of one set of anchors, for cross-validation:
    the surface system is solved once for every anchor column, and each subset costs one solve of
    ``3 × subset`` size (its Schur complement). ``predict(train, values, test)`` equals
    ``sliding_correction(points, normals, anchors[train], values, smoothing=λ)(anchors[test])``.
    :meth:`for_smoothings` builds one per smoothing, sharing what does not depend on it;
    :meth:`surface_weights` is :func:`sliding_weights` from the surface to the anchors, a by-product."""

    def __init__(self, points, normals, anchors, *, smoothing: float = SMOOTHING_MM,
                 max_points: int = MAX_POINTS, seed: int = 0):
        self._solve_surface(_CorrectionBlocks.of(points, normals, anchors, max_points, seed), _check_smoothing(smoothing))

    @classmethod
    def for_smoothings(cls, points, normals, anchors, smoothings, *, max_points: int = MAX_POINTS,
                       seed: int = 0) -> "dict[float, CorrectionSolver]":
        """One solver per surface smoothing (mm) in ``smoothings``, each as :class:`CorrectionSolver`
        gives it: the kernel matrix, the polynomial basis and the anchor blocks formed once (they do
        not depend on the smoothing), one Cholesky factorisation per smoothing (:class:`_Projected`)."""
        lams = [_check_smoothing(lam) for lam in smoothings]
        blocks = _CorrectionBlocks.of(points, normals, anchors, max_points, seed)
        out = {}
        for lam in lams:
            out[lam] = cls.__new__(cls)
            out[lam]._solve_surface(blocks, lam)
        return out

    def _solve_surface(self, blocks: "_CorrectionBlocks", smoothing: float) -> None:
        self.between, self.anchors, self.smoothing = blocks.between, blocks.anchors, smoothing
        chol = blocks.projected.factor(smoothing)  # the surface system, factored once per smoothing
        g = solve_triangular(chol, blocks.projected.d, lower=True, check_finite=False)
        self.schur = blocks.between - blocks.projected.quadratic(g, smoothing)
        # the surface unknowns of every anchor column (surface_weights), kept instead of the (k, k) factor
        self._surface = (blocks.index, blocks.normals, blocks.projected.surface(chol, g))

    @property
    def n_anchors(self) -> int:
        return len(self.anchors)

    def surface_weights(self) -> SlidingWeights:
        """:func:`sliding_weights` ``(points, normals, anchors, smoothing=λ)`` (same thinning): the sliding
        interpolation from the surface points to the anchors, from the solve already done (the
        anchor columns of the system are the interpolant's design at the anchors)."""
        idx, n, x = self._surface
        k, a = len(idx), self.n_anchors
        full = np.zeros((3, a, len(n)))
        full[:, :, idx] = x.T.reshape(3, a, k)
        return SlidingWeights(full, n)

    def _rows(self, ids) -> np.ndarray:
        ids = np.asarray(ids, int).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= self.n_anchors):
            raise InputError(f"anchor indices must lie in [0, {self.n_anchors}), got {ids.min()}..{ids.max()}")
        return np.concatenate([c * self.n_anchors + ids for c in range(3)])

    def predict(self, train, values, test) -> np.ndarray:
        """``(len(test), 3) float`` mm: the correction through ``values : (len(train), 3)`` mm at the
        anchors ``train`` (indices), at the anchors ``test``: ``β = S[tr, tr]⁻¹ v`` and, since the
        surface unknowns are ``−M⁻¹ C[:, tr] β``, the test anchors' values ``S[te, tr] β`` (``S`` the
        Schur complement ``B − Cᵀ M⁻¹ C``)."""
        tr, te = self._rows(train), self._rows(test)
        v = as_vertices(values, "values")
        if 3 * len(v) != len(tr):
            raise InputError(f"values: need one row per train anchor ({len(tr) // 3}), got {len(v)}")
        beta = _solve(self.schur[np.ix_(tr, tr)], v.T.ravel())
        out = self.schur[np.ix_(te, tr)] @ beta
        return np.ascontiguousarray(out.reshape(3, -1).T)
