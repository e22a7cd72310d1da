"""The correspondence field: interior motion carried by a smooth map from one lung surface onto another.

Where the sliding interpolation (:mod:`lungdeform.interior.sliding`) keeps only the surface's normal
motion, this field keeps a whole point-to-point map of the lung, found by registering the end-exhale
surface onto a larger one with strong smoothness (:mod:`lungdeform.fit.registration`): an affine
``W = (A | t)`` (the solid moments' affine) followed by a Gaussian radial field, so a point ``q``
(mm, LPS, end-exhale frame) moves per unit ``s`` of the model by

    v(q) = L [q; 1] + Σ_j exp(−|W [q; 1] − c_j|² / (2 w²)) g_j,

with ``L (3, 4)`` the affine part of the displacement per unit (``(A − I | t) / s_target``),
``c_j (k, 3)`` mm the Gaussian centres (the affine image of the end-exhale surface points),
``g_j (k, 3)`` mm per unit their weights and ``w`` mm the kernel width. A built model's map
(:func:`surface_extension`) adds the population default's interior prior, and a fit's map its
motion prior (:mod:`lungdeform.interior.motion_prior`), tapered to zero at the surface (``prior``,
:class:`lungdeform.interior.prior.TaperedPrior`), so that on the surface the field is the surface's
own motion. The field is linear in ``s`` like every interior field, so a
point's displacement per unit is computed once and playback costs three multiply-adds per point.
Measured on the DIR-Lab COPDgene masks in docs/FITTING.md ("Interior from the surfaces alone").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numba
import numpy as np
from scipy.spatial.distance import cdist

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import as_vertices

from .prior import TaperedPrior


def _affine(matrix, name: str) -> np.ndarray:
    m = np.ascontiguousarray(matrix, dtype=np.float64)
    if m.shape != (3, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"{name} must be a finite (3, 4) affine [A | t], got shape {m.shape}")
    return m


@dataclass(frozen=True, eq=False)
class SurfaceMapField:
    """Displacement per unit of any point of a lung from a surface-to-surface map (module docstring).

    Attributes
    ----------
    linear : (3, 4) float
        ``L = [M | b]``: the affine part of the displacement per unit, ``M q + b`` (mm per unit).
    warp : (3, 4) float
        ``W = [A | t]``: where the Gaussian part is evaluated (``A q + t``, mm).
    centers : (k, 3) float
        Gaussian centres, mm LPS.
    weights : (k, 3) float
        Gaussian weights, mm per unit.
    width_mm : float
        Kernel width ``w``, mm.
    prior : TaperedPrior or None
        An interior prior added on top, zero on the lung's surface (mm per unit); None: none.
    """

    linear: np.ndarray
    warp: np.ndarray
    centers: np.ndarray
    weights: np.ndarray
    width_mm: float
    prior: TaperedPrior | None = None

    def __post_init__(self):
        object.__setattr__(self, "linear", _affine(self.linear, "linear"))
        object.__setattr__(self, "warp", _affine(self.warp, "warp"))
        c, g = as_vertices(self.centers, "centers"), as_vertices(self.weights, "weights")
        if len(c) != len(g):
            raise InputError(f"weights: need one row per centre ({len(c)}), got {len(g)}")
        if not (np.isfinite(self.width_mm) and self.width_mm > 0):
            raise InputError(f"width_mm must be > 0 mm, got {self.width_mm!r}")
        object.__setattr__(self, "centers", c)
        object.__setattr__(self, "weights", g)
        object.__setattr__(self, "width_mm", float(self.width_mm))
        if self.prior is not None and not isinstance(self.prior, TaperedPrior):
            raise InputError(f"prior must be a TaperedPrior or None, got {type(self.prior).__name__}")

    def __call__(self, points) -> np.ndarray:
        """``v : (q, 3) float`` mm per unit at ``points : (q, 3)`` mm LPS."""
        q = as_vertices(points, "points")
        out = np.ascontiguousarray(q @ self.linear[:, :3].T + self.linear[:, 3])
        y = np.ascontiguousarray(q @ self.warp[:, :3].T + self.warp[:, 3])
        _gauss_sum(y, self.centers, self.weights, 1.0 / (2.0 * self.width_mm**2), out)
        if self.prior is not None:
            out += self.prior(q)
        return out

    def along_rows(self, starts, step, counts) -> np.ndarray:
        """``v : (Σ counts, 3) float`` mm per unit at the points of straight rows, row ``r`` the points
        ``starts[r] + a·step`` (``a = 0 … counts[r] − 1``; ``starts : (r, 3)`` mm LPS, ``step`` (3,) mm),
        row after row: :meth:`__call__` of those points, with the Gaussians along each row by
        multiplication (:func:`_gauss_rows`, two or three exponentials a row and centre)."""
        s0 = as_vertices(starts, "starts")
        st = np.asarray(step, dtype=np.float64).reshape(3)
        n = np.asarray(counts, dtype=np.int64).reshape(-1)
        if len(n) != len(s0) or np.any(n < 0) or not np.all(np.isfinite(st)):
            raise InputError(f"counts: need one count >= 0 per row ({len(s0)}) and a finite (3,) step, got "
                             f"{len(n)} counts, step {st.tolist()}")
        offsets = np.concatenate([[0], np.cumsum(n)])
        out = np.empty((int(offsets[-1]), 3))
        lin, warp = self.linear[:, :3], self.warp[:, :3]
        linear = (np.einsum("rb,ab->ra", s0, lin) + self.linear[:, 3], lin @ st)
        gauss = (self.centers, self.weights, 1.0 / (2.0 * self.width_mm**2))
        _gauss_rows(np.einsum("rb,ab->ra", s0, warp) + self.warp[:, 3], warp @ st, offsets, gauss, linear, out)
        if self.prior is not None and len(out):
            a = np.arange(len(out)) - np.repeat(offsets[:-1], n)
            out += self.prior(np.repeat(s0, n, axis=0) + a[:, None] * st)
        return out

    def with_prior(self, prior: TaperedPrior | None) -> "SurfaceMapField":
        """A new field with ``prior`` (:class:`~lungdeform.interior.prior.TaperedPrior`) added on top (None: without one)."""
        return replace(self, prior=prior)


@numba.njit(cache=True, parallel=True)
def _gauss_sum(y, centers, weights, inv, out):
    """Add, in place, ``Σ_j exp(−|y_i − c_j|² · inv) g_j`` to ``out[i]`` (mm per unit) for ``y : (q, 3)``
    mm, ``centers : (k, 3)``, ``weights : (k, 3)``: one fused loop parallel over the points (no
    ``(q, k)`` kernel matrix)."""
    for i in numba.prange(y.shape[0]):
        s0 = s1 = s2 = 0.0
        for j in range(centers.shape[0]):
            d0, d1, d2 = y[i, 0] - centers[j, 0], y[i, 1] - centers[j, 1], y[i, 2] - centers[j, 2]
            e = np.exp(-(d0 * d0 + d1 * d1 + d2 * d2) * inv)
            s0 += e * weights[j, 0]
            s1 += e * weights[j, 1]
            s2 += e * weights[j, 2]
        out[i, 0] += s0
        out[i, 1] += s1
        out[i, 2] += s2
    return out


#: Below this a Gaussian factor is dropped (it only falls farther along the row): no float64 sum feels it.
_NEGLIGIBLE = 1e-300
#: A row whose every Gaussian stays above ``exp(−SWEEP_EXPONENT)`` (far from float64's smallest
#: normal number, ``exp(−708)``) is swept from its first point (:func:`_sweep_row`).
_SWEEP_EXPONENT = 600.0


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _sweep_row(start, step, n, centers, weights_t, inv, out_rows):
    """Add ``Σ_j exp(−|y_a − c_j|² · inv) g_j`` to ``out_rows[a]`` for ``y_a = start + a·step``, ``a < n``:
    all centres at once from ``a = 0``, each Gaussian times its ratio, the ratio times
    ``exp(−2 inv |step|²)``, a point (no exponential past the first point; the centre loop vectorises).
    Only for rows whose Gaussians all stay above ``exp(−600)`` (:func:`_gauss_rows`)."""
    k = centers.shape[0]
    hh = step[0] * step[0] + step[1] * step[1] + step[2] * step[2]
    q = np.exp(-2.0 * inv * hh)
    t, ratio = np.empty(k), np.empty(k)
    for j in range(k):
        d0, d1, d2 = start[0] - centers[j, 0], start[1] - centers[j, 1], start[2] - centers[j, 2]
        t[j] = np.exp(-(d0 * d0 + d1 * d1 + d2 * d2) * inv)
        ratio[j] = np.exp(-(2.0 * (step[0] * d0 + step[1] * d1 + step[2] * d2) + hh) * inv)
    g0, g1, g2 = weights_t[0], weights_t[1], weights_t[2]
    for a in range(n):
        s0 = s1 = s2 = 0.0
        for j in range(k):
            tj = t[j]
            s0 += tj * g0[j]
            s1 += tj * g1[j]
            s2 += tj * g2[j]
            t[j] = tj * ratio[j]
            ratio[j] *= q
        out_rows[a, 0] += s0
        out_rows[a, 1] += s1
        out_rows[a, 2] += s2


@numba.njit(cache=True)
def _peak_row(start, step, n, centers, weights, inv, out_rows):
    """:func:`_sweep_row` for any row: each centre's Gaussian from its largest value on the row outward
    (every factor ≤ 1, nothing overflows, values under :data:`_NEGLIGIBLE` dropped)."""
    hh = step[0] * step[0] + step[1] * step[1] + step[2] * step[2]
    q = np.exp(-2.0 * inv * hh)
    for j in range(centers.shape[0]):
        d0, d1, d2 = start[0] - centers[j, 0], start[1] - centers[j, 1], start[2] - centers[j, 2]
        lin = step[0] * d0 + step[1] * d1 + step[2] * d2
        peak = min(max(-lin / hh, 0.0), n - 1.0) if hh > 0 else 0.0
        a0 = int(np.floor(peak + 0.5))
        e0, e1, e2 = d0 + a0 * step[0], d1 + a0 * step[1], d2 + a0 * step[2]
        t0 = np.exp(-(e0 * e0 + e1 * e1 + e2 * e2) * inv)
        if t0 < _NEGLIGIBLE:
            continue
        g0, g1, g2 = weights[j, 0], weights[j, 1], weights[j, 2]
        out_rows[a0, 0] += t0 * g0
        out_rows[a0, 1] += t0 * g1
        out_rows[a0, 2] += t0 * g2
        slope = 2.0 * (step[0] * e0 + step[1] * e1 + step[2] * e2)
        for sign in (1, -1):
            t, ratio = t0, np.exp(-(sign * slope + hh) * inv)
            a = a0 + sign
            while 0 <= a < n:
                t *= ratio
                if t < _NEGLIGIBLE:
                    break
                ratio *= q
                out_rows[a, 0] += t * g0
                out_rows[a, 1] += t * g1
                out_rows[a, 2] += t * g2
                a += sign


@numba.njit(cache=True, parallel=True)
def _gauss_rows(starts, step, offsets, gauss, linear, out):
    """Write into ``out`` at the points ``y = starts[r] + a·step`` of row ``r`` (``out[offsets[r] + a]``,
    ``a < offsets[r + 1] − offsets[r]``), parallel over rows, ``base[r] + a·slope + Σ_j exp(−|y − c_j|²
    · inv) g_j`` (``gauss = (centres (k, 3), weights (k, 3), inv)``, ``linear = (base (r, 3), slope (3,))``,
    the affine part along the rows).

    Along a row the Gaussian of a centre is ``t(a) = exp(−inv·|d + a·step|²)`` (``d = starts[r] − c``);
    each next value is ``t(a + 1) = t(a)·R(a)``, the ratio ``R(a) = exp(−inv·(2 step·(d + a·step) +
    |step|²))`` itself times ``exp(−2 inv |step|²)`` a point: two or three exponentials a row and
    centre instead of one a point. Rows where every Gaussian stays far above float64's underflow are
    swept from their first point (:func:`_sweep_row`), others from each Gaussian's peak
    (:func:`_peak_row`). A value after ``m`` steps carries at most ``m²/2`` roundings (relative error
    below 1e-10 for rows under 1400 points)."""
    centers, weights, inv = gauss
    base, slope = linear
    weights_t = np.ascontiguousarray(weights.T)
    for r in numba.prange(starts.shape[0]):
        o, n = offsets[r], offsets[r + 1] - offsets[r]
        if n == 0:
            continue
        far = 0.0
        for j in range(centers.shape[0]):
            for a in (0, n - 1):
                d0 = starts[r, 0] + a * step[0] - centers[j, 0]
                d1 = starts[r, 1] + a * step[1] - centers[j, 1]
                d2 = starts[r, 2] + a * step[2] - centers[j, 2]
                far = max(far, d0 * d0 + d1 * d1 + d2 * d2)
        acc = np.zeros((n, 3))
        if far * inv < _SWEEP_EXPONENT:
            _sweep_row(starts[r], step, n, centers, weights_t, inv, acc)
        else:
            _peak_row(starts[r], step, n, centers, weights, inv, acc)
        for a in range(n):
            for c in range(3):
                out[o + a, c] = base[r, c] + a * slope[c] + acc[a, c]
    return out


#: Gaussian width (mm) and number of centres of :func:`surface_extension`.
EXTENSION_WIDTH_MM = 30.0
EXTENSION_CENTRES = 300


def surface_extension(vertices, displacement, *, width_mm: float = EXTENSION_WIDTH_MM,
                      centres: int = EXTENSION_CENTRES, ridge: float = 1e-3) -> SurfaceMapField:
    """A :class:`SurfaceMapField` that carries a surface displacement inside the lung: the
    least-squares affine part of ``displacement : (n, 3)`` (mm per unit) over ``vertices : (n, 3)``
    (mm LPS), plus Gaussians of width ``width_mm`` centred on ``centres`` evenly spread vertices
    (every ``n // centres``-th), their weights the ridge-regularised least squares of the rest.
    ``warp`` is the identity: the field is evaluated in the end-exhale frame."""
    p = as_vertices(vertices)
    u = as_vertices(displacement, "displacement")
    if len(u) != len(p) or len(p) < 4:
        raise InputError(f"displacement must have one row per vertex ({len(p)}, at least 4), got {len(u)}")
    x = np.c_[p, np.ones(len(p))]
    lin = np.linalg.lstsq(x, u, rcond=None)[0].T  # (3, 4)
    rest = u - x @ lin.T
    c = p[:: max(1, len(p) // int(centres))]
    k = np.exp(-cdist(p, c, "sqeuclidean") / (2.0 * width_mm**2))
    normal = k.T @ k
    g = np.linalg.solve(normal + ridge * np.trace(normal) / len(c) * np.eye(len(c)), k.T @ rest)
    return SurfaceMapField(lin, np.c_[np.eye(3), np.zeros(3)], c, g, float(width_mm))
