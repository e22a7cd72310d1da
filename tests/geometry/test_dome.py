"""The dome excursion (geometry.dome) on analytic lung-like solids whose apex and floor are known in closed form."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.dome import APEX_SHARE, dome_excursion, dome_weights
from lungdeform.geometry.mesh import Surface, icosphere

# an analytic "lung" over the ellipse ρ² = x²/A² + y²/B² < 1: a cap z = H·r on top (r = √(1 − ρ²); apex at
# z = H) and a floor z = D·r² − T·r underneath: it rises to a dome of height D − T at the centre and dips
# into a shallow recess near the rim, as a lung sits on its hemidiaphragm
A, B, H, D, T = 60.0, 80.0, 120.0, 60.0, 20.0


def _lung(h=H, d=D, t=T, subdivisions=6):
    s = icosphere(subdivisions, 1.0)
    x, y, z = s.vertices.T
    r = np.sqrt(np.clip(1.0 - x ** 2 - y ** 2, 0.0, 1.0))
    return Surface(np.c_[A * x, B * y, np.where(z >= 0, h * r, d * r ** 2 - t * r)], s.faces, "lung")


def _apex(h=H):
    # the cap's shadow is uniform in t = ρ² over [0, APEX_SHARE] (its footprint π·A·B·t): mean of H·√(1 − t)
    a = APEX_SHARE
    return h * (2.0 / 3.0) * (1.0 - (1.0 - a) ** 1.5) / a


def _floor(d=D, t=T):
    # the floor's mean over its shadow, the whole ellipse (uniform in t = ρ² over [0, 1]): D/2 − 2T/3
    return d / 2.0 - 2.0 * t / 3.0


def test_heights_are_the_apex_cap_and_the_floor():
    # both heights are means weighted by shadow (area projected on a horizontal plane), known in closed form
    s = _lung()
    w = dome_weights(s.vertices, s.faces)
    assert w.apex_height_mm == pytest.approx(_apex(), abs=0.05)
    assert w.dome_height_mm == pytest.approx(_floor(), abs=0.05)
    assert w.footprint_mm2 == pytest.approx(np.pi * A * B, rel=1e-3)
    assert np.isclose(w.apex.sum(), 1.0) and np.isclose(w.dome.sum(), 1.0)


def test_the_steps_of_a_mask_do_not_move_the_floor():
    # the same lung voxelised as a CT mask (1.5 × 1.5 × 2.5 mm) and meshed by marching cubes: its sloping
    # floor is a staircase whose treads face the feet. A tread has the shadow of the slope it replaces and a
    # riser has none, so the floor's height stays that of the smooth lung (to a fraction of a voxel)
    from skimage.measure import marching_cubes

    spacing = np.array([1.5, 1.5, 2.5])
    axes = [np.arange(-A - 5, A + 5, spacing[0]), np.arange(-B - 5, B + 5, spacing[1]),
            np.arange(-10.0, H + 5, spacing[2])]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    rho2 = x ** 2 / A ** 2 + y ** 2 / B ** 2
    r = np.sqrt(np.clip(1.0 - rho2, 0.0, 1.0))
    solid = (rho2 < 1.0) & (z <= H * r) & (z >= D * r ** 2 - T * r)
    v, f, _, _ = marching_cubes(np.pad(solid, 1).astype(float), 0.5, spacing=tuple(spacing))
    v = v - spacing + [axes[0][0], axes[1][0], axes[2][0]]
    w = dome_weights(v, f[:, ::-1])  # marching cubes winds inward here
    assert w.dome_height_mm == pytest.approx(_floor(), abs=0.5)
    assert w.apex_height_mm == pytest.approx(_apex(), abs=1.5)  # the top voxel layer: within one slice


def test_translation_cancels_and_scaling_along_the_axes_is_exact():
    # E = L(S1) − L(S0): a shift of either scan cancels; a scaling by (s_x, s_y, s_z) about any centre
    # multiplies every shadow by s_x·s_y and keeps the order of heights, so E = (s_z − 1)·L exactly, and
    # the Lagrangian reading (weights of S0 applied to the displacement) gives the same number
    s0 = _lung()
    w = dome_weights(s0.vertices, s0.faces)
    moved = Surface(s0.vertices + [13.0, -7.0, 41.0], s0.faces, "moved")
    assert abs(dome_excursion(s0, moved)) < 1e-9
    c, scale = np.array([5.0, 3.0, 70.0]), np.array([1.3, 0.9, 1.15])
    v1 = c + (s0.vertices - c) * scale
    assert dome_excursion(s0, Surface(v1, s0.faces, "scaled")) == pytest.approx(0.15 * w.height_mm, rel=1e-9)
    assert w.excursion(v1 - s0.vertices) == pytest.approx(0.15 * w.height_mm, rel=1e-9)
    assert abs(w.excursion(np.tile([2.0, -1.0, 9.0], (s0.n_vertices, 1)))) < 1e-9


def test_a_dome_that_descends_alone():
    # only the floor changes (its crest drops by 8 mm, the rim and the apex stay): the floor's mean over the
    # ellipse drops by 8/2 mm (its drop D·r² averages to 1/2 over t), and the dome descends relative to the apex
    s0, s1 = _lung(), _lung(d=D - 8.0)
    assert dome_excursion(s0, s1) == pytest.approx(4.0, abs=0.05)
    assert dome_excursion(s1, s0) == pytest.approx(-4.0, abs=0.05)


def test_a_cut_dome_is_refused_a_cut_side_is_not():
    # a crop face under the dome (the scan cut the floor off) leaves its height unknown: refused, naming the
    # surface; a crop face on the side (as the ITK lung's medial face) is measured as it is
    s0 = _lung()
    floor_cut = ~((np.abs(s0.vertices[:, 0]) < 40) & (np.abs(s0.vertices[:, 1]) < 50) & (s0.vertices[:, 2] < 50))
    with pytest.raises(InputError, match="lung: the dome lies on a crop face"):
        dome_weights(s0.vertices, s0.faces, floor_cut, name="lung")
    top_cut = s0.vertices[:, 2] < 110
    with pytest.raises(InputError, match="lung: the apex lies on a crop face"):
        dome_weights(s0.vertices, s0.faces, top_cut, name="lung")
    side_cut = s0.vertices[:, 0] < 55
    assert dome_weights(s0.vertices, s0.faces, side_cut).height_mm == dome_weights(s0.vertices, s0.faces).height_mm
