"""lungdeform.playback.field_grid: a field carried to a REG's coarse grid, and the error a reader gets back."""

import numpy as np
import pytest

from lungdeform.playback.displacement_field import Grid
from lungdeform.playback.field_grid import coarse_grid, coarsened, interpolation_error

#: An oblique grid of 61 × 51 × 21 voxels of 1 × 1.2 × 2.5 mm.
_D = np.linalg.qr(np.array([[1.0, 0.2, 0.1], [0.1, 1.0, -0.2], [0.0, 0.3, 1.0]]))[0]
GRID = Grid((21, 51, 61), np.array([1.0, 1.2, 2.5]), np.array([-30.0, 12.0, 5.0]), _D * np.sign(np.linalg.det(_D)))


def _world(grid: Grid) -> np.ndarray:
    k, j, i = np.indices(grid.shape)
    return grid.world(np.stack([i, j, k], axis=-1).reshape(-1, 3)).reshape(*grid.shape, 3)


def test_the_coarse_grid_spans_the_same_box_at_most_the_given_spacing():
    # why: a REG's first and last nodes lie on the grid's first and last voxel centres (nothing
    # beyond the image, nothing cropped); every step at most 3 mm, the fewest nodes that allow it
    # (60 mm of x: 21 nodes of 3 mm; 60 mm of y: 21; 50 mm of z: 18 of 2.94 mm); an axis already
    # coarser than the spacing is kept
    c = coarse_grid(GRID, 3.0)
    assert np.all(c.spacing <= 3.0 + 1e-12) and c.shape == (18, 21, 21)
    assert c.spacing == pytest.approx([3.0, 3.0, 50 / 17])
    def last(g):
        return g.world(np.array(g.shape[::-1], float) - 1)
    assert np.allclose(c.origin, GRID.origin) and np.allclose(last(c), last(GRID), atol=1e-9)
    assert np.allclose(c.direction, GRID.direction)
    assert coarse_grid(GRID, 2.4).shape[0] == 21 and coarse_grid(GRID, 0.5) is GRID


def test_an_affine_field_comes_back_exactly_and_a_curved_one_within_the_trilinear_bound():
    # why: trilinear interpolation reproduces an affine field exactly (float32 rounding aside), and
    # errs on u = a·s² (s the distance along the first index axis) by at most h²/8 · 2a, reached
    # at cell middles: the measured error lies between half that bound and the bound
    x = _world(GRID)
    affine = (x @ np.array([[0.02, 0.0, 0.01], [0.0, -0.03, 0.0], [0.05, 0.0, 0.02]]) + [1.0, -2.0, 0.5]).astype(np.float32)
    c = coarse_grid(GRID, 3.0)
    err = interpolation_error(affine, coarsened(affine, GRID, c))
    assert err.max_mm < 1e-4 and err.moving == affine[..., 0].size
    a = 0.01
    s = np.indices(GRID.shape)[2] * GRID.spacing[0]
    curved = np.zeros(GRID.shape + (3,), np.float32)
    curved[..., 1] = a * s ** 2
    err = interpolation_error(curved, coarsened(curved, GRID, c))
    bound = c.spacing[0] ** 2 / 8 * 2 * a
    assert 0.5 * bound < err.max_mm <= bound * 1.001, (err, bound)
    # the nodes hold the field's own values where they fall on voxels: along x every third voxel
    # (61 voxels of 1 mm, 21 nodes of 3 mm); the curved field varies along x only
    assert np.allclose(coarsened(curved, GRID, c)[:, :, 5, 1], curved[0, 0, 15, 1], rtol=1e-6)
