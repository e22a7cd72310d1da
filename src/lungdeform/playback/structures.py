"""Radiotherapy structures (a GTV, an ITV, an organ) moved through breathing states.

Behind ``lungdeform track --rtstruct FILE --structure NAME`` (docs/RADIOTHERAPY.md): the structure's
contour points are tracked like any points (:mod:`lungdeform.playback.trajectory`), and its closed
surface through the contours (:func:`lungdeform.io.dicom.rtstruct.structure_mesh`) is moved vertex by
vertex by the same interior field at each state, one surface per state, named ``NAME@TAG`` (``GTV@phase03``,
``GTV@3100mL``) for :func:`lungdeform.io.dicom.rtstruct.write_rtstruct`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungdeform.io.dicom.rtstruct import Structure, pick_structure, read_rois, structure_mesh, structure_points

from .dvf import phase_states
from .trajectory import FrameSchedule, place_points, point_trajectories


@dataclass(frozen=True, eq=False)
class TrackedStructure:
    """A structure read for tracking: ``points : (q, 3) float`` mm LPS (its contour points) with
    ``labels`` (``NAME:i``), its closed surface ``vertices : (n, 3) float`` mm, ``faces``, and the
    ROI as read (``roi``: frame of reference, referenced slices)."""

    name: str
    kind: str
    points: np.ndarray
    labels: list
    vertices: np.ndarray
    faces: np.ndarray
    roi: Structure | None = None


def read_structure(path, name: str) -> TrackedStructure:
    """The structure ``name`` of the RTSTRUCT file ``path``, its points and closed surface. Refused
    (:class:`lungdeform.errors.InputError` naming the file and the structure): a name no ROI or two
    ROIs carry, a contour that is not finite, flat or closed, a stack with gaps or beyond the
    bounds of :mod:`lungdeform.geometry.contours`."""
    s = pick_structure(read_rois(path), name, str(path))
    v, f = structure_mesh(s, str(path))  # every contour checked before its points are used
    pts = structure_points(s)
    return TrackedStructure(name, s.kind or "ORGAN", pts, [f"{name}:{i + 1}" for i in range(len(pts))], v, f, s)


def phase_frames(trace, phases: int) -> tuple[FrameSchedule, list[str]]:
    """``phases`` frames evenly over one breathing cycle of ``trace`` (as ``warp --phases``,
    :func:`lungdeform.playback.dvf.phase_states`) and their tags ``phase00`` …"""
    states, period = phase_states(trace, phases)
    t_s = float(trace.t_s[0]) + period * np.arange(len(states)) / len(states)
    delta = np.array([s.delta_ml for s in states])
    source = f"{len(states)} phase(s) over a cycle of {period:.2f} s of {trace.source}"
    return FrameSchedule(delta, t_s, source), [f"phase{i:02d}" for i in range(len(states))]


def volume_tags(volumes_ml) -> list[str]:
    """ROI tags of absolute volumes (mL): ``3100mL`` …"""
    return [f"{v:g}mL" for v in volumes_ml]


def moved_surfaces(model, structure: TrackedStructure, delta_ml, tags: list[str], lung: str | None = None,
                   source: str = "structure") -> list[tuple]:
    """``(NAME@TAG, vertices (n, 3) float mm LPS, faces, kind)`` per state ``delta_ml : (f,)`` mL
    above end-exhale: the structure's surface moved by the model's interior field."""
    placement = place_points(model, structure.vertices, lung, source=source)
    moved = point_trajectories(model, structure.vertices, placement, delta_ml)
    return [(f"{structure.name}@{tag}", moved[i], structure.faces, structure.kind) for i, tag in enumerate(tags)]
