"""Markers (a tumour, fiducials) carried in an exported glb: read, tied to a lung, given their motion.

Markers are read like any points to track (:func:`lungdeform.playback.trajectory.read_markers_csv`: header
``x_mm,y_mm,z_mm[,label]``, one marker per row, positions in mm, LPS of the end-exhale scan).

:func:`marker_anchors` makes the records of the glb's asset extras ``extras.lungdeform.markers``
(schema version 2; the layout is in :mod:`lungdeform.playback.export`): each marker goes to a lung
(:func:`lungdeform.playback.trajectory.place_points`) and gets ``tidal_mm : (3,) float``, its displacement
(mm, LPS) per unit weight of that lung's morph target 0 (``tidal``), from the lung's interior field
(:attr:`lungdeform.model.lung.LungModel.interior`): at weight ``λ`` it is at
``position_mm + λ·tidal_mm``, as ``lungdeform track`` moves it.
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError
from lungdeform.model.displacement import calibration_units, tidal_displacement
from lungdeform.model.lung import Model

from .trajectory import place_points, unit_displacements


def marker_anchors(model: Model, points: np.ndarray, labels=None, *, source: str = "markers") -> list[dict]:
    """Markers (a tumour, fiducials) for the glb extras: each tied to a lung and given its motion
    per unit of that lung's tidal morph weight.

    Parameters
    ----------
    points : (p, 3) float
        Marker positions, mm LPS of the end-exhale scan.
    labels : sequence of str, optional
        One per point (default ``marker 1``, ``marker 2``, …).
    source : str
        Named in errors (the markers file).

    Each marker goes to the lung that contains it, else the nearest
    (:func:`lungdeform.playback.trajectory.place_points`; more than
    :data:`~lungdeform.playback.trajectory.OUTSIDE_LIMIT_MM` outside every lung raises :class:`InputError`).
    Its ``tidal_mm`` is ``w = (calibration_ml/unit_ml) · v(p)`` with ``v`` the lung's interior field
    (:attr:`LungModel.interior`, mm per unit): at the weight ``λ`` of the lung's target 0
    (``tidal``) the marker is at ``p + λ·w``, i.e. ``lung.points_at(p, scale=λ·calibration_ml/unit_ml)``,
    so marker and mesh move with one weight. Returns one dict per marker: ``label``,
    ``position_mm`` (3,), ``lung``, ``inside`` (inside that lung's end-exhale surface),
    ``distance_mm`` (to that surface), ``tidal_mm`` (3,) and ``landmark_corrected`` (whether the
    field includes the model's landmark correction).
    """
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"{source}: marker positions must be (p, 3) mm LPS, got shape {pts.shape}")
    pts = np.ascontiguousarray(pts)
    labels = [f"marker {i + 1}" for i in range(len(pts))] if labels is None else [str(x) for x in labels]
    if len(labels) != len(pts):
        raise InputError(f"{source}: {len(labels)} labels for {len(pts)} markers")
    placement = place_points(model, pts, source=source)
    per_unit = unit_displacements(model, pts, placement)
    units = np.array([calibration_units(model.lungs[str(n)].calibration_ml, model.lungs[str(n)].unit_ml)
                      for n in placement.lungs])
    tidal = tidal_displacement(per_unit, units[:, None])
    out = []
    for j, (label, q) in enumerate(zip(labels, pts)):
        lung = model.lungs[str(placement.lungs[j])]
        out.append({"label": label, "position_mm": q.tolist(), "lung": str(placement.lungs[j]),
                    "inside": bool(placement.inside[j]), "distance_mm": float(placement.distance_mm[j]),
                    "tidal_mm": tidal[j].tolist(), "landmark_corrected": bool(lung.interior.corrected)})
    return out
