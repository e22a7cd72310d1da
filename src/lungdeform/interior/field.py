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

from .interpolate import DisplacementField, displacement_field, interpolation_weights
from .sliding import MAX_POINTS, RadialSum, SlidingField, sliding_correction, sliding_field
from .surface_map import SurfaceMapField

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


@dataclass(frozen=True, eq=False)
class InteriorField:
    """Displacement per unit ``s`` of any point of a lung, mm (LPS, end-exhale frame).

    Attributes
    ----------
    surface : SlidingField, SurfaceMapField or DisplacementField
        The sliding interpolation of the surface displacement (mm per unit) through the end-exhale
        vertices and their outward normals (all, or a seeded subset of :data:`MAX_SURFACE_POINTS`),
        or a surface-to-surface map (:mod:`lungdeform.interior.surface_map`).
    landmark : SlidingField, DisplacementField or None
        The landmark correction (:func:`correction_per_unit`, mm per unit) through the end-exhale
        landmarks: the sliding correction (kind ``"sliding"``) or a thin-plate spline (older kinds),
        with its smoothing; None without landmarks.
    """

    surface: SlidingField | SurfaceMapField | DisplacementField
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

    def along_rows(self, starts, step, counts) -> np.ndarray:
        """:meth:`displacement` at the points of straight rows, ``(Σ counts, 3) float`` mm per unit, row
        ``r`` the points ``starts[r] + a·step`` (``a = 0 … counts[r] − 1``; ``starts : (r, 3)`` mm LPS,
        ``step`` (3,) mm), row after row: a surface map alone by its row kernel
        (:meth:`~lungdeform.interior.surface_map.SurfaceMapField.along_rows`), any other field point by point."""
        if isinstance(self.surface, SurfaceMapField) and self.landmark is None:
            return self.surface.along_rows(starts, step, counts)
        s0, n = as_vertices(starts, "starts"), np.asarray(counts, dtype=np.int64).reshape(-1)
        a = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        return self.displacement(np.repeat(s0, n, axis=0) + a[:, None] * np.asarray(step, float).reshape(3))

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


@dataclass(frozen=True, eq=False)
class LandmarkCorrection:
    """The landmark correction of an interior field: ``correction : (m, 3)`` mm per unit at
    ``landmarks : (m, 3)`` mm (either None: no correction); ``smoothing``: the correction's, in mm
    (kind ``"sliding"``: the surface smoothing of
    :func:`lungdeform.interior.sliding.sliding_correction`) or mm² (the thin-plate kinds)."""

    landmarks: np.ndarray | None = None
    correction: np.ndarray | None = None
    smoothing: float = 0.0


def interior_field(vertices, displacement, correction: LandmarkCorrection = LandmarkCorrection(), *, normals,
                   kind: str = "sliding", seed: int = 0,
                   correspondence: SurfaceMapField | None = None) -> InteriorField:
    """An :class:`InteriorField` from a lung's ``vertices : (n, 3)`` mm, their unit outward
    ``normals : (n, 3)`` and ``displacement : (n, 3)`` mm per unit, with an optional landmark
    ``correction`` (:class:`LandmarkCorrection`). ``kind``: one of :data:`KINDS`.
    ``correspondence``: the surface part is this map (:mod:`lungdeform.interior.surface_map`)
    instead of the sliding interpolation of ``displacement`` (kind ``"sliding"`` only)."""
    landmarks, smoothing = correction.landmarks, correction.smoothing
    correction = correction.correction
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
