"""Mass-conserving warps and phase projections (lungdeform.playback.density) against analytic truth."""

import numpy as np
import pytest
from scipy import ndimage

from lungdeform.errors import InputError
from lungdeform.io.image import Image, resample_image
from lungdeform.playback import density as M
from lungdeform.playback import displacement_field as D


def _expansion(shape, spacing, centre, s):
    """The resampling field of a uniform expansion by ``s`` about ``centre``: w(y) = (1/s − 1)(y − c)."""
    grid = D.Grid(shape, np.asarray(spacing, float), np.zeros(3), np.eye(3))
    k, j, i = np.indices(shape)
    y = grid.world(np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1))
    return grid, ((1.0 / s - 1.0) * (y - centre)).reshape(shape + (3,)).astype(np.float32), y.reshape(shape + (3,))


def test_uniform_expansion_conserves_the_mass_of_a_lung_phantom():
    # why: a uniform expansion by s about c has det ∇φ = 1/s³ everywhere (φ(y) = c + (y − c)/s), so a
    # −800 HU ball of radius R (mass (200/1000) g/mL × its volume) becomes a ball of radius sR at
    # (200/s³ − 1000) HU with the same mass; a plain resampling keeps −800 HU and gains s³ − 1
    shape, spacing, c, s, radius = (48, 64, 64), (1.5, 1.5, 2.0), np.array([48.0, 48.0, 48.0]), 1.1, 20.0
    grid, w, y = _expansion(shape, spacing, c, s)
    r0 = np.linalg.norm(y - c, axis=-1)
    # a −800 HU lung in water, the edge blurred over a few mm as a scanner's point spread does (a
    # sharp edge makes each voxel on it mix lung and water under interpolation: that is the CT's
    # resolution, not the mass balance)
    # (a region's boundary is drawn where the density is flat, 7 mm inside; a 10 mm water shell in air)
    step = np.where(r0 <= radius, -800.0, np.where(r0 <= radius + 10, 0.0, -1000.0))
    hu = ndimage.gaussian_filter(step, 1.0).astype(np.float32)
    img = Image(hu, np.array(spacing, float), np.zeros(3), np.eye(3), "phantom")
    jac = D.jacobian_determinant(w, grid.spacing, grid.direction)
    assert np.allclose(jac, s ** -3, rtol=1e-4)
    plain = resample_image(img, w, default=-1000.0).array
    dens = M.conserve_mass(plain, jac)
    vox = float(np.prod(spacing)) / 1000.0
    ball0, ball1 = r0 <= radius - 7, r0 <= s * (radius - 7)
    # the region at the state: the reference ball resampled linearly (each voxel's fraction in it)
    moved = resample_image(Image(ball0.astype(np.float32), img.spacing, img.origin, img.direction, "b"), w,
                           default=0.0).array
    assert M.mass_g(dens, vox, moved) == pytest.approx(M.mass_g(hu, vox, ball0), rel=0.005)
    assert M.mass_g(dens, vox, ball1) == pytest.approx(M.mass_g(hu, vox, ball0), rel=0.03)  # voxel counts
    assert M.mass_g(dens, vox) == pytest.approx(M.mass_g(hu, vox), rel=1e-3)
    assert M.mass_g(plain, vox, moved) == pytest.approx(s ** 3 * M.mass_g(hu, vox, ball0), rel=0.01)
    core = np.linalg.norm(y - c, axis=-1) < s * radius - 10
    assert np.allclose(dens[core], 200.0 / s ** 3 - 1000.0, atol=0.5)


def test_pixel_type_rounds_integers_and_refuses_what_does_not_fit():
    # why: an int16 CT stays int16 (rounded), and a value its type cannot hold is an error, not clipped
    assert M.as_pixel_type(np.array([1.4, -2.6]), np.int16).tolist() == [1, -3]
    with pytest.raises(InputError, match="uint8"):
        M.as_pixel_type(np.array([300.0]), np.uint8)
    assert M.as_pixel_type(np.array([0.25]), np.float32).dtype == np.float32


def test_projections_are_the_maximum_mean_and_minimum_over_phases():
    # why: MIP, AIP and MinIP are by definition the voxel-wise max, mean and min over the phases
    rng = np.random.default_rng(3)
    stack = rng.normal(-500, 300, size=(5, 4, 6, 7)).astype(np.float32)
    p = M.Projector()
    for a in stack:
        p.add(a)
    assert np.array_equal(p.result("mip"), stack.max(axis=0))
    assert np.array_equal(p.result("minip"), stack.min(axis=0))
    assert np.allclose(p.result("aip"), stack.mean(axis=0), atol=1e-3)
    assert M.parse_projections("MIP, minip") == ["mip", "minip"]
    for bad in ("mip,mip", "max", ""):
        with pytest.raises(InputError, match="--projections"):
            M.parse_projections(bad)
