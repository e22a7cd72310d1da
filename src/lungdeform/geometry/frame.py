"""The per-lung frame of the paper (Sec. IV-B.1; docs/METHOD_NOTES.md §1).

Axes, as unit vectors in LPS (x → patient left, y → posterior, z → head):

- X grows laterally from the heart: +x for the left lung, −x for the right lung;
- Y grows anteriorly from the posterior side: −y;
- Z grows toward the base from the apex: −z.

Origins sit on the end-exhale bounding box: X at its medial face, Y at its posterior face, Z at its
apex. Normalised coordinates ``x̂, ŷ, ẑ ∈ [0, 1]`` use that box (min, max).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from lungdeform.constants import gravity_vector
from lungdeform.errors import InputError

from .distance import vertex_areas
from .mesh import as_vertices

SIDES = ("left", "right")


def frame_axes(side: str) -> np.ndarray:
    """``(3, 3) float``: rows are the lung-frame X, Y, Z axes in LPS for ``side``."""
    if side not in SIDES:
        raise InputError(f"side must be 'left' or 'right', got {side!r}")
    lateral = 1.0 if side == "left" else -1.0
    return np.array([[lateral, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class LungFrame:
    """A lung's frame.

    Attributes
    ----------
    side : 'left' | 'right'
    axes : (3, 3) float
        Rows = lung X, Y, Z unit axes in LPS.
    lower, upper : (3,) float
        End-exhale bounding box in lung-frame mm (``lower`` is the origin).
    """

    side: str
    axes: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def to_frame(self, points: np.ndarray) -> np.ndarray:
        """``(n, 3)`` LPS mm → lung-frame mm (origin at the box's lower corner)."""
        return as_vertices(points, "points") @ self.axes.T - self.lower

    def normalized(self, points: np.ndarray) -> np.ndarray:
        """``(n, 3)`` LPS mm → ``(x̂, ŷ, ẑ)`` in [0, 1] over the end-exhale box (values outside
        the box fall outside [0, 1])."""
        return self.to_frame(points) / (self.upper - self.lower)

    def to_world(self, vectors: np.ndarray) -> np.ndarray:
        """Lung-frame vectors ``(n, 3)`` → LPS vectors."""
        return np.ascontiguousarray(np.asarray(vectors, float) @ self.axes)

    def supported(self, gravity) -> "LungFrame":
        """The frame whose X and Y origins sit on the side the lung rests on under ``gravity``.

        Paper Sec. IV-B.1 puts the Y origin at the posterior side because, supine, the posterior
        part of the lung rests on the table and cannot move forward. By the same reasoning, an
        axis (X or Y) that grows toward the dependent side (``axis · gravity > 0``) is flipped so
        that it grows away from the support: prone flips Y (origin anterior), the lower lung in a
        decubitus position flips X (origin lateral). Z (apex → base) never flips. Supine and
        upright return the anatomical frame unchanged.
        """

        g = gravity_vector(gravity)
        flip = np.array([1.0, 1.0, 1.0])
        for k in (0, 1):
            if self.axes[k] @ g > 1e-9:
                flip[k] = -1.0
        if np.all(flip > 0):
            return self
        lower = np.where(flip > 0, self.lower, -self.upper)
        upper = np.where(flip > 0, self.upper, -self.lower)
        return LungFrame(self.side, self.axes * flip[:, None], lower, upper)


def lung_frame(vertices: np.ndarray, side: str) -> LungFrame:
    """The frame of a lung whose end-exhale vertices are ``(n, 3) float`` mm LPS."""
    axes = frame_axes(side)
    q = as_vertices(vertices) @ axes.T
    lower, upper = q.min(axis=0), q.max(axis=0)
    if np.any(upper - lower <= 0):
        raise InputError("lung surface is flat along a frame axis: cannot normalise coordinates")
    return LungFrame(side, axes, lower, upper)


def guess_sides(centroids_x: list[float]) -> list[str]:
    """Sides for two lungs from their LPS x centroids: the larger x (patient left) is 'left'."""
    if len(centroids_x) != 2:
        raise InputError("sides can be guessed only for exactly two lungs; give each lung's side")
    return ["left", "right"] if centroids_x[0] > centroids_x[1] else ["right", "left"]


#: |score| of :func:`side_from_shape` above which the shape's side is taken as known (measured on
#: thirteen real lungs, left and right: 0.053–0.105; docs/FITTING.md).
SIDE_SCORE_MIN = 0.03


@numba.njit(cache=True, parallel=True)
def _hull_depth(points, planes):  # pragma: no cover - compiled
    """``(n,) float`` mm: how far each of ``points : (n, 3)`` mm lies inside the convex hull whose
    facets are the columns of ``planes : (4, f)`` (Qhull's outward unit normal and offset, rows
    ``n_x, n_y, n_z, d``): ``max(−max_f (n_f · p + d_f), 0)``; no ``(n, f)`` temporary."""
    out = np.empty(points.shape[0])
    nx, ny, nz, off = planes[0], planes[1], planes[2], planes[3]
    for i in numba.prange(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        top = -np.inf
        for f in range(nx.shape[0]):
            top = max(top, nx[f] * x + ny[f] * y + nz[f] * z + off[f])
        out[i] = max(-top, 0.0)
    return out


def side_from_shape(vertices: np.ndarray, faces: np.ndarray, max_points: int = 20000,
                    seed: int = 0) -> tuple[str, float]:
    """Which lung a closed surface is, from its shape: ``(side, score)``.

    The medial face of a lung is concave (the heart and the hilum press into it) and the lateral
    face follows the ribs, so the surface lies deepest below its convex hull medially: toward +x
    (LPS, patient left) for a right lung, −x for a left one. ``score`` is the x offset, from the
    lung's centroid and over its x extent, of the surface's centroid weighted by area × depth below
    the hull (``vertices : (n, 3)`` mm LPS; depths at ``max_points`` seeded vertices at most).
    Trust the side only when ``|score|`` > :data:`SIDE_SCORE_MIN`; measured values are in
    ``docs/FITTING.md``."""


    v = as_vertices(vertices, "vertices")
    area = vertex_areas(v, np.asarray(faces))
    try:
        eq = ConvexHull(v).equations
    except QhullError as exc:
        raise InputError(f"the surface has no convex hull (flat or degenerate: {len(v)} vertices)") from exc
    pick = np.random.default_rng(seed).permutation(len(v))[:max_points]  # a seeded subset bounds the cost
    depth = np.zeros(len(v))
    depth[pick] = _hull_depth(np.ascontiguousarray(v[pick]), np.ascontiguousarray(eq.T))  # mm below the hull
    w = np.zeros(len(v))
    w[pick] = area[pick] * depth[pick]
    width = float(np.ptp(v[:, 0]))
    if w.sum() <= 1e-9 * area.sum() * max(width, 1e-9):  # convex: no medial side to see
        return ("right", 0.0)
    score = float((w @ v[:, 0] / w.sum() - area @ v[:, 0] / area.sum()) / width)
    return ("right" if score > 0 else "left", score)


def clear_side(vertices: np.ndarray, faces: np.ndarray) -> tuple[str | None, float]:
    """:func:`side_from_shape`, with the side ``None`` unless ``|score|`` > :data:`SIDE_SCORE_MIN`."""
    side, score = side_from_shape(vertices, faces)
    return (side if abs(score) > SIDE_SCORE_MIN else None), score


def check_side(vertices: np.ndarray, faces: np.ndarray, side: str, source: str) -> None:
    """Refuse a lung whose shape clearly says the other side than ``side`` (:func:`clear_side`),
    naming ``source``: a wrong ``--side``, or a surface in RAS (x flipped). Unclear shapes pass."""
    shape_side, score = clear_side(vertices, faces)
    if shape_side not in (None, side):
        raise InputError(f"{source}: the lung's shape says {shape_side}, not {side} (its concave medial face lies "
                         f"toward {'+' if score > 0 else '-'}x in LPS, score {score:+.2f}): is the side wrong, or the "
                         "surface in RAS (x flipped)? (--no-side-check skips this check)")


def resolve_sides(surfaces, given: list[str] | None, check: bool = True) -> list[str]:
    """Sides of ``surfaces`` (objects with ``name``, ``vertices : (n, 3)`` mm LPS, ``faces``): ``given``
    (one per surface), else from names ending in -left/-right, from position (two lungs) or from the
    shape (one lung: :func:`lungdeform.geometry.frame.side_from_shape`). Each lung's side is checked
    against its shape (:func:`lungdeform.geometry.frame.check_side`) unless ``check`` is False.

    Given or named sides of a left and a right surface are checked against their positions: in
    LPS the left lung lies at larger x. A pair the other way round (sides or labels swapped, or
    meshes in RAS) is refused rather than built with the wrong sides and the wrong gravity frame.
    """

    by_position = False
    if given:
        if len(given) != len(surfaces):
            raise InputError(f"sides: {len(given)} given for {len(surfaces)} surfaces")
        bad = [s for s in given if s not in SIDES]
        if bad:
            raise InputError(f"sides must be left or right, got {bad[0]!r}")
        sides = list(given)
    else:
        named = [next((sd for sd in SIDES if s.name.lower().endswith(sd)), None) for s in surfaces]
        if all(named):
            sides = named
        elif len(surfaces) == 2:  # from position (so the position check below has nothing to add)
            sides, by_position = guess_sides([float(s.vertices[:, 0].mean()) for s in surfaces]), True
        elif len(surfaces) == 1:  # one lung: its shape (the concave medial face) tells, when it is clear
            shape_side, _ = clear_side(surfaces[0].vertices, surfaces[0].faces)
            if shape_side is None:
                raise InputError(f"cannot tell the side of {surfaces[0].name} (its shape is not clear enough): "
                                 "give its side (left or right)")
            return [shape_side]
        else:
            raise InputError(f"cannot tell the sides of {len(surfaces)} surfaces: give each one's side")
    for sd, s in zip(sides, surfaces) if check else ():  # each lung is the side its shape says, when that is clear
        check_side(s.vertices, s.faces, sd, s.name)
    if sorted(sides) == ["left", "right"] and not by_position:
        x = {sd: float(s.vertices[:, 0].mean()) for sd, s in zip(sides, surfaces)}
        if x["left"] <= x["right"]:
            name = {sd: s.name for sd, s in zip(sides, surfaces)}
            raise InputError(f"the surface taken as left ({name['left']}, mean x {x['left']:.0f} mm) lies to the "
                             f"patient's right of the one taken as right ({name['right']}, {x['right']:.0f} mm); in "
                             "LPS the left lung has the larger x: sides or labels swapped, or the meshes are in RAS")
    return sides
