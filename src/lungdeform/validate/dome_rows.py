"""The rows of ``lungdeform validate single-scan`` that are given one measured number: the dome excursion.

Per lung, the dome excursion ``E`` (mm, relative to the apex) is measured from the two masks
(:func:`lungdeform.geometry.dome.dome_excursion`: the smaller-volume model mesh and the larger-volume surface,
their crop faces marked), as a clinician would measure it on the patient; both rows then predict the larger
volume from the smaller scan, that volume and ``E``:

- ``dome``: :func:`lungdeform.model.lung.build_lung` with the lung's default and ``dome_mm = E`` at the volume
  change (:mod:`lungdeform.model.dome`: the default's pattern and a head–foot stretch, split so that the dome
  descends ``E``);
- ``dome_scaling``: the fair baseline given the same number: scaling about the solid's centroid, by
  ``s_z = 1 + E/L`` head–foot (``L`` the apex-to-dome height of the smaller scan, so that the scaled lung's
  dome descends exactly ``E``) and ``s_x = s_y = √(V₁ / (V₀·s_z))`` across (the other two axes take the
  remaining volume equally).

A lung whose apex or dome the scan cut off (:func:`~lungdeform.geometry.dome.dome_weights` refuses it) gets
neither row; one whose dome rose (``E < 0``, not modelled), whose ``E`` the volume cannot produce, or whose
split does not converge gets no ``dome`` row (a "–" in the tables). Each row records the ``dome_mm`` it was
given.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.dome import dome_excursion, dome_weights
from lungdeform.geometry.mesh import Surface
from lungdeform.geometry.moments import solid_moments
from lungdeform.model.lung import BuildSettings, build_lung
from lungdeform.model.population import PopulationDefault

#: The rows this module adds, in report order.
ROWS = ("dome", "dome_scaling")


def measured_excursion(rest: Surface, keep, target) -> float | None:
    """``E`` mm from the smaller-volume ``rest`` (``keep (n,) bool``: its vertices off the crop faces) to the
    larger-volume ``target`` (a :class:`lungdeform.fit.objective.Target`); None when the scans cut off the apex
    or the dome."""
    try:
        return dome_excursion(rest, target.surface, keep_smaller=keep, keep_larger=target.keep)
    except InputError:
        return None


def dome_scaling(rest: Surface, volume_ml: float, excursion_mm: float, points) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (n, 3), points (m, 3))`` mm LPS of ``rest`` and ``points`` scaled as the ``dome_scaling`` row
    (module docstring) to ``volume_ml`` with the dome ``excursion_mm`` lower."""
    length = dome_weights(rest.vertices, rest.faces, name=rest.name).height_mm
    sz = 1.0 + excursion_mm / length
    sxy = np.sqrt(volume_ml / rest.volume_ml / sz)
    _, mu, _ = solid_moments(rest.vertices, rest.faces)
    s = np.array([sxy, sxy, sz])
    return mu + (rest.vertices - mu) * s, mu + (np.asarray(points, float) - mu) * s


def dome_predictions(pair, default: PopulationDefault) -> dict:
    """``{row: (vertices, landmarks)}`` of :data:`ROWS` for a :class:`lungdeform.validate.single_scan.LungPair`
    with ``default`` (empty when ``E`` cannot be measured; without ``dome`` when the volume cannot produce it)."""
    e = measured_excursion(pair.rest, pair.keep, pair.target)
    if e is None:
        return {}
    out = {}
    delta = pair.volume_ml - pair.rest.volume_ml
    try:
        lung = build_lung(pair.rest, pair.side, default=default, settings=BuildSettings(calibration_ml=delta, dome_mm=e))
        out["dome"] = (lung.surface_at(pair.volume_ml, exact=True).vertices,
                       lung.points_at(pair.landmarks_rest, pair.volume_ml, exact=True))
    except LungdeformError:  # refused (InputError) or not converged: no dome row for this lung ("–" in the table)
        pass
    out["dome_scaling"] = dome_scaling(pair.rest, pair.volume_ml, e, pair.landmarks_rest)
    return out


def scored_rows(pair, default: PopulationDefault, score: Callable) -> dict:
    """``{row: figures}``: :func:`dome_predictions` scored by ``score(pair, vertices, landmarks)`` (the
    experiment's scoring), each with the ``dome_mm`` it was given."""
    e = measured_excursion(pair.rest, pair.keep, pair.target)
    return {row: {**score(pair, *pred), "dome_mm": e} for row, pred in dome_predictions(pair, default).items()}
