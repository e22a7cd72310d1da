"""The population default: Table I and the shipped default, the file round trip, mirror symmetry,
and what a model built with a default records and plays."""

import json
from dataclasses import replace

import numpy as np
import pytest

from lungdeform.constants import TABLE_I
from lungdeform.errors import InputError, ReadError
from lungdeform.geometry.mesh import Surface
from lungdeform.interior.prior import lung_normaliser, prior_displacement
from lungdeform.model.lung import build_lung, build_model
from lungdeform.model.population import (
    PopulationDefault,
    paper_default,
    read_default,
    resolve_default,
    save_default,
    shipped_default,
)


def test_paper_default_is_table_i(left_lung):
    # 'paper' is Table I with the paper's directions: the same model as the explicit constants
    d = paper_default()
    assert d.constants_for("left").tolist() == list(TABLE_I["left"])
    assert d.correction_for("left") is None and d.prior_for() is None
    a = build_lung(left_lung, "left", default="paper")
    b = build_lung(left_lung, "left", constants=TABLE_I["left"])
    assert np.array_equal(a.displacement, b.displacement)
    assert a.interior_map is None  # no prior: the sliding interior, as before


def test_shipped_default_is_learned_and_cited():
    # the shipped file: learned figures (not Table I), with its subjects and the data's citation
    d = shipped_default()
    assert d.name == "population"
    assert not np.allclose(d.constants_for("right"), TABLE_I["right"])
    assert np.array_equal(d.constants_for("left"), d.constants_for("right"))  # one set, lung frame
    assert d.interior_prior is not None and d.interior_prior.shape == (4, 3)
    prov = d.provenance
    assert "Castillo" in prov["citation"] and len(prov["subject_digests"]) >= 2
    assert resolve_default(None).digest == d.digest == resolve_default("population").digest


def test_round_trip_and_digest(tmp_path, rng):
    # save → read gives the same numbers (and so the same digest); a change changes the digest
    c = {"left": rng.uniform(0.1, 1, 9), "right": rng.uniform(0.1, 1, 9)}
    d = PopulationDefault("x", c, 1, rng.normal(size=(4, 3)), rng.normal(size=(4, 3)) * 1e-3, {"source": "test"})
    back = read_default(save_default(tmp_path / "d.json", d))
    assert back.digest == d.digest
    assert np.array_equal(back.direction_correction, d.direction_correction)
    assert replace(d, interior_prior=None).digest != d.digest


@pytest.mark.parametrize("change, what", [
    (lambda j: j.update(schema="other"), "not a lungdeform.population_default"),
    (lambda j: j["constants"].update(left=[1, 2]), "constants['left'] must be 9 finite"),
    (lambda j: j.update(interior_prior=[[1, 2, 3]]), "interior_prior must be a finite (4, 3)"),
    (lambda j: j.update(direction_degree=9), "direction_degree must be 0"),
])
def test_bad_file_names_file_and_field(tmp_path, change, what):
    # a malformed default is refused naming the file and what is wrong
    j = shipped_default().as_dict()
    change(j)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(j))
    with pytest.raises(ReadError) as err:
        read_default(p)
    assert str(p) in str(err.value) and what in str(err.value)


def test_resolve_refuses_unknown_name(tmp_path):
    with pytest.raises(InputError, match="constants must be one of population, paper"):
        resolve_default("tablei")


def test_left_is_the_mirror_of_right(right_lung):
    # the default lives in the lung frame: a right lung mirrored in x (a left lung) must move as the
    # mirror image of the right one, correction and prior included
    rng = np.random.default_rng(7)
    d = replace(shipped_default(), direction_degree=1, direction_correction=0.2 * rng.normal(size=(4, 3)))
    mirrored = Surface(right_lung.vertices * [-1, 1, 1], right_lung.faces[:, ::-1], "left")
    r = build_lung(right_lung, "right", default=d)
    left = build_lung(mirrored, "left", default=d)
    assert np.allclose(left.displacement, r.displacement * [-1, 1, 1], atol=1e-9)
    q = right_lung.vertices.mean(axis=0) + rng.normal(scale=10.0, size=(20, 3))
    assert np.allclose(left.interior.displacement(q * [-1, 1, 1]), r.interior.displacement(q) * [-1, 1, 1], atol=1e-9)


def test_prior_is_per_ml_and_learned_posture_only(left_lung):
    # the interior prior adds its affine motion per mL (unit_ml = 1) to the interior, and nothing to
    # the surface; another posture drops it (it was learned supine)
    d = shipped_default()
    with_prior = build_lung(left_lung, "left", default=d)
    without = build_lung(left_lung, "left", default=replace(d, interior_prior=None))
    assert np.array_equal(with_prior.displacement, without.displacement)
    q = left_lung.vertices.mean(axis=0)[None]
    expected = prior_displacement(d.interior_prior, q, *lung_normaliser(left_lung), "left")
    ext = build_lung(left_lung, "left", default=replace(d, interior_prior=np.zeros((4, 3))))
    assert np.allclose(with_prior.interior.displacement(q) - ext.interior.displacement(q), expected, atol=1e-9)
    assert build_lung(left_lung, "left", default=d, gravity="prone").interior_map is None


@pytest.mark.parametrize("side", ["left", "right"])
def test_the_interior_carries_the_surface_models_lung(side):
    # why: dvf, warp and track move tissue by the interior field, so the lung it carries (its image of
    # the lung's surface, p + s·v(p)) must be the surface model's lung (p + s·u): same volume within 2 %
    # of the volume change, inhaling and exhaling, and the same surface within a tenth of the motion.
    # Before the prior was tapered (schema 6) its contraction kept only 52–59 % of the change (POPI).
    # The prior must still act inside (truth: deeper than its taper it is the affine prior itself)
    from lungdeform.geometry.mesh import signed_volume
    from tests.conftest import ellipsoid_lung

    surface = ellipsoid_lung(side, 4)
    p, f = surface.vertices, surface.faces
    d = shipped_default()
    lung = build_lung(surface, side, default=d)
    ext = build_lung(surface, side, default=replace(d, interior_prior=np.zeros((4, 3)))).interior
    v0 = signed_volume(p, f)
    for dv in (-250.0, 250.0, 500.0):
        s = lung.scale_for(lung.volume_ee_ml + dv, exact=True)
        model = signed_volume(p + s * lung.displacement, f) - v0
        carried = signed_volume(p + s * lung.interior.displacement(p), f) - v0
        assert model == pytest.approx(dv * 1000.0, rel=1e-6)
        assert abs(carried - model) < 0.02 * abs(model), (dv, carried / model)
    gap = np.linalg.norm(lung.interior.displacement(p) - lung.displacement, axis=1)
    assert gap.max() < 0.1 * np.linalg.norm(lung.displacement, axis=1).max()
    centre = p.mean(axis=0)[None]
    prior = prior_displacement(d.interior_prior, centre, *lung_normaliser(surface), side)
    assert np.abs(prior).max() > 1e-3  # mm per mL: the prior is there, and acts in full at the centre
    np.testing.assert_allclose(lung.interior.displacement(centre) - ext.displacement(centre), prior, atol=1e-12)


def test_model_records_its_default(left_lung, right_lung):
    # a model file must say which default built it
    m = build_model({"left": left_lung, "right": right_lung}, default="paper")
    assert m.provenance["default"]["name"] == "paper"
    m = build_model({"left": left_lung, "right": right_lung})
    assert m.provenance["default"] == shipped_default().record()
