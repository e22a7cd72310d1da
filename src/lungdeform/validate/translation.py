"""The one translation that brings a predicted lung surface closest to the real one (``validate single-scan``).

Every row of :mod:`lungdeform.validate.single_scan` is moved by it before it is scored (the phases of the
COPDgene and Learn2Reg masks were re-centred or cropped apart, the ITK scans carry a table shift), and
:mod:`lungdeform.validate.lung_pair` uses it to place a cut lung's crop faces in the other scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungdeform.fit.objective import Target
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.geometry.mesh import face_normals, thinned


def best_translation(vertices, faces, keep, target: Target, iterations: int = 50, *,
                     target_distance: SurfaceDistance | None = None, start=None) -> np.ndarray:
    """``t : (3,) float`` mm: the translation of the surface ``(vertices (n, 3) mm, faces)`` that
    minimises its symmetric closest-point distance to ``target`` (kept vertices on both sides): the
    fixed point of iterated closest points, where the mean residual of both directions (pooled) is
    zero, to within :data:`TOLERANCE_MM` (its last step; or after ``iterations`` exact steps).
    ``target_distance``: a prepared :class:`SurfaceDistance` of ``target.surface`` (reused); ``start``:
    the translation ``(3,)`` mm the descent starts from (zero by default).

    Plain iterated closest points creeps along the directions the surfaces slide in (on the COPDgene
    lungs it had stopped at 50 steps, up to 0.8 mm short of it), so each step here is a Gauss-
    Newton step on the mean squared closest-point distance (point-to-plane: :func:`_evaluate`; same
    fixed point), coarse to fine: first on a seeded subsample (:data:`COARSE_POINTS` per side, each
    side weighted as all its points), then on all points (:func:`_descend`)."""
    tgt = target.surface
    kt = np.ones(tgt.n_vertices, bool) if target.keep is None else np.asarray(target.keep, bool)
    vertices = np.asarray(vertices, float)
    to_target = target_distance or SurfaceDistance(tgt.vertices, tgt.faces)
    own = SurfaceDistance(vertices, faces)
    pts, tpts = vertices[np.asarray(keep, bool)], tgt.vertices[kt]
    share = len(pts) / (len(pts) + len(tpts))
    full = [_Side(to_target, pts, 1.0, share, face_normals(to_target.vertices, to_target.faces)),
            _Side(own, tpts, -1.0, 1.0 - share, face_normals(own.vertices, own.faces))]
    coarse = [_Side(s.distance, s.points[thinned(len(s.points), COARSE_POINTS, seed=k)], s.sign, s.weight, s.normals)
              for k, s in enumerate(full)]
    t = _descend(coarse, np.zeros(3) if start is None else np.asarray(start, float), 10 * TOLERANCE_MM, 4 * iterations)
    return _descend(full, t, TOLERANCE_MM, iterations)


#: :func:`best_translation`: points per side in its coarse stage (a seeded subsample).
COARSE_POINTS = 4000
#: :func:`best_translation`: it stops where its Newton step (the distance to the fixed point it
#: estimates) is below this, mm. Exact closest points switch faces as the surface moves, so on a lung
#: the mean residual stays noisy at ~1e-4 mm (steps of ~5e-4 mm) however long one iterates.
TOLERANCE_MM = 1e-3


@dataclass(frozen=True, eq=False)
class _Side:
    """One direction of the symmetric closest-point distance: ``points (k, 3)`` mm moved by
    ``sign · t`` to the surface of ``distance`` (``normals (m, 3)``, unit, per face), their mean
    residual counting ``weight`` (this direction's share of all the points)."""

    distance: SurfaceDistance
    points: np.ndarray
    sign: float
    weight: float
    normals: np.ndarray


def _evaluate(sides, t) -> tuple[np.ndarray, float, np.ndarray]:
    """At translation ``t``: ``(step (3,) mm, energy mm², curvature (3, 3))``: the pooled mean
    closest-point residual (the plain iterated-closest-points step; minus half the gradient of the
    energy), the pooled mean squared distance, and the point-to-plane curvature (mean n nᵀ of the
    closest faces' normals: the Gauss-Newton Hessian of half the energy)."""
    step, energy, curvature = np.zeros(3), 0.0, np.zeros((3, 3))
    for s in sides:
        moved = s.points + s.sign * t
        _, closest, face = s.distance.query(moved)
        r = s.sign * (closest - moved)
        n = s.normals[face]
        step += s.weight * r.mean(axis=0)
        energy += s.weight * float(np.mean(np.einsum("ij,ij->i", r, r)))
        curvature += s.weight * (n.T @ n) / len(n)
    return step, energy, curvature


def _descend(sides, t, tol: float, iterations: int) -> np.ndarray:
    """Gauss-Newton steps ``t ← t + H⁻¹ step`` (:func:`_evaluate` at ``t``) from ``t`` until one is
    shorter than ``tol`` mm (the point after it is returned; after ``iterations`` evaluations, the last
    point kept). A step that raised the energy is taken back and replaced by the plain step from the
    point before (iterated closest points, which does not raise it)."""
    best, plain = None, False  # best: (t, energy, step) of the last point kept
    for _ in range(iterations):
        step, energy, gauss = _evaluate(sides, t)
        if best is not None and energy > best[1] and not plain:
            t, plain = best[0] + best[2], True
            continue
        best, plain = (t, energy, step), False
        move = np.linalg.lstsq(gauss, step, rcond=None)[0]
        if np.linalg.norm(move) < np.linalg.norm(step):  # the curvature (trace 1) lacks a direction: plain step
            move = step
        t = t + move
        if np.linalg.norm(move) < tol:
            return t
    return best[0] if best is not None else t
