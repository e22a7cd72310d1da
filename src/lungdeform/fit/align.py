"""Rigid alignment between scans of the same lung (table shift, patient motion) and crop faces.

Two scans of one subject differ by a rigid motion (the ITK pair: a table shift of about 40 mm in
z) besides breathing. It must be removed before deformation is judged, and it is reported.

Readings chosen:

- :func:`align_apex` anchors on the **apex cap** (the top ``cap_mm`` of the lung along the head
  axis), which moves least in breathing: iterative closest point from the larger-volume cap to
  the smaller-volume surface, translation only by default (a cap alone fixes rotation poorly;
  ``rigid=True`` also fits a rotation). It uses no landmark, so landmark errors measured after it
  are fair.
- :func:`align_landmarks` is the least-squares rigid fit (Kabsch) of corresponding landmarks. It
  absorbs part of the breathing motion into the rigid part, so landmark errors after it are
  optimistic; it is offered for comparison only.

The transform maps the **moving** (larger-volume) scan into the frame of the **fixed**
(end-exhale) scan: ``x_fixed = R @ x_moving + t`` (mm, LPS).

Crop faces: a mask that touches the border of its image (the ITK masks touch the medial face)
gives a flat artificial surface there. :func:`crop_planes` finds those planes from the image and
:func:`near_planes` marks vertices within a margin of them, so that metrics can leave them out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.distance import SurfaceDistance
from lungdeform.geometry.mesh import Surface, as_vertices


@dataclass(frozen=True)
class RigidTransform:
    """``x' = rotation @ x + translation`` (mm).

    Attributes
    ----------
    rotation : (3, 3) float
        Proper rotation (det +1).
    translation : (3,) float
        mm.
    """

    rotation: np.ndarray
    translation: np.ndarray

    @staticmethod
    def identity() -> "RigidTransform":
        return RigidTransform(np.eye(3), np.zeros(3))

    def apply(self, points) -> np.ndarray:
        """``(n, 3)`` mm → ``(n, 3)`` mm."""
        return np.ascontiguousarray(as_vertices(points, "points") @ self.rotation.T + self.translation)

    def apply_surface(self, surface: Surface) -> Surface:
        return Surface(self.apply(surface.vertices), surface.faces, surface.name)

    def inverse(self) -> "RigidTransform":
        r = self.rotation.T
        return RigidTransform(r, -r @ self.translation)

    def compose(self, other: "RigidTransform") -> "RigidTransform":
        """``self ∘ other`` (apply ``other`` first)."""
        return RigidTransform(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    @property
    def matrix(self) -> np.ndarray:
        """4×4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    @property
    def angle_deg(self) -> float:
        """Rotation angle, degrees."""
        return float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1.0) / 2.0, -1.0, 1.0))))

    def as_dict(self) -> dict:
        return {"translation_mm": [float(x) for x in self.translation],
                "rotation_deg": self.angle_deg,
                "matrix": [[float(x) for x in row] for row in self.matrix]}


@dataclass(frozen=True)
class Alignment:
    """Result of an alignment.

    Attributes
    ----------
    transform : RigidTransform
        moving → fixed.
    method : str
    residual_rms_mm : float
        RMS distance of the anchor points after alignment, mm.
    n_anchor : int
        Number of anchor points used.
    iterations : int
    details : dict
    """

    transform: RigidTransform
    method: str
    residual_rms_mm: float
    n_anchor: int
    iterations: int = 0
    details: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"method": self.method, **self.transform.as_dict(),
                "anchor_rms_mm": self.residual_rms_mm, "anchor_points": self.n_anchor,
                "iterations": self.iterations, **self.details}


def kabsch(source, target, weights=None) -> RigidTransform:
    """Least-squares rigid transform taking ``source : (n, 3)`` onto ``target : (n, 3)`` (mm)."""
    a = as_vertices(source, "source")
    b = as_vertices(target, "target")
    if a.shape != b.shape or len(a) < 3:
        raise InputError(f"source {a.shape} and target {b.shape} must match, with at least 3 points")
    w = np.ones(len(a)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    h = (a - ca).T @ ((b - cb) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    s = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T)) or 1.0])
    r = vt.T @ s @ u.T
    return RigidTransform(r, cb - r @ ca)


