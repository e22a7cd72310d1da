"""lungdeform.playback.phases: phases numbered as 4-D CT numbers them, and where the scan lies among them."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.model.scan_state import parse_scan_state
from lungdeform.playback.phases import phase_schedule, scan_phase_text, scan_phases
from lungdeform.playback.schedule import VolumeTrace, plain_cycle


def test_phase_zero_is_end_inhale_and_fifty_percent_end_exhale_on_the_plain_cycle():
    # why: the cosine breath 250 (1 − cos 2πt/4) peaks at t = 2 s (500 mL) and is 0 at t = 0 and 4 s:
    # from its peak, phase i of 10 is at 2 + 0.4 i s (folded into the one-period trace), so phase 0
    # is 500 mL, phase 5 (50 %) 0 mL and phase i 250 (1 + cos(2π i/10)) mL, exactly
    s = phase_schedule(plain_cycle(), 10)
    i = np.arange(10)
    assert np.mod(s.t_s, 4.0) == pytest.approx((2.0 + 0.4 * i) % 4.0)  # t = 4 s is t = 0 s of the cycle
    assert s.delta_ml == pytest.approx(250 * (1 + np.cos(2 * np.pi * i / 10)), abs=1.5)  # linear between 30 Hz samples
    assert s.delta_ml[0] == pytest.approx(500.0) and s.delta_ml[5] == pytest.approx(0.0, abs=1e-9)
    assert [s.percent(k) for k in (0, 3, 5)] == [0, 30, 50]
    # the old numbering from the first sample, and end-exhale first: each a shift of the same cycle
    assert phase_schedule(plain_cycle(), 10, "start").delta_ml == pytest.approx(np.roll(s.delta_ml, 5))
    assert phase_schedule(plain_cycle(), 10, "end-exhale").delta_ml == pytest.approx(np.roll(s.delta_ml, 5))
    with pytest.raises(InputError, match="--phase-zero must be one of end-inhale, end-exhale, start"):
        phase_schedule(plain_cycle(), 10, "peak")


def test_a_long_curve_is_phased_from_its_first_peak_without_folding():
    # why: a 3-cycle breath of 5 s period starting at mid-volume (phase offset): phase 0 must be the
    # first maximum, and every phase a time within the curve after it (no folding of a long curve)
    t = np.linspace(0, 15, 1501)
    v = 300 * (1 - np.cos(2 * np.pi * (t + 1.0) / 5.0)) / 2
    s = phase_schedule(VolumeTrace(t, v, "three breaths"), 4)
    assert s.period_s == pytest.approx(5.0, rel=0.02)
    assert s.t0_s == pytest.approx(1.5, abs=0.011) and np.all(np.diff(s.t_s) > 0)
    assert s.delta_ml == pytest.approx([300, 150, 0, 150], abs=3.0)


@pytest.mark.parametrize("state, where", [
    ("end-inhale", [(0.0, "at its peak")]),
    ("end-exhale", [(50.0, "at its trough")]),
    ("mid", [(25.0, "exhaling"), (75.0, "inhaling")]),
])
def test_the_scan_is_found_where_the_breath_passes_its_volume(state, where):
    # why: on the cosine breath from its peak the volume is 250 (1 + cos 2πx) at fraction x of the
    # cycle: 500 mL (end-inhale) at 0 %, 0 mL (end-exhale) at 50 %, 250 mL (mid) at 25 % falling
    # and 75 % rising
    trace = plain_cycle()
    s = phase_schedule(trace, 10)
    got = scan_phases(trace, s, parse_scan_state(state, 500.0).above_ee_ml)
    assert [d for _, d in got] == [d for _, d in where]
    assert [p for p, _ in got] == pytest.approx([p for p, _ in where], abs=0.2)


def test_the_scans_phase_in_words():
    trace = plain_cycle()
    s = phase_schedule(trace, 10)
    assert "is at 0 % of the cycle (at its peak): phase 0 of 10 (0 %)" in scan_phase_text(
        trace, s, parse_scan_state("end-inhale", 500))
    assert "at 50 % of the cycle (at its trough): phase 5 of 10 (50 %)" in scan_phase_text(
        trace, s, parse_scan_state("end-exhale", 500))
    # a breath shallower than the scan's height never reaches it: said, not guessed
    text = scan_phase_text(plain_cycle(400.0), phase_schedule(plain_cycle(400.0), 10), parse_scan_state("end-inhale", 500))
    assert "lies outside this breath (0 to 400 mL above end-exhale): no phase is the scan" in text
