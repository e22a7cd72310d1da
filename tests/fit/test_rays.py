"""Ray correspondence against an analytic sphere (hit distances exact up to faceting)."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.fit.rays import BACKWARD, FORWARD, GRAZING, MISS, NO_DIRECTION, RayCaster, correspond
from lungdeform.geometry.mesh import icosphere

R = 100.0


def _sphere_t(o, d):
    # analytic ray–sphere: |o + t d| = R, the positive root for an origin inside
    b = np.einsum("ij,ij->i", o, d)
    return -b + np.sqrt(b * b - (np.einsum("ij,ij->i", o, o) - R * R))


@pytest.fixture(scope="module")
def sphere():
    return icosphere(5, R)  # edge ≈ 3.8 mm: faceting error ≤ about 0.04 mm (plus float32 rounding)


def test_forward_hits_exact(sphere, rng):
    o = rng.normal(size=(2000, 3)) * 20
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = correspond(o, d, sphere, max_distance=300.0, min_cosine=0.0, both_directions=False)
    assert np.all(hits.status == FORWARD)
    assert hits.distance == pytest.approx(_sphere_t(o, d), abs=0.05)
    assert np.linalg.norm(hits.points, axis=1) == pytest.approx(R, abs=0.05)
    # both directions with a bound: the forward hit is kept where it exists, else the backward one
    both = correspond(o, d, sphere, max_distance=100.0, min_cosine=0.0)
    back = _sphere_t(o, -d)
    fwd = _sphere_t(o, d)
    clear = np.abs(fwd - 100.0) > 0.1  # leave out rays whose wall is at the bound (faceting decides)
    assert both.distance[clear] == pytest.approx(np.where(fwd <= 100.0, fwd, -back)[clear], abs=0.05)
    assert np.all((both.status == FORWARD)[clear] == (fwd <= 100.0)[clear])


def test_backward_hit_is_negative(sphere):
    # origin outside, pointing away: only the backward ray hits, at minus the entry distance
    o = np.array([[0.0, 0.0, 130.0]])
    d = np.array([[0.0, 0.0, 1.0]])
    hits = correspond(o, d, sphere, max_distance=100.0, min_cosine=0.0)
    assert hits.status[0] == BACKWARD
    assert hits.distance[0] == pytest.approx(-30.0, abs=0.05)
    only_forward = correspond(o, d, sphere, max_distance=100.0, both_directions=False)
    assert only_forward.status[0] == MISS and np.isnan(only_forward.distance[0])


def test_bounded_search_and_grazing_and_zero(sphere):
    o = np.array([[0.0, 0, 0], [0, 99.0, -50.0], [0, 0, 0]])
    d = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 0, 0]])
    hits = correspond(o, d, sphere, max_distance=50.0, min_cosine=0.5, both_directions=False)
    assert hits.status[0] == MISS  # the wall is 100 mm away, beyond the bound
    assert hits.status[1] == GRAZING  # hits at ~8° to the surface
    assert hits.status[2] == NO_DIRECTION
    assert sum(hits.counts.values()) == 3
    counts, edges = hits.histogram(10)
    assert counts.sum() == hits.valid.sum() == 0 and edges[0] == -50.0


def test_caster_reuse_and_shapes(sphere):
    caster = RayCaster(sphere.vertices, sphere.faces)
    t, face = caster.first_hits(np.zeros((1, 3)), np.array([[0, 1.0, 0]]))
    assert face[0] >= 0 and t[0] == pytest.approx(R, abs=0.05)
    with pytest.raises(InputError):
        correspond(np.zeros((2, 3)), np.zeros((3, 3)), caster)
