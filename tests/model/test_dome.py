"""A lung whose dome moves as told (model.dome): the split meets both conditions exactly, refuses what a
volume cannot produce, and a build without it is unchanged."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.dome import dome_weights
from lungdeform.geometry.mesh import Surface, icosphere, signed_volume
from lungdeform.model.displacement import volume_polynomial
from lungdeform.model.dome import ACCEPT_MM, BREATHING, TOLERANCE_MM, DomeRequest, dome_split, stretch_mode
from lungdeform.model.lung import BuildSettings, build_lung, build_model

A, B, H, D, T = 60.0, 80.0, 120.0, 60.0, 20.0


def _lung(subdivisions=4):
    # the analytic lung of tests/geometry/test_dome.py: a cap over an ellipse and a domed floor
    s = icosphere(subdivisions, 1.0)
    x, y, z = s.vertices.T
    r = np.sqrt(np.clip(1.0 - x ** 2 - y ** 2, 0.0, 1.0))
    return Surface(np.c_[A * x, B * y, np.where(z >= 0, H * r, D * r ** 2 - T * r)], s.faces, "lung")


def _isotropic(surface, delta_ml):
    # a stand-in default: scaling about the centroid, to exactly +delta_ml (volume of a scaled solid: s³·V)
    s = ((surface.volume_ml + delta_ml) / surface.volume_ml) ** (1.0 / 3.0)
    c = surface.vertices.mean(axis=0)
    return (surface.vertices - c) * (s - 1.0)


def _excursion(surface, u):
    return dome_weights(surface.vertices + u, surface.faces).height_mm - dome_weights(surface.vertices,
                                                                                      surface.faces).height_mm


@pytest.mark.parametrize("asked", [0.0, 3.0, 9.0, 14.0])
def test_the_split_meets_the_volume_and_the_excursion(asked):
    # both conditions of the split, measured independently: the enclosed volume of p + u (divergence theorem)
    # is V + ΔV to rounding, and the dome, measured on p + u as on a mask, descends what was asked
    lung, delta = _lung(), 250.0
    split = dome_split(lung.vertices, lung.faces, _isotropic(lung, delta), asked, delta)
    moved = lung.vertices + split.displacement
    assert signed_volume(moved, lung.faces) / 1000.0 == pytest.approx(lung.volume_ml + delta, rel=1e-9)
    assert _excursion(lung, split.displacement) == pytest.approx(asked, abs=TOLERANCE_MM)
    assert split.excursion_mm == pytest.approx(_excursion(lung, split.displacement), abs=1e-9)


def test_the_default_own_excursion_keeps_the_default():
    # asked for the excursion the default already gives, the split is the default itself: no stretch
    lung, delta = _lung(), 250.0
    u = _isotropic(lung, delta)
    own = _excursion(lung, u)
    split = dome_split(lung.vertices, lung.faces, u, own, delta)
    assert split.default_excursion_mm == pytest.approx(own, abs=1e-9)
    assert split.weights[0] == pytest.approx(1.0, abs=1e-3) and abs(split.weights[1]) < 0.05
    assert np.abs(split.displacement - u).max() < 0.05


def test_the_stretch_is_volume_neutral_and_leaves_the_apex():
    # the stretch is divergence-free (no volume change at first order: the cubic's linear term is a tiny
    # share of the volume a piston of the same depth would move), its lowest point descends 1 mm per unit
    # and its apex not at all
    lung = _lung(5)
    s = stretch_mode(lung.vertices, lung.faces)
    a = volume_polynomial(lung.vertices, lung.faces, s)
    piston = dome_weights(lung.vertices, lung.faces).footprint_mm2  # mm³ per mm of a floor moved down
    assert abs(a[1]) < 0.01 * piston
    top, bottom = np.argmax(lung.vertices[:, 2]), np.argmin(lung.vertices[:, 2])
    assert np.allclose(s[top], 0.0) and s[bottom, 2] == pytest.approx(-1.0)


def test_what_the_volume_cannot_produce_is_refused():
    # seen from the apex, a floor descending E over the footprint F sweeps E·F: beyond ΔV the rest of the lung
    # would shrink. Refused with the most this volume allows; just below it the split is made
    lung, delta = _lung(), 250.0
    u = _isotropic(lung, delta)
    most = delta * 1000.0 / dome_weights(lung.vertices, lung.faces).footprint_mm2
    with pytest.raises(InputError, match=rf"cannot come with \+250 mL: .* at most {most:.1f} mm"):
        dome_split(lung.vertices, lung.faces, u, 1.01 * most, delta)
    assert dome_split(lung.vertices, lung.faces, u, 0.99 * most, delta).excursion_mm == pytest.approx(0.99 * most,
                                                                                                      abs=TOLERANCE_MM)
    for bad in (-1.0, float("nan"), float("inf"), 1e4):
        with pytest.raises(InputError, match="dome excursion must be"):
            dome_split(lung.vertices, lung.faces, u, bad, delta)


def test_breathing_shorthand_and_sides():
    # --breathing: the floor sweeps a share κ of each lung's volume change, E = κ·ΔV/F (F its footprint);
    # --dome-mm per side or for both
    lung = _lung()
    footprint = dome_weights(lung.vertices, lung.faces).footprint_mm2
    per = DomeRequest.breathing("mixed").per_lung({"left": lung}, {"left": 200.0})
    assert per["left"] == pytest.approx(BREATHING["mixed"] * 200.0 * 1000.0 / footprint, rel=1e-12)
    assert DomeRequest(mm={"both": 7.0}).per_lung({"right": lung}, {"right": 300.0}) == {"right": 7.0}
    with pytest.raises(InputError, match="no dome excursion given for the left lung"):
        DomeRequest(mm={"right": 7.0}).per_lung({"left": lung, "right": lung}, {"left": 1.0, "right": 1.0})
    with pytest.raises(InputError, match="breathing must be one of chest, mixed, belly"):
        DomeRequest.breathing("deep")
    assert 0 < BREATHING["chest"] < BREATHING["mixed"] < BREATHING["belly"] < 1  # each producible (κ < 1)


def test_build_with_a_dome_and_without():
    # the built lung: calibrated exactly (its volume cubic at the calibration volume), its dome where it was
    # told; a model built without a request has no "dome" in its provenance and the same displacement as a
    # lung built before this option existed (the default's own)
    from lungdeform.data import default_lungs

    lungs = default_lungs()
    plain = build_model(lungs)
    assert "dome" not in plain.provenance
    ref = build_lung(lungs["left"], "left", settings=BuildSettings(calibration_ml=plain.lungs["left"].calibration_ml))
    assert np.array_equal(plain.lungs["left"].displacement, ref.displacement)
    chest, belly = (build_model(lungs, dome=DomeRequest.breathing(b)) for b in ("chest", "belly"))
    for model, name in ((chest, "chest"), (belly, "belly")):
        rec = model.provenance["dome"]
        for side, lung in model.lungs.items():
            units = lung.calibration_ml / lung.unit_ml
            got = np.polyval(lung.volume_poly[::-1], units) - lung.volume_poly[0]
            assert got / 1000.0 == pytest.approx(lung.calibration_ml, rel=1e-9)
            footprint = dome_weights(lung.surface.vertices, lung.surface.faces).footprint_mm2
            assert rec["asked_mm"][side] == pytest.approx(BREATHING[name] * lung.calibration_ml * 1000 / footprint,
                                                          abs=1e-3)
            assert rec["measured_mm"][side] == pytest.approx(rec["asked_mm"][side], abs=ACCEPT_MM + 1e-3)
    # the diaphragm does more of a belly breath: its base descends further, its front moves less
    for side in ("left", "right"):
        sc = chest.lungs[side].displacement * chest.lungs[side].calibration_ml
        sb = belly.lungs[side].displacement * belly.lungs[side].calibration_ml
        assert -sb[:, 2].min() > -sc[:, 2].min()
        assert np.abs(sb[:, 1]).mean() <= np.abs(sc[:, 1]).mean() + 1e-9
