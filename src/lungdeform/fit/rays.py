"""Ray correspondence between end-exhale vertices and a larger-volume surface (Sec. IV-B.1; docs/METHOD_NOTES.md §8).

From each end-exhale vertex ``p_i`` a ray is cast along its displacement direction ``d_i`` and
intersected with the target surface; the hit distance ``t_i`` (mm) is the observed displacement
magnitude. The pitfall of docs/METHOD_NOTES.md §8 (rays running almost tangent to the surface or pointing inward
cross the lung and hit the far side) is handled explicitly:

- the search is **bounded** (``max_distance`` mm); no hit within it is a *miss*;
- rays are cast in **both directions** (``+d`` and ``−d``); a valid forward hit is preferred
  (a nearer backward hit is usually the far side of a thin part, not the correspondence), a
  backward hit is used only where no forward one exists and gives a negative ``t`` (the surface
  moved against ``d`` there);
- **grazing** hits, where the ray meets the hit triangle at ``|cos| < min_cosine`` to its normal,
  are rejected (their distance is unstable under small changes of direction);
- every ray gets a status code (:data:`STATUS`) so that callers see why a vertex has no
  observation; nothing is silently filled in.

Ray casting uses Embree (the ``embreex`` binding), single precision, on vertices centred at their
mean to keep float32 precision at world coordinates far from the origin.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from lungdeform.errors import InputError, require
from lungdeform.geometry.mesh import Surface, as_faces, as_vertices, face_normals

#: Status codes of :class:`RayHits`.
STATUS = {0: "forward hit", 1: "backward hit", 2: "miss (no hit within max_distance)",
          3: "grazing hit rejected", 4: "zero direction"}
FORWARD, BACKWARD, MISS, GRAZING, NO_DIRECTION = 0, 1, 2, 3, 4


class RayCaster:
    """An Embree scene over one triangle surface; cast many rays, first hits only.

    Parameters
    ----------
    vertices : (n, 3) float
        mm, any frame (rays in the same frame).
    faces : (m, 3) int
    """

    def __init__(self, vertices, faces):
        rtcore_scene = require("embreex.rtcore_scene", "ray casting", "embreex")
        mesh_construction = require("embreex.mesh_construction", "ray casting", "embreex")
        v = as_vertices(vertices)
        f = as_faces(faces, len(v))
        if len(f) == 0:
            raise InputError("faces: ray casting needs at least one triangle")
        self.center = v.mean(axis=0)
        self.normals = face_normals(v, f)
        self._scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(scene=self._scene, vertices=(v - self.center).astype(np.float32),
                                       indices=f.astype(np.int32))

    def first_hits(self, origins, directions, max_distance: float = np.inf):
        """First hit of each ray ``origins + t·directions``, ``0 ≤ t ≤ max_distance``.

        ``origins, directions : (k, 3) float`` (directions unit length). Returns
        ``(t (k,) float mm, inf for a miss; face (k,) int, -1 for a miss)``.
        """
        o = (as_vertices(origins, "origins") - self.center).astype(np.float32)
        d = as_vertices(directions, "directions").astype(np.float32)
        if o.shape != d.shape:
            raise InputError(f"origins {o.shape} and directions {d.shape} must have the same shape")
        if len(o) == 0:
            return np.zeros(0), np.zeros(0, np.int64)
        tmax = np.full(len(o), min(float(max_distance), 1e30), np.float32)
        out = self._scene.run(o, d, dists=tmax, output=True)
        face = out["primID"].astype(np.int64)
        t = np.where(face >= 0, out["tfar"].astype(np.float64), np.inf)
        return t, face


@dataclass(frozen=True, eq=False)
class RayHits:
    """Correspondences from :func:`correspond`.

    Attributes
    ----------
    distance : (n,) float
        Signed hit distance along ``d_i``, mm (negative: the backward ray hit). NaN where no
        valid hit (see ``status``).
    status : (n,) int8
        :data:`STATUS` code per ray.
    points : (n, 3) float
        Hit points, mm, same frame as the origins; NaN where no valid hit.
    cosine : (n,) float
        ``|cos|`` of the angle between the ray and the hit triangle's normal (NaN for misses).
    max_distance : float
        The search bound used, mm.
    min_cosine : float
        The grazing threshold used.
    """

    distance: np.ndarray
    status: np.ndarray
    points: np.ndarray
    cosine: np.ndarray
    max_distance: float
    min_cosine: float

    @property
    def valid(self) -> np.ndarray:
        """``(n,) bool``: rays with a usable hit (forward or backward)."""
        return self.status <= BACKWARD

    @cached_property
    def counts(self) -> dict[str, int]:
        """Number of rays per status, keyed by the :data:`STATUS` text."""
        return {text: int(np.sum(self.status == code)) for code, text in STATUS.items()}

    def histogram(self, bins: int = 40) -> tuple[np.ndarray, np.ndarray]:
        """``(counts (bins,), edges (bins + 1,) mm)`` of the valid signed hit distances, over
        ``[-max_distance, max_distance]``; look at it before trusting a fit (docs/METHOD_NOTES.md §8)."""
        lim = self.max_distance if np.isfinite(self.max_distance) else max(
            1.0, float(np.nanmax(np.abs(self.distance), initial=1.0)))
        return np.histogram(self.distance[self.valid], bins=bins, range=(-lim, lim))

    def summary(self) -> dict:
        """Counts per status and statistics of the valid distances (mm), for reports."""
        t = self.distance[self.valid]
        out = {"rays": int(len(self.status)), **self.counts}
        if len(t):
            out.update(mean_mm=float(t.mean()), median_mm=float(np.median(t)),
                       mean_abs_mm=float(np.abs(t).mean()), p95_abs_mm=float(np.percentile(np.abs(t), 95)))
        return out


def correspond(
    origins,
    directions,
    target: Surface | RayCaster,
    *,
    max_distance: float = 30.0,
    min_cosine: float = 0.25,
    both_directions: bool = True,
) -> RayHits:
    """Cast rays from ``origins`` along ``directions`` to ``target`` and clean the hits.

    Parameters
    ----------
    origins : (n, 3) float
        End-exhale vertices ``p``, mm (same frame as ``target``).
    directions : (n, 3) float
        Displacement directions ``d`` (normalised here; zero rows get status 4).
    target : Surface or RayCaster
        The larger-volume surface (a prepared :class:`RayCaster` avoids rebuilding the scene).
    max_distance : float
        Bound of the search in each direction, mm.
    min_cosine : float
        Hits with ``|cos(ray, face normal)| < min_cosine`` are rejected as grazing (0 keeps all).
    both_directions : bool
        Also cast along ``−d``, used where the forward ray has no valid hit.
    """
    p = as_vertices(origins, "origins")
    d = as_vertices(directions, "directions")
    if p.shape != d.shape:
        raise InputError(f"origins {p.shape} and directions {d.shape} must have the same shape")
    if not max_distance > 0:
        raise InputError(f"max_distance must be > 0 mm, got {max_distance!r}")
    if not 0.0 <= min_cosine < 1.0:
        raise InputError(f"min_cosine must be in [0, 1), got {min_cosine!r}")
    caster = target if isinstance(target, RayCaster) else RayCaster(target.vertices, target.faces)
    norm = np.linalg.norm(d, axis=1)
    ok = norm > 0
    unit = np.divide(d, norm[:, None], out=np.zeros_like(d), where=ok[:, None])
    n = len(p)
    best_t = np.full(n, np.inf)
    best_face = np.full(n, -1, np.int64)
    sign = np.zeros(n)
    grazing = np.zeros(n, bool)
    for s in ((1.0, -1.0) if both_directions else (1.0,)):
        t, face = caster.first_hits(p[ok], s * unit[ok], max_distance)
        hit = face >= 0
        cos = np.zeros(len(t))
        cos[hit] = np.abs(np.einsum("ij,ij->i", caster.normals[face[hit]], unit[ok][hit]))
        good = hit & (cos >= min_cosine)
        idx = np.nonzero(ok)[0]
        grazing[idx[hit & ~good]] = True
        # a forward hit is preferred; the backward ray only fills in where no forward hit exists
        better = good & ((t < best_t[idx]) if s > 0 else (best_face[idx] < 0))
        j = idx[better]
        best_t[j] = t[better]
        best_face[j] = face[better]
        sign[j] = s
    valid = best_face >= 0
    status = np.full(n, MISS, np.int8)
    status[valid & (sign > 0)] = FORWARD
    status[valid & (sign < 0)] = BACKWARD
    status[~valid & grazing] = GRAZING
    status[~ok] = NO_DIRECTION
    dist = np.full(n, np.nan)
    dist[valid] = sign[valid] * best_t[valid]
    points = np.where(valid[:, None], p + dist[:, None] * unit, np.nan)
    cosine = np.full(n, np.nan)
    cosine[valid] = np.abs(np.einsum("ij,ij->i", caster.normals[best_face[valid]], unit[valid]))
    return RayHits(dist, status, points, cosine, float(max_distance), float(min_cosine))


def rays_per_second(target: Surface, n_rays: int = 1_000_000, seed: int = 0) -> tuple[float, int]:
    """Throughput of :meth:`RayCaster.first_hits` on ``target``: ``(rays/s, n_faces)``.

    Rays start at random vertices of the surface (jittered 1 mm) in random directions, bounded
    by the surface's bounding-box diagonal; the scene is built before timing (warm).
    """

    rng = np.random.default_rng(seed)
    caster = RayCaster(target.vertices, target.faces)
    o = target.vertices[rng.integers(0, target.n_vertices, n_rays)] + rng.normal(size=(n_rays, 3))
    d = rng.normal(size=(n_rays, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    diag = float(np.linalg.norm(np.ptp(target.vertices, axis=0)))
    caster.first_hits(o[:1000], d[:1000], diag)  # warm-up
    t0 = time.perf_counter()
    caster.first_hits(o, d, diag)
    return n_rays / (time.perf_counter() - t0), len(target.faces)
