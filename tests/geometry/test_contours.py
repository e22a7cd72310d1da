"""Tests of lungdeform.geometry.contours: planar sections of a surface and a surface through contours."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from lungdeform.geometry.contours import contours_to_mesh, plane_normal, section_mesh
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
