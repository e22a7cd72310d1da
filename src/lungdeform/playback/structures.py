"""Radiotherapy structures (a GTV, an ITV, an organ) moved through breathing states.

Behind ``lungdeform track --rtstruct FILE --structure NAME`` (docs/RADIOTHERAPY.md): the structure's
contour points are tracked like any points (:mod:`lungdeform.playback.trajectory`), and its closed
surface through the contours (:func:`lungdeform.io.dicom.rtstruct.structure_mesh`) is moved vertex by
vertex by the same interior field at each state, one surface per state, named ``NAME@TAG`` (``GTV@phase03``,
``GTV@3100mL``) for :func:`lungdeform.io.dicom.rtstruct.write_rtstruct`; their union over the states, the
ITV (:func:`itv_surface`), and the per-state volume and centroid motion (:func:`motion_table`).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from lungdeform.geometry.moments import solid_moments
from lungdeform.io.dicom.rtstruct import (
    Structure,
    enclosing_contours,
    pick_structure,
    read_rois,
    structure_mesh,
    structure_points,
)
from lungdeform.io.grid import Image
from lungdeform.io.mask import mask_to_surface

from .displacement_field import Grid, check_phases
from .phases import phase_schedule
from .rigid import RigidRegion, surface_mask
from .trajectory import FrameSchedule, place_points, point_trajectories

#: Voxel size (mm) of the grid the ITV's union is filled on.
ITV_VOXEL_MM = 0.5


@dataclass(frozen=True, eq=False)
class TrackedStructure:
    """A structure read for tracking: ``points : (q, 3) float`` mm LPS (its contour points) with
    ``labels`` (``NAME:i``), its closed surface ``vertices : (n, 3) float`` mm, ``faces``, and the
    ROI as read (``roi``: frame of reference, referenced slices); ``skipped``: one line per contour
    left out because it encloses no area (:func:`lungdeform.io.dicom.rtstruct.enclosing_contours`)."""

    name: str
    kind: str
    points: np.ndarray
    labels: list
    vertices: np.ndarray
    faces: np.ndarray
    roi: Structure | None = None
    skipped: tuple = ()


def read_structure(path, name: str) -> TrackedStructure:
    """The structure ``name`` of the RTSTRUCT file ``path``, its points and closed surface; contours
    that enclose no area (tips of 1 or 2 points, a repeated point, a line) are left out, one line
    each in ``skipped``. Refused (:class:`lungdeform.errors.InputError` naming the file and the
    structure): a name no ROI or two ROIs carry, no contour enclosing an area, a contour that is not
    finite, flat or closed, a stack with gaps or beyond the bounds of :mod:`lungdeform.geometry.contours`."""
    s, skipped = enclosing_contours(pick_structure(read_rois(path), name, str(path)), str(path))
    v, f = structure_mesh(s, str(path))  # every contour checked before its points are used
    pts = structure_points(s)
    return TrackedStructure(name, s.kind, pts, [f"{name}:{i + 1}" for i in range(len(pts))], v, f, s, tuple(skipped))


def phase_frames(trace, phases: int, zero: str = "end-inhale") -> tuple[FrameSchedule, list[str]]:
    """``phases`` frames evenly over one breathing cycle of ``trace`` from phase 0 at ``zero`` (as
    ``warp --phases``, :func:`lungdeform.playback.phases.phase_schedule`) and their tags ``phase00`` …"""
    check_phases(phases)
    sched = phase_schedule(trace, phases, zero)
    source = f"{sched.count} phase(s) over a cycle of {sched.period_s:.2f} s of {trace.source} (phase 0 at {zero})"
    return FrameSchedule(sched.delta_ml, sched.t_s, source), [f"phase{i:02d}" for i in range(sched.count)]


def volume_tags(volumes_ml) -> list[str]:
    """ROI tags of absolute volumes (mL): ``3100mL`` …"""
    return [f"{v:g}mL" for v in volumes_ml]


def moved_surfaces(model, structure: TrackedStructure, delta_ml, tags: list[str], lung: str | None = None,
                   source: str = "structure", rigid: RigidRegion | None = None) -> list[tuple]:
    """``(NAME@TAG, vertices (n, 3) float mm LPS, faces, kind)`` per state ``delta_ml : (f,)`` mL
    above end-exhale: the structure's surface moved by the model's interior field (made rigid over
    ``rigid``, :func:`moved_points`)."""
    placement = place_points(model, structure.vertices, lung, source=source)
    moved = moved_points(model, structure.vertices, placement, delta_ml, rigid)
    return [(f"{structure.name}@{tag}", moved[i], structure.faces, structure.kind) for i, tag in enumerate(tags)]


def rigid_structure(model, path, name: str, border_mm: float, tracked: TrackedStructure | None = None) -> RigidRegion:
    """The structure ``name`` of the RTSTRUCT ``path`` (``tracked`` when it is the one already read) as a
    :class:`~lungdeform.playback.rigid.RigidRegion` blended over ``border_mm``, its samples placed in
    ``model``'s lungs."""
    s = tracked if tracked is not None else read_structure(path, name)
    region = RigidRegion(name, s.vertices, s.faces, float(border_mm))
    return replace(region, placement=place_points(model, region.samples, source=f"{path} rigid structure {name}"))


