"""Landmark readers: DIR-Lab voxel files and elastix point sets (lungdeform.io.landmarks)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.errors import InputError, ReadError
from lungdeform.io.landmarks import (
    dirlab_index_to_mm,
    read_dirlab_indices,
    read_dirlab_points,
    read_elastix_points,
    write_elastix_points,
)
from tests.conftest import require_path


def test_dirlab_crlf_tabs_floats(tmp_path):
    p = tmp_path / "case1_4D-75_T10.txt"
    p.write_bytes(b" 88.000000\t 175.000000\t 81.000000\t\r\n100\t142\t26\r\n\r\n")
    idx = read_dirlab_indices(p)
    assert idx.shape == (2, 3) and idx.flags["C_CONTIGUOUS"]
    # truth: mm = (index - 1) * spacing, 1-based
    pts = read_dirlab_points(p, (0.97, 0.97, 2.5))
    assert np.allclose(pts[0], [87 * 0.97, 174 * 0.97, 80 * 2.5])
    assert np.allclose(dirlab_index_to_mm([[1, 1, 1]], (2, 2, 2)), 0.0)  # the first voxel is the origin


@pytest.mark.parametrize(
    "body, message",
    [
        (b"1 2 3\r\n4 5\r\n", r"bad\.txt, line 2: expected 3 numbers"),
        (b"1 2 3\n4 five 6\n", r"bad\.txt, line 2: not a number"),
        (b"1 2 3\n0 5 6\n", r"bad\.txt, line 2: voxel index 0 < 1.*1-based"),
        (b"\n\n", r"bad\.txt: no landmarks"),
        (b"1 2 nan\n", r"bad\.txt, line 1: non-finite"),
    ],
)
def test_dirlab_bad_rows_name_file_and_line(tmp_path, body, message):
    p = tmp_path / "bad.txt"
    p.write_bytes(body)
    with pytest.raises(ReadError, match=message):
        read_dirlab_points(p, (1, 1, 1))


def test_dirlab_outside_image_and_bad_spacing(tmp_path):
    p = tmp_path / "pts.txt"
    p.write_text("10 10 10\n257 10 10\n")
    with pytest.raises(ReadError, match=r"pts\.txt: landmark 2 .* outside the image of \[256, 256, 94\]"):
        read_dirlab_points(p, (1, 1, 1), shape=(256, 256, 94))
    assert read_dirlab_points(p, (1, 1, 1), shape=(257, 256, 94)).shape == (2, 3)
    for bad in [(1, 1), (1, 0, 1), (1, -2, 1), (1, float("nan"), 1)]:
        with pytest.raises(InputError, match="spacing"):
            read_dirlab_points(p, bad)
    with pytest.raises(ReadError, match="no such file"):
        read_dirlab_points(tmp_path / "missing.txt", (1, 1, 1))


def test_elastix_roundtrip_and_index_files(tmp_path, rng):
    pts = rng.normal(0, 100, (7, 3))
    p = write_elastix_points(tmp_path / "pts.txt", pts)
    assert np.allclose(read_elastix_points(p), pts, atol=1e-6)
    assert [f.name for f in tmp_path.iterdir()] == ["pts.txt"]  # atomic: no temp file left
    q = tmp_path / "idx.txt"
    q.write_bytes(b"index\r\n2\r\n0 0 0\r\n1 2 3\r\n")
    with pytest.raises(InputError, match="idx.txt holds voxel indices"):
        read_elastix_points(q)
    # truth: world = origin + direction @ (index * spacing)
    d = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    w = read_elastix_points(q, spacing=(1, 2, 3), origin=(10, 20, 30), direction=d)
    assert np.allclose(w, [[10, 20, 30], [10 - 4, 20 + 1, 30 + 9]])


@pytest.mark.parametrize(
    "body, message",
    [
        ("pont\n1\n1 2 3\n", r"line 1: expected 'point' or 'index'"),
        ("point\nthree\n1 2 3\n", r"line 2: expected the number of points"),
        ("point\n3\n1 2 3\n", r"header says 3 points, the file holds 1"),
        ("point\n2\n1 2 3\n1 2\n", r"line 4: expected 3 numbers"),
    ],
)
def test_elastix_bad_files(tmp_path, body, message):
    p = tmp_path / "set.txt"
    p.write_text(body)
    with pytest.raises(ReadError, match=message):
        read_elastix_points(p)


@pytest.mark.realdata
def test_itk_corrected_point_sets(data_dir):
    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    fixed = read_elastix_points(folder / "CT_3D_lung_fixed_point_set_corrected.txt")
    moving = read_elastix_points(folder / "CT_3D_lung_moving_point_set_corrected.txt")
    # README: 51 in-lung pairs, world mm; the first fixed row is -36.351 -36.974 -1204.5
    assert fixed.shape == moving.shape == (51, 3)
    assert np.allclose(fixed[0], [-36.351, -36.974, -1204.5])