def apex_cap(vertices, cap_mm: float = 30.0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``(n,) bool``: vertices within ``cap_mm`` of the highest point along ``up`` (LPS head = +z)."""
    v = as_vertices(vertices)
    h = v @ (np.asarray(up, float) / np.linalg.norm(up))
    return h >= h.max() - float(cap_mm)


def anchor_mask(vertices, cap_mm: float = 15.0, posterior_mm: float | None = 10.0) -> np.ndarray:
    """``(n,) bool``: the anchor region of a lung surface (mm LPS): the apex cap (top ``cap_mm``
    along +z) and, unless ``posterior_mm`` is None, the posterior band (the last ``posterior_mm``
    along +y, the wall that rests on the table in a supine scan)."""
    v = as_vertices(vertices)
    m = apex_cap(v, cap_mm)
    if posterior_mm is not None:
        m |= apex_cap(v, posterior_mm, up=(0.0, 1.0, 0.0))
    return m


@dataclass(frozen=True)
class ApexSettings:
    """How :func:`align_apex` aligns: anchors are the apex cap of ``cap_mm`` and, unless
    ``posterior_mm`` is None, the posterior band of that depth (mm); translation only unless
    ``rigid``; ICP stops after ``max_iterations`` or when a step moves less than ``tol_mm``."""

    cap_mm: float = 15.0
    posterior_mm: float | None = 10.0
    rigid: bool = False
    max_iterations: int = 100
    tol_mm: float = 1e-4


def align_apex(fixed: Surface, moving: Surface, *, settings: ApexSettings = ApexSettings(),
               exclude_moving=None, exclude_fixed=None) -> Alignment:
    """Align ``moving`` onto ``fixed`` on the regions that breathing moves least (ICP).

    Anchors (:func:`anchor_mask`): the apex cap and, by default, the posterior band of both
    surfaces; the moving anchor points are matched to the fixed *anchor* surface region (closest
    point on the fixed surface, restricted to points whose closest fixed vertex is an anchor).
    Translation only unless ``settings.rigid``. ``exclude_moving`` / ``exclude_fixed : (n,) bool``
    leave vertices out (e.g. a crop face). Starts from the translation that matches the apex heights
    and the posterior walls. Raises :class:`InputError` when fewer than 10 anchor vertices remain.
    """
    cap_mm, posterior_mm, rigid = settings.cap_mm, settings.posterior_mm, settings.rigid
    max_iterations, tol_mm = settings.max_iterations, settings.tol_mm
    if not cap_mm > 0:
        raise InputError(f"cap_mm must be > 0 mm, got {cap_mm!r}")
    am = anchor_mask(moving.vertices, cap_mm, posterior_mm)
    af = anchor_mask(fixed.vertices, cap_mm, posterior_mm)
    if exclude_moving is not None:
        am &= ~np.asarray(exclude_moving, bool)
    if exclude_fixed is not None:
        af &= ~np.asarray(exclude_fixed, bool)
    pts = moving.vertices[am]
    if len(pts) < 10 or af.sum() < 10:
        raise InputError(f"{moving.name}: only {len(pts)} anchor vertices (apex cap {cap_mm} mm)")
    top = fixed.vertices[:, 2].max() - moving.vertices[:, 2].max()
    back = fixed.vertices[:, 1].max() - moving.vertices[:, 1].max() if posterior_mm is not None else 0.0
    cap_f = fixed.vertices[apex_cap(fixed.vertices, cap_mm)].mean(0)
    cap_m = moving.vertices[apex_cap(moving.vertices, cap_mm)].mean(0)
    xf = RigidTransform(np.eye(3), np.array([cap_f[0] - cap_m[0], back, top]))
    # restrict the target to the fixed anchor faces (all corners anchors)
    faces = fixed.faces[af[fixed.faces].all(axis=1)]
    sd = SurfaceDistance(fixed.vertices, faces)
    it = 0
    for it in range(1, max_iterations + 1):
        cur = xf.apply(pts)
        _, closest, _ = sd.query(cur)
        step = kabsch(cur, closest) if rigid else RigidTransform(np.eye(3), (closest - cur).mean(axis=0))
        xf = step.compose(xf)
        if np.linalg.norm(step.translation) < tol_mm and step.angle_deg < 1e-5:
            break
    resid = sd.distance(xf.apply(pts))
    method = ("apex-posterior" if posterior_mm is not None else "apex") + ("-rigid" if rigid else "")
    return Alignment(xf, method, float(np.sqrt(np.mean(resid**2))), len(pts), it,
                     {"cap_mm": float(cap_mm), "posterior_mm": posterior_mm})


def align_landmarks(fixed_points, moving_points) -> Alignment:
    """Rigid least-squares fit of corresponding landmarks, moving → fixed (Kabsch)."""
    f = as_vertices(fixed_points, "fixed landmarks")
    m = as_vertices(moving_points, "moving landmarks")
    if f.shape != m.shape:
        raise InputError(f"fixed landmarks {f.shape} and moving landmarks {m.shape} must correspond row by row")
    xf = kabsch(m, f)
    resid = np.linalg.norm(xf.apply(m) - f, axis=1)
    return Alignment(xf, "landmarks", float(np.sqrt(np.mean(resid**2))), len(f))


# --------------------------------------------------------------------------- crop faces
@dataclass(frozen=True)
class CropPlane:
    """A border face of an image that the mask touches: ``normal · x = offset`` (mm, LPS).

    ``normal`` points out of the image; ``voxels`` is how many mask voxels touch that face.
    """

    normal: np.ndarray
    offset: float
    voxels: int
    label: str

    def transformed(self, xf: RigidTransform) -> "CropPlane":
        n = xf.rotation @ self.normal
        point = xf.apply((self.normal * self.offset)[None])[0]
        return CropPlane(n, float(n @ point), self.voxels, self.label)


def crop_planes(image, min_voxels: int = 1) -> list[CropPlane]:
    """Border faces of ``image`` (a :class:`lungdeform.io.grid.Image`) that its foreground touches.

    The surface of a padded mask sits half a voxel outside the last voxel, so the plane is at
    index ``-0.5`` or ``size - 0.5`` along the axis.
    """
    a = np.asarray(image.array) != 0
    sizes = a.shape[::-1]  # (i, j, k) = (x, y, z)
    planes = []
    names = "ijk"
    for axis in range(3):
        np_axis = 2 - axis
        for side, idx in (("low", 0), ("high", sizes[axis] - 1)):
            count = int(np.take(a, idx, axis=np_axis).sum())
            if count < min_voxels:
                continue
            normal = image.direction[:, axis] * (1.0 if side == "high" else -1.0)
            ijk = np.zeros(3)
            ijk[axis] = idx + (0.5 if side == "high" else -0.5)
            point = image.index_to_world(ijk[None])[0]
            planes.append(CropPlane(normal, float(normal @ point), count, f"{names[axis]}-{side}"))
    return planes


def near_planes(vertices, planes: list[CropPlane], margin_mm: float = 5.0) -> np.ndarray:
    """``(n,) bool``: vertices within ``margin_mm`` inside any of ``planes``."""
    v = as_vertices(vertices)
    out = np.zeros(len(v), bool)
    for p in planes:
        out |= (v @ p.normal) >= p.offset - margin_mm
    return out
