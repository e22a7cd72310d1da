"""Surface refinement: the fitted displacement brought onto the target surfaces by a smooth residual (beyond the paper).

The model's displacement ``u = k·F·d`` (Green's-function force, stiffness field, corrected
directions; :mod:`lungdeform.fit.fitting`) has a few dozen degrees of freedom. With the volume
changes of breath-hold CT (+30 to +100 %, DIR-Lab COPDgene) it leaves 2–3 mm of surface error
where a free-form registration (CPD) leaves about 2. This step adds to ``u`` a per-vertex
residual, made smooth, in coarse-to-fine rounds (Gaussian widths :data:`WIDTHS_MM`, down to
``finest_mm``):

    r_i^t = closest point of target t to x_i^t − x_i^t,      x_i^t = p_i + s_t u_i   (kept vertices only),
    Δu_i  = Σ_t s_t G_w[r^t]_i / Σ_t s_t²,                   u ← u + Δu,

``G_w`` the normalised Gaussian average over the end-exhale positions ``p`` (width ``w`` mm, cut
at 3 ``w``; vertices on crop faces get no residual of their own and take their neighbours'). The
closest point moves a vertex along the target's normal, so the residual carries no tangential
sliding. The model stays linear in the scale ``s``: playback is unchanged, ``x = p + s·u``
(three multiply-adds per vertex). The rest of the fit (c1…c9, stiffness, the interior field) is
not touched; :attr:`Refinement.before` keeps the unrefined displacement for the ablation.

Measured: docs/FITTING.md ("Surface refinement").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from lungdeform.errors import InputError
from lungdeform.geometry.distance import DistanceStack, SurfaceDistance

#: Gaussian widths (mm) of the coarse-to-fine rounds; those below ``finest_mm`` are skipped.
WIDTHS_MM = (20.0, 14.0, 10.0, 7.0, 5.0)
#: Default finest width (mm): about one to two model-mesh edges.
FINEST_MM = 5.0
#: Residual updates per width.
ITERATIONS = 2
#: Kernel cut-off, in widths.
CUTOFF = 3.0


@dataclass(frozen=True, eq=False)
class Refinement:
    """What :func:`refine_displacement` did: ``displacement (n, 3)`` mm per unit (refined),
    ``before (n, 3)`` mm per unit, the ``widths_mm`` used, and the largest and mean per-vertex
    change ``|Δu|·s`` at the largest scale (mm)."""

    displacement: np.ndarray
    before: np.ndarray
    widths_mm: tuple[float, ...]
    max_change_mm: float
    mean_change_mm: float

    def as_dict(self) -> dict:
        return {"widths_mm": list(self.widths_mm), "max_change_mm": self.max_change_mm,
                "mean_change_mm": self.mean_change_mm}


def gaussian_smoother(points, width_mm: float) -> sp.csr_matrix:
    """``W : (n, n)`` sparse, rows summing to 1: the Gaussian average (width ``width_mm``, cut at
    :data:`CUTOFF` widths) over ``points : (n, 3)`` mm, each point included with weight 1."""
    pts = np.ascontiguousarray(points, float)
    pairs = cKDTree(pts).query_pairs(CUTOFF * width_mm, output_type="ndarray")
    w = np.exp(-np.sum((pts[pairs[:, 0]] - pts[pairs[:, 1]]) ** 2, axis=1) / (2.0 * width_mm ** 2))
    n = len(pts)
    rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
    return sp.csr_matrix((np.concatenate([w, w, np.ones(n)]), (rows, cols)), shape=(n, n))


def refine_displacement(rest_vertices, displacement, targets, scales, keep=None, *,
                        finest_mm: float = FINEST_MM, iterations: int = ITERATIONS) -> Refinement:
    """Refine ``displacement : (n, 3)`` mm per unit of a model whose end-exhale vertices are
    ``rest_vertices : (n, 3)`` mm onto ``targets`` (surfaces in the same frame, mm) at ``scales``
    (one per target, the model's ``s``; module docstring). ``keep : (n,) bool``: the vertices
    whose residual counts (default all; False on crop faces). ``finest_mm``: the smallest
    Gaussian width (mm, ≥ 1)."""
    p = np.ascontiguousarray(rest_vertices, float)
    u0 = np.ascontiguousarray(displacement, float)
    s = np.asarray(scales, float).reshape(-1)
    targets = list(targets)
    if u0.shape != p.shape or p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"displacement must be (n, 3) like the vertices {p.shape}, got {u0.shape}")
    if len(targets) != len(s) or not len(s) or not np.all(np.isfinite(s)) or not np.any(s != 0):
        raise InputError(f"need one finite scale per target, not all zero; got {len(s)} scale(s) for {len(targets)} target(s)")
    if not (np.isfinite(finest_mm) and finest_mm >= 1.0):
        raise InputError(f"finest_mm must be ≥ 1 mm, got {finest_mm!r}")
    kept = np.ones(len(p), bool) if keep is None else np.asarray(keep, bool)
    if kept.shape != (len(p),):
        raise InputError(f"keep must be one bool per vertex ({len(p)}), got shape {kept.shape}")
    # every target's closest points in one search, each started from its last faces (the vertices move
    # little between rounds, so those bound the search tightly; exact either way)
    stack = DistanceStack([SurfaceDistance(t.vertices, t.faces) for t in targets])
    faces = None
    widths = tuple(w for w in WIDTHS_MM if w >= finest_mm - 1e-9) or (float(finest_mm),)
    u = u0.copy()
    for width in widths:
        smoother = gaussian_smoother(p, width)
        weight = smoother @ kept.astype(float)
        for _ in range(int(iterations)):
            x = [p + st * u for st in s]
            found = stack.query(range(len(x)), x, faces)
            faces = [face for _, _, face in found]
            r = np.hstack([np.where(kept[:, None], c - xt, 0.0) for (_, c, _), xt in zip(found, x)])
            smoothed = smoother @ r  # (n, 3 × targets): every target's residual in one pass over the kernel
            step = np.zeros_like(u)
            for t, st in enumerate(s):
                step += st * smoothed[:, 3 * t:3 * t + 3]
            u = u + step / np.maximum(weight, 1e-9)[:, None] / float(np.sum(s ** 2))
    change = np.linalg.norm(u - u0, axis=1) * float(np.max(np.abs(s)))
    return Refinement(u, u0, widths, float(change.max()), float(change.mean()))
