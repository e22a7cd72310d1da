"""Interior motion: where points inside a lung (a tumour, a fiducial, landmarks) go at any volume.

The model moves surface vertices, ``x = p + s·u`` (docs/METHOD_NOTES.md §7). A point ``q`` inside the lung moves
by the same law, ``q + s·v(q)``, with ``v : R³ → R³`` (mm per unit ``s``) built from two parts:

1. **surface-driven**: the sliding interpolation of the surface's displacement per unit
   (:mod:`lungdeform.interior.sliding`: the smoothest field with the surface's *normal* motion, since the
   lung slides along its boundary; reproduces any affine motion);
2. **landmark correction** (optional): where corresponding interior landmarks were observed at the
   fitted volumes, the part of their motion the surface cannot see (sliding along the chest wall,
   uneven expansion inside), the per-unit residuals
   ``c_j = Σ_i s_i (o_ij − s_i·v_s(q_j)) / Σ_i s_i²`` (least squares over the targets ``i`` at
   scales ``s_i``, ``o_ij`` the observed displacement of landmark ``j``), interpolated by
   :func:`lungdeform.interior.sliding.sliding_correction`: the smoothest field through the ``c_j`` that
   leaves the surface's normal motion unchanged (softly: surface smoothing ``λ`` mm, chosen from
   :data:`CORRECTION_SMOOTHING_MM` by k-fold cross-validation on the landmarks themselves).

Both parts are linear in ``s``, so a point's displacement per unit is precomputed once and playback
costs three multiply-adds per point, as for vertices. The correction holds for the posture the
landmarks were observed in: a model re-oriented to another gravity drops it.

:data:`KINDS` names the three fields a model file can hold: ``"sliding"`` (the above; schema 3),
``"sliding_thin_plate"`` (schema-2 files: the same surface part, the correction a thin-plate spline
through the ``c_j`` that ignores the surface, smoothing in mm²) and ``"thin_plate"`` (schema-1 files:
the thin-plate spline of the whole surface displacement, and the same thin-plate correction).
Older files play back as they were made.

Measured on the ITK right-lung pair (51 landmarks, 5-fold held out; ``lungdeform validate
itk-pair``): see ``docs/FITTING.md`` for the current figures of the surface-driven field alone and
with the landmark correction.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import as_vertices

from .correspondence import CorrespondenceField
from .interpolate import DisplacementField, displacement_field, interpolation_weights
from .sliding import MAX_POINTS, CorrectionSolver, RadialSum, SlidingField, sliding_correction, sliding_field

#: Candidate smoothings (mm², thin-plate regularisation) of the thin-plate landmark correction.
SMOOTHING_MM2 = (0.0, 10.0, 100.0, 1000.0)
#: Candidate surface smoothings ``λ`` (mm) of the sliding landmark correction.
CORRECTION_SMOOTHING_MM = (100.0, 300.0, 1000.0)
#: The interior fields: surface part and landmark correction (module docstring).
KINDS = ("sliding", "sliding_thin_plate", "thin_plate")
#: Each kind in words: the surface part, and the landmark correction (for reports).
KIND_TEXT = {"sliding": ("sliding interpolation of the surface's normal motion",
                         "the fit's landmark correction, which keeps the surface's normal motion"),
             "sliding_thin_plate": ("sliding interpolation of the surface's normal motion",
                                    "the fit's thin-plate landmark correction (model schema 2)"),
             "thin_plate": ("thin-plate spline of the surface displacement (model schema 1)",
                            "the fit's thin-plate landmark correction")}
#: Surface fields through more vertices than this use a seeded subset.
MAX_SURFACE_POINTS = MAX_POINTS


def landmark_folds(n: int, folds: int = 5, seed: int = 0, *, parameter: str = "folds") -> list[np.ndarray]:
    """``folds`` disjoint index arrays covering ``range(n)`` (seeded random split, sizes within 1).
    ``parameter``: how the error for a bad ``folds`` names it (e.g. ``"--folds"``)."""
    if not 2 <= int(folds) <= n:
        raise InputError(f"{parameter} must be between 2 and the number of landmarks ({n}), got {folds}")
    idx = np.random.default_rng(seed).permutation(int(n))
    return [np.sort(part) for part in np.array_split(idx, int(folds))]


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


def _select(candidates, predict, index, values, folds: int, seed: int) -> float:
    """The candidate whose ``predict(candidate, train, values[train], test)`` (landmark indices
    into ``index``'s space) has the least summed held-out error over a seeded ``folds``-fold split
    of ``index``; fewer than 10 points: the largest candidate (too few to judge; the smoothest is
    safest)."""
    idx = np.asarray(index, int).ravel()
    v = as_vertices(values, "values")
    if len(idx) < 10:
        return float(max(candidates))

    parts = landmark_folds(len(idx), min(int(folds), len(idx)), seed)
    best, best_err = None, np.inf
    for cand in candidates:
        err = 0.0
        for test in parts:
            train = np.setdiff1d(np.arange(len(idx)), test)
            err += np.linalg.norm(predict(cand, idx[train], v[train], idx[test]) - v[test], axis=1).sum()
        if err < best_err - 1e-9:
            best, best_err = float(cand), err
    return best


def _held_out(q, observed, scales, predicted_unit, folds, select, predict) -> list[np.ndarray]:
    """Per fold, the correction through the other folds' landmarks (``select(train, c)`` picks its
    smoothing on them, ``predict(smoothing, train, c, test)`` moves the fold's own): the landmarks
    ``q : (m, 3)`` mm moved to each target, ``(m, 3) float`` mm per target."""
    p = as_vertices(predicted_unit, "predicted_unit")
    if len(p) != len(q):
        raise InputError(f"predicted_unit: need one row per landmark ({len(q)}), got {len(p)}")
    out = [np.full_like(q, np.nan) for _ in scales]
    for test in folds:
        train = np.setdiff1d(np.arange(len(q)), test)
        c = correction_per_unit([np.asarray(o)[train] for o in observed], scales, p[train])
        v = p[test] + predict(select(train, c), train, c, test)
        for i, s in enumerate(scales):
            out[i][test] = q[test] + float(s) * v
    return out


def _spline_predictor(points):
    p = as_vertices(points, "points")
    return lambda sm, train, values, test: spline_predict(p[train], values, p[test], sm)


def select_smoothing(points, values, candidates=SMOOTHING_MM2, folds: int = 5, seed: int = 0) -> float:
    """The candidate smoothing (mm²) with the least mean held-out error of the thin-plate spline
    through ``values : (k, 3)`` at ``points : (k, 3)`` (``folds``-fold, seeded split).
    Fewer than 10 points: the largest candidate (too few to judge; the smoothest is safest)."""
    p = as_vertices(points, "points")
    return _select(candidates, _spline_predictor(p), np.arange(len(p)), values, folds, seed)


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
    predict = _spline_predictor(q)
    return _held_out(q, observed, scales, predicted_unit, folds,
                     lambda train, c: _select(candidates, predict, train, c, 5, seed), predict)


def correction_solvers(points, normals, landmarks, candidates=CORRECTION_SMOOTHING_MM, *,
                       seed: int = 0) -> dict[float, CorrectionSolver]:
    """One :class:`~lungdeform.interior.sliding.CorrectionSolver` per candidate surface smoothing (mm): the
    sliding landmark correction from the surface ``points : (k, 3)`` mm (unit ``normals``) through
    any subset of ``landmarks : (m, 3)`` mm, each factorised once."""
    return {float(lam): CorrectionSolver(points, normals, landmarks, smoothing=float(lam), max_points=MAX_SURFACE_POINTS,
                                         seed=seed) for lam in candidates}


def _solver_predictor(solvers: dict):
    return lambda lam, train, values, test: solvers[lam].predict(train, values, test)


def select_correction_smoothing(solvers: dict, index, values, folds: int = 5, seed: int = 0) -> float:
    """The surface smoothing (mm, a key of ``solvers``) whose sliding correction through
    ``values : (len(index), 3)`` at the solvers' landmarks ``index`` has the least mean held-out
    error (``folds``-fold, seeded split). Fewer than 10 landmarks: the largest (the smoothest)."""
    return _select(solvers, _solver_predictor(solvers), index, values, folds, seed)


def held_out_sliding(observed, scales, predicted_unit, folds, solvers: dict, *, seed: int = 0) -> list[np.ndarray]:
    """As :func:`held_out_positions`, with the sliding landmark correction: per fold, the
    correction and its surface smoothing (:func:`select_correction_smoothing`, inner folds) come
    from the other folds' landmarks only. ``solvers``: :func:`correction_solvers` over every
    landmark (end-exhale, mm). Returns per target ``(m, 3) float`` mm predicted positions."""
    predict = _solver_predictor(solvers)
    return _held_out(next(iter(solvers.values())).anchors, observed, scales, predicted_unit, folds,
                     lambda train, c: _select(solvers, predict, train, c, 5, seed), predict)


@dataclass(frozen=True, eq=False)
class InteriorField:
    """Displacement per unit ``s`` of any point of a lung, mm (LPS, end-exhale frame).

    Attributes
    ----------
    surface : SlidingField, CorrespondenceField or DisplacementField
        The sliding interpolation of the surface displacement (mm per unit) through the end-exhale
        vertices and their outward normals (all, or a seeded subset of :data:`MAX_SURFACE_POINTS`),
        or a surface-to-surface map (:mod:`lungdeform.interior.correspondence`).
    landmark : SlidingField, DisplacementField or None
        The landmark correction (:func:`correction_per_unit`, mm per unit) through the end-exhale
        landmarks: the sliding correction (kind ``"sliding"``) or a thin-plate spline (older kinds),
        with its smoothing; None without landmarks.
    """

    surface: SlidingField | CorrespondenceField | DisplacementField
    landmark: SlidingField | DisplacementField | None = None

    @property
    def corrected(self) -> bool:
        return self.landmark is not None

    def displacement(self, points) -> np.ndarray:
        """``v : (q, 3) float`` mm per unit at ``points : (q, 3)`` mm LPS (sliding fields: one fused
        kernel sum, :attr:`radial`)."""
        if self.radial is not None:
            return self.radial(points)
        v = self.surface(points)
        return v if self.landmark is None else np.ascontiguousarray(v + self.landmark(points))

    @cached_property
    def radial(self) -> RadialSum | None:
        """Surface field plus correction as one :class:`~lungdeform.interior.sliding.RadialSum` when
        both are sliding fields (they share the surface points); None for the thin-plate kinds."""
        parts = [f for f in (self.surface, self.landmark) if f is not None]
        if not all(isinstance(f, SlidingField) for f in parts):
            return None
        return parts[0].radial if len(parts) == 1 else parts[0].radial + parts[1].radial

    def positions(self, points, scale: float) -> np.ndarray:
        """``q + s·v(q) : (q, 3) float`` mm LPS."""
        q = as_vertices(points, "points")
        return q + float(scale) * self.displacement(q)


def interior_field(vertices, displacement, landmarks=None, correction=None, smoothing: float = 0.0,
                   *, normals, kind: str = "sliding", seed: int = 0,
                   correspondence: CorrespondenceField | None = None) -> InteriorField:
    """An :class:`InteriorField` from a lung's ``vertices : (n, 3)`` mm, their unit outward
    ``normals : (n, 3)`` and ``displacement : (n, 3)`` mm per unit, with an optional landmark
    ``correction : (m, 3)`` mm per unit at ``landmarks : (m, 3)`` mm. ``kind``: one of
    :data:`KINDS`; ``smoothing``: the correction's, in mm (``"sliding"``: the surface smoothing of
    :func:`lungdeform.interior.sliding.sliding_correction`) or mm² (the thin-plate kinds).
    ``correspondence``: the surface part is this map (:mod:`lungdeform.interior.correspondence`)
    instead of the sliding interpolation of ``displacement`` (kind ``"sliding"`` only)."""
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise InputError(f"smoothing must be >= 0, got {smoothing!r}")
    if correspondence is not None and kind != "sliding":
        raise InputError(f"a correspondence field goes with interior kind 'sliding', got {kind!r}")
    if correspondence is not None:
        surface = correspondence
    elif kind in ("sliding", "sliding_thin_plate"):
        surface = sliding_field(vertices, normals, displacement, max_points=MAX_SURFACE_POINTS, seed=seed)
    elif kind == "thin_plate":
        surface = displacement_field(vertices, displacement, max_points=MAX_SURFACE_POINTS, seed=seed)
    else:
        raise InputError(f"interior kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if landmarks is None or correction is None:
        return InteriorField(surface)
    if kind == "sliding":
        return InteriorField(surface, sliding_correction(vertices, normals, landmarks, correction, smoothing=float(smoothing),
                                                         max_points=MAX_SURFACE_POINTS, seed=seed))
    m = len(np.asarray(landmarks))  # every landmark: the correction is never thinned
    return InteriorField(surface, displacement_field(landmarks, correction, smoothing=float(smoothing), max_points=max(m, 1)))
