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
split does not converge gets no ``dome`` row (a "–" in the tables). A lung without landmarks is scored on
its surface. Each row records the ``dome_mm`` it was given.
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import LungdeformError
from lungdeform.geometry.dome import dome_weights
from lungdeform.geometry.mesh import Surface
from lungdeform.geometry.moments import solid_moments
from lungdeform.model.lung import BuildSettings, build_lung

from .lung_pair import measured_excursion

__all__ = ["ROWS", "dome_row", "dome_scaling", "dome_scaling_row", "measured_excursion"]

#: The rows this module adds, in report order.
ROWS = ("dome", "dome_scaling")


def dome_scaling(rest: Surface, volume_ml: float, excursion_mm: float, points) -> tuple[np.ndarray, np.ndarray | None]:
    """``(vertices (n, 3), points (m, 3) or None)`` mm LPS of ``rest`` and ``points`` (or None) scaled as the ``dome_scaling`` row
    (module docstring) to ``volume_ml`` with the dome ``excursion_mm`` lower."""
    length = dome_weights(rest.vertices, rest.faces, name=rest.name).height_mm
    sz = 1.0 + excursion_mm / length
    sxy = np.sqrt(volume_ml / rest.volume_ml / sz)
    _, mu, _ = solid_moments(rest.vertices, rest.faces)
    s = np.array([sxy, sxy, sz])
    return mu + (rest.vertices - mu) * s, None if points is None else mu + (np.asarray(points, float) - mu) * s


def dome_row(pair, training):
    """The ``dome`` row, a :data:`lungdeform.validate.single_scan.Predictor`: the lung's default
    (``training.default``) split so that its dome descends the excursion measured from the two masks; None
    when that cannot be measured, when the volume cannot produce it or when the split does not converge."""
    e = pair.dome_mm
    if e is None:
        return None
    delta = pair.volume_ml - pair.rest.volume_ml
    try:
        lung = build_lung(pair.rest, pair.side, default=training.default,
                          settings=BuildSettings(calibration_ml=delta, dome_mm=e))
    except LungdeformError:  # refused (InputError) or not converged: no dome row for this lung ("–" in the table)
        return None
    points = pair.landmarks_rest
    return (lung.surface_at(pair.volume_ml, exact=True).vertices,
            None if points is None else lung.points_at(points, pair.volume_ml, exact=True), {"dome_mm": e})


def dome_scaling_row(pair, training):
    """The ``dome_scaling`` row, a :data:`lungdeform.validate.single_scan.Predictor`: :func:`dome_scaling` by
    the excursion measured from the two masks; None when that cannot be measured."""
    e = pair.dome_mm
    return None if e is None else (*dome_scaling(pair.rest, pair.volume_ml, e, pair.landmarks_rest), {"dome_mm": e})
