"""The painter's rasterizer (lungdeform.plot.raster), checked against areas known analytically, the
per-sample containment rule evaluated densely, and pictures whose colours are known."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.plot.raster import SNAP, _fill, paint


def _area(tri: np.ndarray) -> float:
    (ax, ay), (bx, by), (cx, cy) = tri
    return 0.5 * abs((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))


def _perimeter(tri: np.ndarray) -> float:
    return float(np.linalg.norm(tri - np.roll(tri, 1, axis=0), axis=1).sum())


def test_a_triangles_covered_fraction_is_its_area(rng):
    # truth: the area of a triangle, ½|cross|. A sample cell (side d = mm per pixel / supersample)
    # that the boundary does not cross is counted exactly; one it crosses is off by at most d², and a
    # closed polygon of perimeter L crosses at most √2 L / d + 2 per edge of them: so the alpha
    # summed over the image, times the pixel area, is the area within √2 L d + 6 d²
    mm_per_pixel, supersample = 0.7, 3
    d = mm_per_pixel / supersample
    errors = []
    for _ in range(40):
        tri = rng.uniform(1.0, 39.0, (3, 2))
        image = paint(tri[None], [[0.2, 0.4, 0.6]], np.array([0.0, 40.0]), mm_per_pixel, (58, 58), supersample)
        covered = image[..., 3].sum() * mm_per_pixel ** 2
        bound = np.sqrt(2.0) * _perimeter(tri) * d + 6.0 * d * d
        assert covered == pytest.approx(_area(tri), abs=bound)
        errors.append(abs(covered - _area(tri)) / (_perimeter(tri) * d))
    # and the errors along the edges cancel on average: far inside the worst case (a sampler that
    # dropped or doubled a row of samples would be off by about ½ L d)
    assert np.mean(errors) < 0.1


def test_more_samples_shrink_the_error_with_the_sample_spacing(rng):
    # truth: the analytic areas again; the box filter's error scales with the sample spacing d, so
    # nine samples a side (d / 9) are, at worst over many triangles, several times nearer than one
    tris = rng.uniform(1.0, 39.0, (40, 3, 2))
    def worst(supersample):
        return max(abs(paint(t[None], [[1.0, 1.0, 1.0]], np.array([0.0, 40.0]), 1.0, (40, 40),
                             supersample)[..., 3].sum() - _area(t)) for t in tris)
    assert worst(9) < worst(1) / 3.0


def test_faces_sharing_edges_leave_no_seam_and_no_overlap(rng):
    # truth: a 12 × 12 mm square cut into a fan of triangles around a random inner point, aligned to
    # the pixel grid: every pixel inside it is covered exactly once (alpha 1; a seam would show as
    # alpha < 1), none outside (alpha 0); the colour of a pixel is the mean of its faces' colours, so
    # with one colour for all it is that colour exactly
    centre = rng.uniform(2.0, 10.0, 2)
    corners = np.array([[0.0, 0.0], [5.3, 0.0], [12.0, 0.0], [12.0, 7.7], [12.0, 12.0], [0.0, 12.0], [0.0, 4.1]])
    fan = np.array([[centre, corners[k], corners[(k + 1) % len(corners)]] for k in range(len(corners))])
    image = paint(fan, np.tile([0.3, 0.5, 0.7], (len(fan), 1)), np.array([-2.0, 14.0]), 0.5, (32, 32), 3)
    inside = np.zeros((32, 32), bool)
    inside[4:28, 4:28] = True  # the square's pixels: 2 mm = 4 pixels from the image's corner
    assert (image[inside, 3] == 1.0).all() and (image[~inside, 3] == 0.0).all()
    assert image[inside, :3] == pytest.approx(np.tile([0.3, 0.5, 0.7], (inside.sum(), 1)))


def test_a_nearer_face_painted_later_covers_a_farther_one():
    # truth: the painter's order: two overlapping triangles, the second painted last; where both lie
    # its colour shows, where only the first lies the first's
    far = [[0.0, 0.0], [20.0, 0.0], [0.0, 20.0]]
    near = [[5.0, 5.0], [25.0, 5.0], [5.0, 25.0]]
    image = paint(np.array([far, near]), [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.array([0.0, 30.0]), 1.0, (30, 30))
    def at(x, y):
        return image[int(30.0 - y), int(x)]  # the pixel holding the point (x, y) mm
    assert at(7.5, 7.5) == pytest.approx([0.0, 0.0, 1.0, 1.0])  # both: the later (near) one
    assert at(2.5, 2.5) == pytest.approx([1.0, 0.0, 0.0, 1.0])  # the far one only
    assert at(28.5, 28.5)[3] == 0.0  # neither


def test_a_faces_pixels_carry_its_colour_and_edges_only_lose_alpha():
    # truth: a single face's colour, whatever its winding; on its edge pixels only the alpha (the
    # covered fraction) drops, the colour stays (straight alpha), so over white it blends correctly
    tri = np.array([[[1.2, 1.7], [18.9, 3.1], [6.4, 17.3]]])
    colour = [[0.9, 0.25, 0.1]]
    image = paint(tri, colour, np.array([0.0, 20.0]), 0.8, (25, 25))
    reverse = paint(tri[:, ::-1], colour, np.array([0.0, 20.0]), 0.8, (25, 25))
    covered = image[..., 3] > 0
    assert (covered & (image[..., 3] < 1.0)).any() and (image[..., 3] == 1.0).any()
    assert image[covered, :3] == pytest.approx(np.tile(colour, (covered.sum(), 1)))
    assert np.array_equal(image, reverse)


def test_the_row_spans_equal_the_per_sample_rule(rng):
    # truth: the dense reference, every sample tested against every edge with the tie rule written
    # out (inside: edge function > 0, or = 0 on an edge running down the rows, or along a row toward
    # lower columns); vertices snapped to half samples so that samples on edges and corners abound
    height, width = 8, 9
    cols, rows = np.meshgrid(np.arange(width) * SNAP + SNAP // 2, np.arange(height) * SNAP + SNAP // 2)
    for _ in range(200):
        fixed = rng.integers(-2, 12, (int(rng.integers(1, 6)), 3, 2)) * (SNAP // 2)
        want = np.full((height, width), -1)
        for t, ((ax, ay), (bx, by), (cx, cy)) in enumerate(fixed):
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if area == 0:
                continue
            if area < 0:
                bx, by, cx, cy = cx, cy, bx, by
            ok = np.ones((height, width), bool)
            for x0, y0, x1, y1 in ((ax, ay, bx, by), (bx, by, cx, cy), (cx, cy, ax, ay)):
                dx, dy = x1 - x0, y1 - y0
                e = dx * (rows - y0) - dy * (cols - x0)
                ok &= (e > 0) | ((e == 0) & ((dy > 0) | ((dy == 0) & (dx < 0))))
            want[ok] = t
        assert np.array_equal(_fill(np.ascontiguousarray(fixed, dtype=np.int64), height, width), want)


def test_paint_refuses_colours_that_do_not_match_the_triangles():
    # an rgb row short would have the compiled loop read past the array: refused at the boundary
    with pytest.raises(ValueError, match="rgb has 1 rows for 2 triangles"):
        paint(np.zeros((2, 3, 2)), [[1.0, 0.0, 0.0]], np.zeros(2), 1.0, (4, 4))
