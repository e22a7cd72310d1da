"""Presets: each breathes with the tidal volume, period and physiology it claims."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.breathing.presets import PRESET_NAMES, get_preset
from lungdeform.breathing.pv import simulate
from lungdeform.errors import InputError


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_preset_hits_its_tidal_volume_and_period(name):
    # truth: the preset's own target V_T, reproduced by the (independent) Radau integrator
    p = get_preset(name)
    curve = simulate(p.params, n_cycles=2, fs_hz=50.0)
    assert curve.tidal_volume_ml == pytest.approx(p.tidal_volume_ml, rel=0.01)
    # periodic: the second cycle repeats the first
    first = curve.t_s[curve.t_s < p.params.period_s]
    # (linear interpolation between 50 Hz samples: allow 0.2 % of V_T)
    assert np.allclose(curve.volume_at(first), curve.volume_at(first + p.params.period_s),
                       atol=0.002 * p.tidal_volume_ml)
    assert p.sources and all(isinstance(s, str) and s for s in p.sources)
    assert curve.pressure_cmH2O.max() > 0  # inspiration is driven by the muscles


def _air_trapping(name, cycles=8):
    p = get_preset(name).params
    rest = simulate(p, n_cycles=cycles, fs_hz=50.0, start="rest")
    last = rest.t_s >= rest.t_s[-1] - p.period_s
    return rest.volume_ml[last].min() - p.relaxation_ml


def test_copd_traps_air_normal_does_not():
    # physiology: τ = R/E = 1.5 s with T_e ≈ 2.1 s < 3τ leaves air behind each breath
    assert _air_trapping("copd") > 100.0
    assert abs(_air_trapping("normal")) < 10.0
    copd, normal = get_preset("copd").params, get_preset("normal").params
    assert copd.mechanics.time_constant_s > 3 * normal.mechanics.time_constant_s
    assert copd.insp_fraction < normal.insp_fraction  # long expiration


def test_disease_patterns_are_what_they_say():
    normal = get_preset("normal")
    restrictive = get_preset("restrictive")
    dysp = get_preset("dyspnoea")
    deep = get_preset("deep")
    ptx = get_preset("pneumothorax")
    assert restrictive.params.mechanics.elastance >= 2 * normal.params.mechanics.elastance
    assert restrictive.tidal_volume_ml < normal.tidal_volume_ml
    # rapid shallow breathing index f/V_T above 105 breaths/min/L (Yang & Tobin 1991)
    assert (60.0 / dysp.params.period_s) / (dysp.tidal_volume_ml / 1000.0) > 105.0
    assert (60.0 / normal.params.period_s) / (normal.tidal_volume_ml / 1000.0) < 105.0
    # vital-capacity manoeuvre: active expiration below the relaxation volume (expiratory reserve)
    vc = simulate(deep.params, n_cycles=1, fs_hz=25.0)
    assert vc.volume_ml.min() < deep.params.relaxation_ml - 500.0
    assert vc.tidal_volume_ml > 3000.0
    # the collapsed lung barely ventilates
    assert ptx.tidal_volume_ml < 0.2 * normal.tidal_volume_ml
    assert ptx.params.relaxation_ml < 0.25 * normal.params.relaxation_ml


def test_unknown_preset():
    with pytest.raises(InputError, match="unknown breathing preset 'asthma'; choose one of: normal"):
        get_preset("asthma")
    assert get_preset("COPD").name == "copd"
