"""Tests of lungdeform.geometry.contours: planar sections of a surface and a surface through contours."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh
from skimage.draw import polygon2mask

from lungdeform.errors import InputError
from lungdeform.geometry.contours import MAX_POINTS, contours_to_mesh, parity_mask, plane_normal, section_mesh
from lungdeform.geometry.mesh import signed_volume


def test_section_of_a_sphere_is_its_circle():
    # the plane z = 5 cuts a sphere of radius 12 in a circle of radius sqrt(144 - 25); the
    # icosphere's chords sag less than 0.02 mm
    s = trimesh.creation.icosphere(4, radius=12.0)
    loops = section_mesh(s.vertices, s.faces, [0, 0, 5.0], [0, 0, 1.0])
    assert len(loops) == 1 and np.allclose(loops[0][:, 2], 5.0)
    assert np.abs(np.linalg.norm(loops[0][:, :2], axis=1) - np.sqrt(119.0)).max() < 0.02
    assert plane_normal(loops[0]) == pytest.approx([0, 0, 1])
    assert section_mesh(s.vertices, s.faces, [0, 0, 20.0], [0, 0, 1.0]) == []


def test_surface_through_sphere_contours():
    # 2 mm slices of a sphere of radius 12 (z = -11 … 11): the surface through them is closed and
    # outward (positive volume) and holds the sphere's volume less its caps beyond the end slices
    # (the surface closes half a slice past them): within 3 %
    s = trimesh.creation.icosphere(4, radius=12.0)
    contours = [c for z in np.arange(-11.0, 11.1, 2.0) for c in section_mesh(s.vertices, s.faces, [0, 0, z], [0, 0, 1])]
    v, f = contours_to_mesh(contours)
    assert signed_volume(v, f) == pytest.approx(4 / 3 * np.pi * 12.0**3, rel=0.03)
    assert trimesh.Trimesh(v, f, process=True).is_watertight


def test_parity_mask_matches_skimage_and_stays_fast():
    # the scanline fill replaces skimage's polygon2mask, which tests every pixel against every edge
    # (a 250 000-point contour: hours); it must fill the same pixel centres, holes by parity
    rng = np.random.default_rng(3)
    for _ in range(100):
        polys = [rng.uniform(-5, 60, (int(rng.integers(3, 30)), 2)) for _ in range(int(rng.integers(1, 4)))]
        want = np.zeros((50, 55), bool)
        for p in polys:
            want ^= polygon2mask((50, 55), p)
        assert np.array_equal(parity_mask((50, 55), polys, chunk=int(rng.integers(1, 200))), want)
    zigzag = rng.uniform(0, 383, (MAX_POINTS, 2))
    start = time.monotonic()
    parity_mask((384, 384), [zigzag])
    assert time.monotonic() - start < 20.0


def test_contour_checks_name_the_contour():
    # each contour is checked before the surface is made; the error names the source, the contour
    # (1-based) and the structure
    ring = [c for z in (0.0, 2.0, 4.0) for c in section_mesh(*_sphere_mesh(), [0, 0, z], [0, 0, 1])]
    bad = [ring[0], np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0]]), ring[2]]
    with pytest.raises(InputError, match=r"^rs.dcm: contour 2 of structure 'GTV' has 2 point\(s\)"):
        contours_to_mesh(bad, "structure 'GTV'", "rs.dcm")
    with pytest.raises(InputError, match=r"^contour 2 of structure has non-finite coordinates"):
        contours_to_mesh([ring[0], ring[1] * np.nan, ring[2]])


def _sphere_mesh():
    s = trimesh.creation.icosphere(3, radius=8.0)
    return s.vertices, s.faces


def test_a_repeated_contour_is_refused_and_a_tiny_one_kept():
    # a contour listed twice (from another start, or backwards) cancels itself by parity: the slice
    # would be empty and the surface cut in two, so it is refused; a contour smaller than a pixel
    # (a 0.3 mm sliver) would do the same: it counts as one pixel, and the surface stays one body
    ring = [c for z in (0.0, 2.0, 4.0) for c in section_mesh(*_sphere_mesh(), [0, 0, z], [0, 0, 1])]
    again = np.roll(ring[1][::-1], 5, axis=0)
    with pytest.raises(InputError, match=r"contour 4 of structure 'GTV' repeats contour 2 \(on one slice they cancel\)"):
        contours_to_mesh(ring + [again], "structure 'GTV'")
    tiny = np.array([[0.0, 0.1234, 2.0], [0.3, 0.1234, 2.0], [0.15, 0.1236, 2.0]])  # a 0.3 mm sliver
    v, f = contours_to_mesh([ring[0], tiny, ring[2]], "structure 'GTV'")
    assert len(trimesh.Trimesh(v, f).split(only_watertight=False)) == 1
