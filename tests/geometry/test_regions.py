"""Regions of a lung's surface (lungdeform.geometry.regions) on an ellipsoid, where each is known analytically."""

from __future__ import annotations

import numpy as np

from lungdeform.geometry.mesh import Surface, icosphere, vertex_normals
from lungdeform.geometry.regions import REGIONS, region_means, region_shares, surface_regions

AXES = np.array([60.0, 45.0, 110.0])


def _ellipsoid():
    s = icosphere(4, 1.0)
    return Surface(s.vertices * AXES + [30.0, -20.0, 100.0], s.faces, "ellipsoid")


def test_regions_follow_height_and_normal_on_both_sides():
    # truth: on an ellipsoid the lung frame's height is z (apex at the top, LPS +z), the outward normal is
    # known at every vertex; a right lung's heart lies at +x (its medial face), a left lung's at -x: the
    # labels are the rules of the docstring written out in LPS, and the left labels mirror the right ones
    s = _ellipsoid()
    v, n = s.vertices, vertex_normals(s.vertices, s.faces)
    height = (v[:, 2].max() - v[:, 2]) / np.ptp(v[:, 2])
    for side, towards_heart in (("right", 1.0), ("left", -1.0)):
        labels = surface_regions(v, s.faces, side)
        expected = np.full(len(v), REGIONS.index("costal"))
        expected[towards_heart * n[:, 0] > 0.5] = REGIONS.index("mediastinal")
        expected[(height > 0.5) & (-n[:, 2] > 0.5)] = REGIONS.index("base")
        expected[height < 0.15] = REGIONS.index("apex")
        assert np.array_equal(labels, expected), side
        assert set(labels) == set(range(len(REGIONS)))  # every region is there
    shares = region_shares(v, s.faces, labels)
    assert abs(sum(shares.values()) - 1.0) < 1e-12 and all(x > 0 for x in shares.values())


def test_region_means_are_area_weighted_per_region():
    # truth: a value constant per region gives that constant back; weights change a mixed region's mean
    # exactly as np.average does; an index selects vertices; a region left without vertices is None
    labels = np.array([0, 0, 1, 2, 2, 3])
    values = np.array([1.0, 3.0, 5.0, 7.0, 7.0, 9.0])
    weights = np.array([1.0, 3.0, 1.0, 2.0, 1.0, 1.0])
    got = region_means(labels, values, weights)
    assert got == {"apex": 2.5, "base": 5.0, "costal": 7.0, "mediastinal": 9.0}
    got = region_means(labels, values[[0, 2]], weights[[0, 2]], index=np.array([0, 2]))
    assert got == {"apex": 1.0, "base": 5.0, "costal": None, "mediastinal": None}
