"""Interior motion: where points inside a lung (a tumour, a fiducial, landmarks) go at any volume.

The model moves surface vertices, ``x = p + s·u`` (METHOD §7). A point ``q`` inside the lung moves
by the same law, ``q + s·v(q)``, with ``v : R³ → R³`` (mm per unit ``s``) built from two parts:

1. **surface-driven**: the sliding interpolation of the surface's displacement per unit
   (:mod:`lungdeform.sliding`: the smoothest field with the surface's *normal* motion, since the
   lung slides along its boundary; reproduces any affine motion);
2. **landmark correction** (optional): where corresponding interior landmarks were observed at the
   fitted volumes, the part of their motion the surface cannot see (sliding along the chest wall,
   uneven expansion inside), as a second thin-plate spline through the per-unit residuals
   ``c_j = Σ_i s_i (o_ij − s_i·v_s(q_j)) / Σ_i s_i²`` (least squares over the targets ``i`` at
   scales ``s_i``, ``o_ij`` the observed displacement of landmark ``j``). Its smoothing (mm², the
   thin-plate regularisation) is chosen by k-fold cross-validation on the landmarks themselves.

Both parts are linear in ``s``, so a point's displacement per unit is precomputed once and playback
costs three multiply-adds per point, as for vertices. The correction holds for the posture the
landmarks were observed in: a model re-oriented to another gravity drops it.

Measured on the ITK right-lung pair (51 landmarks, 5-fold held out; ``lungdeform validate
itk-pair``): see ``docs/FITTING.md`` for the current figures of the surface-driven field alone and
with the landmark correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .interpolate import DisplacementField, displacement_field, interpolation_weights
from .mesh import as_vertices
from .sliding import MAX_POINTS, SlidingField, sliding_field

#: Candidate smoothings (mm², thin-plate regularisation) of the landmark correction.
SMOOTHING_MM2 = (0.0, 10.0, 100.0, 1000.0)
#: How the surface displacement extends inside: its normal motion (the default), or all of it
#: (the thin-plate spline of model files of schema 1).
KINDS = ("sliding", "thin_plate")
#: Surface fields through more vertices than this use a seeded subset.
MAX_SURFACE_POINTS = MAX_POINTS


def correction_per_unit(observed, scales, predicted_unit) -> np.ndarray:
    """``c : (m, 3) float`` mm per unit: the landmark motion the surface-driven field misses.

    observed : sequence of (m, 3) float
        Observed landmark displacement (target − end-exhale), mm, one array per target volume.
    scales : sequence of float
        The model's ``s`` at each target volume (units).
    predicted_unit : (m, 3) float
        Surface-driven displacement per unit at the landmarks, mm.

    Least squares over the targets of ``s_i·(predicted_unit + c) ≈ observed_i``.
    """
    s = np.asarray(scales, float).ravel()
    if len(s) != len(observed) or len(s) == 0:
        raise InputError(f"scales: need one per observed target ({len(observed)}), got {len(s)}")
    if not np.all(np.isfinite(s)) or not np.any(s != 0):
        raise InputError(f"scales must be finite and not all 0, got {s.tolist()}")
    p = as_vertices(predicted_unit, "predicted_unit")
    num = sum(si * (as_vertices(o, "observed") - si * p) for si, o in zip(s, observed))
    return np.ascontiguousarray(num / float(np.sum(s * s)))


def spline_predict(points, values, query, smoothing: float) -> np.ndarray:
    """Thin-plate spline through ``values : (k, 3)`` at ``points : (k, 3)`` mm, at ``query : (q, 3)``."""
    return interpolation_weights(points, query, smoothing=smoothing) @ np.asarray(values, float)


def select_smoothing(points, values, candidates=SMOOTHING_MM2, folds: int = 5, seed: int = 0) -> float:
    """The candidate smoothing (mm²) with the least mean held-out error of the thin-plate spline
    through ``values : (k, 3)`` at ``points : (k, 3)`` (``folds``-fold, seeded split).
    Fewer than 10 points: the largest candidate (too few to judge; the smoothest is safest)."""
    p = as_vertices(points, "points")
    v = as_vertices(values, "values")
    if len(p) < 10:
        return float(max(candidates))
    from .crossval import landmark_folds

    parts = landmark_folds(len(p), min(int(folds), len(p)), seed)
    best, best_err = None, np.inf
    for sm in candidates:
        err = 0.0
        for test in parts:
            train = np.setdiff1d(np.arange(len(p)), test)
            err += np.linalg.norm(spline_predict(p[train], v[train], p[test], sm) - v[test], axis=1).sum()
        if err < best_err - 1e-9:
            best, best_err = float(sm), err
    return best


def held_out_positions(landmarks, observed, scales, predicted_unit, folds, *, candidates=SMOOTHING_MM2,
                       seed: int = 0) -> list[np.ndarray]:
    """Landmarks moved by the corrected field, each predicted by a correction that did not see it.

    landmarks : (m, 3) float, mm (end-exhale); observed : per target (m, 3) mm displacement;
    scales : per target, units; predicted_unit : (m, 3) mm per unit (surface-driven);
    folds : index arrays partitioning ``range(m)``. Per fold, the correction and its smoothing
    (:func:`select_smoothing`, inner folds) come from the other folds' landmarks only.
    Returns per target ``(m, 3) float`` mm predicted positions.
    """
    q = as_vertices(landmarks, "landmarks")
    p = as_vertices(predicted_unit, "predicted_unit")
    out = [np.full_like(q, np.nan) for _ in scales]
    for test in folds:
        train = np.setdiff1d(np.arange(len(q)), test)
        c = correction_per_unit([np.asarray(o)[train] for o in observed], scales, p[train])
        sm = select_smoothing(q[train], c, candidates, seed=seed)
        v = p[test] + spline_predict(q[train], c, q[test], sm)
        for i, s in enumerate(scales):
            out[i][test] = q[test] + float(s) * v
    return out


@dataclass(frozen=True, eq=False)
class InteriorField:
    """Displacement per unit ``s`` of any point of a lung, mm (LPS, end-exhale frame).

    Attributes
    ----------
    surface : SlidingField
        The sliding interpolation of the surface displacement (mm per unit) through the end-exhale
        vertices and their outward normals (all, or a seeded subset of :data:`MAX_SURFACE_POINTS`).
    landmark : DisplacementField or None
        The thin-plate spline of the landmark correction (:func:`correction_per_unit`, mm per unit)
        through the end-exhale landmarks, with its smoothing; None without landmarks.
    """

    surface: SlidingField | DisplacementField
    landmark: DisplacementField | None = None

    @property
    def corrected(self) -> bool:
        return self.landmark is not None

    def displacement(self, points) -> np.ndarray:
        """``v : (q, 3) float`` mm per unit at ``points : (q, 3)`` mm LPS."""
        v = self.surface(points)
        return v if self.landmark is None else np.ascontiguousarray(v + self.landmark(points))

    def positions(self, points, scale: float) -> np.ndarray:
        """``q + s·v(q) : (q, 3) float`` mm LPS."""
        q = as_vertices(points, "points")
        return q + float(scale) * self.displacement(q)


def interior_field(vertices, displacement, landmarks=None, correction=None, smoothing: float = 0.0,
                   *, normals, kind: str = "sliding", seed: int = 0) -> InteriorField:
    """An :class:`InteriorField` from a lung's ``vertices : (n, 3)`` mm, their unit outward
    ``normals : (n, 3)`` and ``displacement : (n, 3)`` mm per unit, with an optional landmark
    ``correction : (m, 3)`` at ``landmarks : (m, 3)`` mm (``smoothing`` mm²). ``kind``: one of
    :data:`KINDS`; ``"thin_plate"`` (the thin-plate spline of the whole displacement, no normals
    used) is how model files of schema 1 were made."""
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise InputError(f"smoothing must be >= 0 mm², got {smoothing!r}")
    if kind == "sliding":
        surface = sliding_field(vertices, normals, displacement, max_points=MAX_SURFACE_POINTS, seed=seed)
    elif kind == "thin_plate":
        surface = displacement_field(vertices, displacement, max_points=MAX_SURFACE_POINTS, seed=seed)
    else:
        raise InputError(f"interior kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if landmarks is None or correction is None:
        return InteriorField(surface)
    m = len(np.asarray(landmarks))  # every landmark: the correction is never thinned
    return InteriorField(surface, displacement_field(landmarks, correction, smoothing=float(smoothing), max_points=max(m, 1)))
