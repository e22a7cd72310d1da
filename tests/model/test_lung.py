"""Building a lung model end to end, re-orienting it, and the model file round trip."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.model.force import field_basis
from lungdeform.model.graph import spring_graph
from lungdeform.model.lung import BuildSettings, build_lung, build_model
from lungdeform.model.solve import push
from lungdeform.model.transfer import local_transfer


@pytest.fixture
def model(left_lung):
    return build_lung(left_lung, "left")


def test_volume_linear_over_tidal_range(model):
    # docs/METHOD_NOTES.md §7 (linear in volume): across 500 mL, V(s) matches V_EE + s·ΔV within 1 % (end point exact).
    v0 = model.volume_ee_ml
    for s in np.linspace(0, 500, 11):
        v = model.surface_at(scale=s).volume_ml
        assert abs(v - (v0 + s * model.unit_ml)) <= 0.01 * (v0 + s * model.unit_ml)
    assert model.surface_at(scale=500).volume_ml == pytest.approx(v0 + 500, rel=1e-12)
    # the exact path hits any volume exactly
    assert model.surface_at(v0 + 123.0, exact=True).volume_ml == pytest.approx(v0 + 123.0, rel=1e-12)


def test_force_basis_is_the_solver_response(model, left_lung):
    # The stored responses are what the push loop gives for each field (dense-free reference).
    g = spring_graph(left_lung.vertices, left_lung.edges)
    t = local_transfer(g, model.stiffness)
    fields = field_basis(model.frame.normalized(left_lung.vertices))
    ref = push(t, fields[2], tol=1e-12).kept[: model.n_vertices]
    assert np.abs(model.force_basis[2] - ref).max() <= 1e-6 * np.abs(ref).max()
    # and the force of the model's orientation is the weighted sum
    assert np.allclose(model.force, model.force_weights @ model.force_basis)


def test_stiff_region_moves_less(left_lung):
    # Heterogeneous stiffness: a stiff sphere (tumour) keeps less force, so it moves less.
    from lungdeform.model.stiffness import sphere_override, uniform

    centre = left_lung.vertices[np.argmin(left_lung.vertices[:, 1])]  # anterior surface point
    e = sphere_override(uniform(left_lung.n_vertices), left_lung.vertices, centre, 25.0, 20.0)
    soft = build_lung(left_lung, "left")
    stiff = build_lung(left_lung, "left", stiffness=e)
    inside = np.linalg.norm(left_lung.vertices - centre, axis=1) <= 25.0
    ratio = stiff.force[inside].mean() / soft.force[inside].mean()
    assert ratio < 0.5


def test_orientation_changes_motion_but_keeps_volume(model):
    up = model.oriented("upright")
    assert not np.allclose(up.displacement, model.displacement)
    assert up.surface_at(scale=500).volume_ml == pytest.approx(model.volume_ee_ml + 500, rel=1e-12)
    # supine → supine is the identity
    assert np.allclose(model.oriented("supine").displacement, model.displacement, rtol=1e-12)


def test_solver_choice_does_not_change_the_model(left_lung, model):
    direct = build_lung(left_lung, "left", settings=BuildSettings(solver="direct"))
    assert np.allclose(direct.displacement, model.displacement, rtol=1e-8, atol=1e-12)


def test_bad_constants_and_stiffness(left_lung):
    with pytest.raises(InputError, match="constants"):
        build_lung(left_lung, "left", constants=[1, 2, 3])
    with pytest.raises(InputError, match="stiffness"):
        build_lung(left_lung, "left", stiffness=np.zeros(left_lung.n_vertices))


def _check_tidal_linearity(lung_model):
    # Across the tidal range the enclosed volume at s units is V_EE + s·ΔV within 1 %.
    v0 = lung_model.volume_ee_ml
    worst = 0.0
    for s in np.linspace(0, lung_model.calibration_ml / lung_model.unit_ml, 21):
        want = v0 + s * lung_model.unit_ml
        got = lung_model.surface_at(scale=s).volume_ml
        worst = max(worst, abs(got - want) / want)
    assert worst <= 0.01
    return worst


def test_embedded_real_lungs_follow_500_ml(tmp_path):
    # The embedded lungs are real (Coronacases 001): 500 mL over both lungs, and each lung alone.
    from lungdeform.data import default_lungs
    from lungdeform.model.lung import build_model

    lungs = default_lungs()
    model = build_model(lungs, tidal_ml=500.0)
    for lung in model.lungs.values():
        _check_tidal_linearity(lung)
    single = build_lung(lungs["right"], "right", settings=BuildSettings(500.0))
    _check_tidal_linearity(single)
    # directions and force are physical: every vertex moves outward-ish on average
    u = single.displacement
    assert np.einsum("ij,ij->i", u, single.surface.vertex_normals).mean() > 0


def test_real_itk_lung_follows_500_ml(data_dir):
    # Real data: the ITK right lung (smaller volume) from its mask, 500 mL tidal range.
    from lungdeform.io.meshfile import load
    from tests.conftest import require_path

    folder = require_path(data_dir, "itk-right-lung-two-volumes")
    mask = sorted(p for p in folder.iterdir() if p.name.endswith("_mask.mha"))
    assert mask, f"no *_mask.mha in {folder}"
    surfaces = [s for m in mask for s, _ in load(m, target_vertices=4000)]
    smaller = min(surfaces, key=lambda s: s.volume_ml)
    assert 3000 < smaller.volume_ml < 3700  # data README: 3.36 L
    lung = build_lung(smaller, "right", settings=BuildSettings(500.0))
    _check_tidal_linearity(lung)


def test_every_named_orientation_expands_real_lungs():
    # Directions take their origins on the side the lung rests on (paper's supine reasoning
    # applied to any position), so prone and both decubitus positions breathe too.
    from lungdeform.constants import GRAVITY
    from lungdeform.data import default_lungs
    from lungdeform.model.lung import build_model

    model = build_model(default_lungs())
    for name in GRAVITY:
        for lung in model.oriented(name).lungs.values():
            grown = lung.surface_at(scale=lung.calibration_ml / lung.unit_ml).volume_ml
            assert grown == pytest.approx(lung.volume_ee_ml + lung.calibration_ml, rel=1e-9)


def test_prone_directions_mirror_supine(left_lung):
    # Prone flips only the anterior–posterior axis of the directions.
    supine = build_lung(left_lung, "left")
    prone = supine.oriented("prone")
    frame = supine.frame.supported("prone")
    assert np.allclose(frame.axes[1], -supine.frame.axes[1]) and np.allclose(frame.axes[[0, 2]], supine.frame.axes[[0, 2]])
    assert np.all(prone.directions[:, 1] >= 0)  # now posterior (+y LPS) or zero
    assert np.allclose(prone.directions[:, [0, 2]] != 0, supine.directions[:, [0, 2]] != 0)


def test_a_reoriented_model_drops_its_interior_map(model):
    # the surface-to-surface map was observed in the scans' posture, like the landmark correction:
    # another gravity falls back to the sliding field of the recombined displacement
    from dataclasses import replace

    from lungdeform.interior.surface_map import SurfaceMapField

    c = model.surface.vertices[:10]
    mapped = replace(model, interior_map=SurfaceMapField(np.full((3, 4), 0.01), np.c_[np.eye(3), np.zeros(3)], c,
                                                             np.zeros((10, 3)), 50.0))
    q = model.surface.vertices.mean(axis=0)[None, :]
    np.testing.assert_allclose(mapped.interior.displacement(q), mapped.interior_map(q))
    turned = mapped.oriented("prone")
    assert turned.interior_map is None
    assert not np.allclose(turned.interior.displacement(q), mapped.interior_map(q))


def test_a_lone_lung_is_calibrated_at_its_share_two_lungs_at_all(left_lung, right_lung):
    # truth: the surface at each lung's calibration encloses V_EE + its part, measured on the mesh; a
    # lone left lung takes 46.4 % of 500 mL (its side's usual share), two lungs all 500 mL by volume
    one = build_model({"left": left_lung}, tidal_ml=500.0, default="paper")
    lung = one.lungs["left"]
    assert lung.calibration_ml == pytest.approx(0.464 * 500.0)
    grown = lung.surface_at(scale=lung.calibration_ml / lung.unit_ml).volume_ml
    assert grown == pytest.approx(lung.volume_ee_ml + 232.0, rel=1e-9)
    assert one.provenance["tidal_ml"] == 500.0 and "46.4%" in one.provenance["tidal_split"]
    two = build_model({"left": left_lung, "right": right_lung}, tidal_ml=500.0, default="paper")
    total = left_lung.volume_ml + right_lung.volume_ml
    for side, s in (("left", left_lung), ("right", right_lung)):
        assert two.lungs[side].calibration_ml == pytest.approx(500.0 * s.volume_ml / total, rel=1e-12)
    assert sum(l.calibration_ml for l in two.lungs.values()) == pytest.approx(500.0, rel=1e-12)


def test_surface_interior_is_the_interior_field_on_the_surface_once(model):
    # the cached per-unit displacement at the lung's own vertices must be the interior field there
    # (what surface_peak measured on every call), computed once a lung, and moved by a re-oriented
    # lung's own field (a new object, a new cache)
    v = model.interior.displacement(model.surface.vertices)
    assert np.array_equal(model.surface_interior, v) and np.abs(v).max() > 0
    assert model.surface_interior is model.surface_interior
    turned = model.oriented("prone")
    assert np.array_equal(turned.surface_interior, turned.interior.displacement(turned.surface.vertices))
    assert not np.array_equal(turned.surface_interior, v)