def moved_points(model, points, placement, delta_ml, rigid: RigidRegion | None = None) -> np.ndarray:
    """``(f, q, 3)`` mm LPS: ``points (q, 3)`` at ``delta_ml : (f,)`` mL above end-exhale by the
    model's interior field (:func:`~lungdeform.playback.trajectory.point_trajectories`), and with
    ``rigid`` that structure's best rigid motion under the same field blended in
    (:class:`~lungdeform.playback.rigid.RigidRegion`): ``track --rigid-structure`` as ``warp
    --rigid-structure``."""
    elastic = point_trajectories(model, points, placement, delta_ml)
    if rigid is None:
        return elastic
    inner = rigid.placement
    if inner is None:
        inner = place_points(model, rigid.samples, source=f"rigid structure {rigid.name}")
    motions = rigid.motions(point_trajectories(model, rigid.samples, inner, delta_ml))
    return rigid.applied(points, elastic, motions)


def itv_surface(surfaces: list[tuple], name: str, voxel_mm: float = ITV_VOXEL_MM) -> tuple:
    """``(ITV_NAME, vertices (n, 3) float mm LPS, faces, "")``: the internal target volume, the union
    of the regions ``surfaces`` (``(name, vertices, faces, kind)`` per state, :func:`moved_surfaces`)
    enclose. Each region is filled on a common grid of ``voxel_mm`` voxels (voxel centres inside the
    surface), the union grown by one voxel so that it holds every state's surface (the mesh through
    the voxels' faces lies half a voxel in, its smoothing a little more), and meshed
    (:func:`lungdeform.io.mask.mask_to_surface`). Its RT ROI Interpreted Type is empty: DICOM
    (PS3.3 C.8.8.8) has no defined term for an ITV, and a defined one (GTV, CTV) would say what it
    is not; its name says ITV."""
    pts = np.concatenate([np.asarray(s[1], float) for s in surfaces])
    lo = pts.min(axis=0) - 4 * voxel_mm
    shape = tuple(int(n) for n in (np.ceil((pts.max(axis=0) + 4 * voxel_mm - lo) / voxel_mm) + 1)[::-1])
    grid = Grid(shape, np.full(3, float(voxel_mm)), lo, np.eye(3))
    union = np.zeros(shape, bool)
    for s in surfaces:
        union |= surface_mask(s[1], s[2], grid)
    union = ndimage.binary_dilation(union, structure=np.ones((3, 3, 3), bool))
    surface = mask_to_surface(Image(union.astype(np.uint8), grid.spacing, grid.origin, grid.direction, f"ITV of {name}"))
    return (f"ITV_{name}", surface.vertices, surface.faces, "")


def motion_table(surfaces: list[tuple]) -> list[dict]:
    """Per state of a structure (``surfaces`` as :func:`moved_surfaces`, state 0 first): ``state`` (the
    tag after ``@``), ``volume_ml``, ``centroid_mm`` (3,) LPS (of the solid,
    :func:`lungdeform.geometry.moments.solid_moments`), ``displacement_mm`` (3,) from state 0 and its
    length ``distance_mm``, and the structure's ``amplitude_mm`` (3,): max − min of the centroid over
    the states along x, y, z (LR, AP, SI)."""
    moments = [solid_moments(s[1], s[2]) for s in surfaces]
    centroids = np.array([c for _v, c, _cov in moments])
    amplitude = centroids.max(axis=0) - centroids.min(axis=0)
    rows = []
    for s, (vol, c, _cov) in zip(surfaces, moments):
        d = c - centroids[0]
        rows.append({"state": s[0].split("@", 1)[-1], "volume_ml": vol / 1000.0, "centroid_mm": c,
                     "displacement_mm": d, "distance_mm": float(np.linalg.norm(d)), "amplitude_mm": amplitude})
    return rows


def motion_csv(tables: dict[str, list[dict]]) -> bytes:
    """``structure_motion.csv``: one row per structure and state (:func:`motion_table`), mm LPS, mL."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["structure", "state", "volume_ml", "centroid_x_mm", "centroid_y_mm", "centroid_z_mm", "dx_mm",
                "dy_mm", "dz_mm", "distance_mm", "amplitude_x_mm", "amplitude_y_mm", "amplitude_z_mm"])
    for name, rows in tables.items():
        for r in rows:
            w.writerow([name, r["state"], f"{r['volume_ml']:.4f}", *(f"{x:.3f}" for x in r["centroid_mm"]),
                        *(f"{x:.3f}" for x in r["displacement_mm"]), f"{r['distance_mm']:.3f}",
                        *(f"{x:.3f}" for x in r["amplitude_mm"])])
    return buf.getvalue().encode()
