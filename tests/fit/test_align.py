"""Rigid alignment recovers known motions; crop faces are found where the mask touches the border."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lungdeform.fit.align import RigidTransform, align_apex, align_landmarks, crop_planes, kabsch, near_planes
from lungdeform.io.grid import Image
from tests.conftest import ellipsoid_lung


def test_kabsch_recovers_rigid(rng):
    r = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    t = np.array([5.0, -3.0, 40.0])
    a = rng.normal(size=(30, 3)) * 50
    xf = kabsch(a, a @ r.T + t)
    assert xf.rotation == pytest.approx(r, abs=1e-10)
    assert xf.translation == pytest.approx(t, abs=1e-8)
    assert xf.inverse().compose(xf).matrix == pytest.approx(np.eye(4), abs=1e-10)


def test_apex_alignment_recovers_table_shift():
    # the same lung shifted by a table move: the anchored ICP undoes it exactly
    fixed = ellipsoid_lung("right", 4)
    shift = np.array([2.0, -1.5, 40.0])
    moving = fixed.deformed(np.tile(shift, (fixed.n_vertices, 1)))
    al = align_apex(fixed, moving)
    assert al.transform.translation == pytest.approx(-shift, abs=0.02)
    assert al.residual_rms_mm < 0.02


def test_landmark_alignment_exact(rng):
    pts = rng.normal(size=(20, 3)) * 40
    xf = RigidTransform(Rotation.from_rotvec([0, 0, 0.05]).as_matrix(), np.array([1.0, 2, 3]))
    al = align_landmarks(xf.apply(pts), pts)
    assert al.residual_rms_mm < 1e-9
    assert al.transform.apply(pts) == pytest.approx(xf.apply(pts), abs=1e-9)


def test_crop_planes():
    a = np.zeros((6, 7, 8), np.uint8)  # (z, y, x)
    a[2:4, 2:5, 5:] = 1  # touches the x-high face only
    img = Image(a, np.array([2.0, 1.0, 3.0]), np.array([10.0, 0.0, 0.0]), np.eye(3))
    planes = crop_planes(img)
    assert [p.label for p in planes] == ["i-high"]
    assert planes[0].offset == pytest.approx(10.0 + 7.5 * 2.0)  # half a voxel beyond the last one
    near = near_planes(np.array([[24.0, 0, 0], [10.0, 0, 0]]), planes, margin_mm=2.0)
    assert near.tolist() == [True, False]
    moved = planes[0].transformed(RigidTransform(np.eye(3), np.array([-5.0, 0, 0])))
    assert moved.offset == pytest.approx(20.0)
