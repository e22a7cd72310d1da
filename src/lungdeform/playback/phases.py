"""The phases of one breathing cycle, numbered as 4-D CT scanners and DIR-Lab number them.

Phase ``i`` of ``N`` is the state at ``i/N`` of one period after phase 0 (phase binning). By default
phase 0 is **end-inhale** (the volume's maximum within the first period), so that 50 % is
end-exhale on a symmetric breath: the clinical convention (Siemens, GE, Philips and Varian 4-D CT,
the DIR-Lab and POPI data sets: T00 end-inhale, T50 end-exhale). ``zero="end-exhale"`` starts at the
minimum instead, ``zero="start"`` at the trace's first sample (lungdeform before 0.9). The period is
:func:`lungdeform.breathing.cycles.dominant_period`, or the whole trace when it holds less than two
periods or none is clear; phase 0 is sought within the first period, and a trace of at least two
periods holds the whole cycle after it; a shorter one is taken as one periodic cycle (times past its
end come round from its start).

Volumes are ``mL`` of both lungs above end-exhale (:class:`lungdeform.playback.schedule.VolumeTrace`);
times in s from the trace's first sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungdeform.breathing.cycles import dominant_period
from lungdeform.errors import InputError, LungdeformError

#: What phase 0 can be (``--phase-zero``): the clinical default first.
PHASE_ZEROS = ("end-inhale", "end-exhale", "start")
#: Help of ``--phase-zero`` (warp, dvf, track).
PHASE_ZERO_HELP = ("What phase 0 is: end-inhale (default: 0 % end-inhale, 50 % end-exhale, as 4-D CT scanners and "
                   "DIR-Lab number phases), end-exhale, or start (the curve's first sample, as before 0.9).")


@dataclass(frozen=True)
class PhaseSchedule:
    """``N`` phases of one cycle: ``t_s : (N,) float`` s (the trace's time of each phase), ``delta_ml :
    (N,) float`` mL above end-exhale, ``period_s`` s, ``zero`` what phase 0 is (:data:`PHASE_ZEROS`),
    ``t0_s`` its time."""

    t_s: np.ndarray
    delta_ml: np.ndarray
    period_s: float
    zero: str
    t0_s: float

    @property
    def count(self) -> int:
        return len(self.t_s)

    def percent(self, i: int) -> int:
        """Phase ``i``'s whole percentage of the cycle (the name of a DICOM phase folder)."""
        return round(100.0 * i / self.count)


def check_zero(zero: str) -> str:
    """``zero`` when it is one of :data:`PHASE_ZEROS`; :class:`InputError` naming ``--phase-zero`` otherwise."""
    if zero not in PHASE_ZEROS:
        raise InputError(f"--phase-zero must be one of {', '.join(PHASE_ZEROS)}, got {zero!r}")
    return zero


def cycle_period(trace) -> float:
    """The period (s) phases divide: the trace's dominant period, or its whole span when it holds
    less than two periods or has no clear one."""
    t = np.asarray(trace.t_s, float)
    span = float(t[-1] - t[0])
    try:
        period = float(dominant_period(t, trace.volume_ml))
    except LungdeformError:
        period = span
    return period if np.isfinite(period) and 0 < period <= span / 2 else span


def _folded(trace, times: np.ndarray, period: float) -> np.ndarray:
    """``times`` (s) past the trace's last sample brought back by one period (a trace of one cycle)."""
    end = float(trace.t_s[-1])
    return np.where(times > end + 1e-9 * max(period, 1.0), times - period, times)


def phase_schedule(trace, phases: int, zero: str = "end-inhale") -> PhaseSchedule:
    """``phases`` states evenly over one cycle of ``trace`` from phase 0 (module docstring)."""
    check_zero(zero)
    t = np.asarray(trace.t_s, float)
    v = np.asarray(trace.volume_ml, float)
    period = cycle_period(trace)
    first = t <= t[0] + period * (1 + 1e-9)
    if zero == "start":
        t0 = float(t[0])
    else:
        pick = np.argmax if zero == "end-inhale" else np.argmin
        t0 = float(t[first][pick(v[first])])
    times = _folded(trace, t0 + period * np.arange(int(phases)) / int(phases), period)
    return PhaseSchedule(times, trace.sample(times), period, zero, t0)


def scan_phases(trace, schedule: PhaseSchedule, above_ee_ml: float, tolerance_ml: float = 0.5) -> list[tuple[float, str]]:
    """Where in the cycle the breath passes the scan's volume ``above_ee_ml`` (mL above end-exhale):
    ``(percent of the cycle from phase 0, "inhaling" | "exhaling" | "at its peak" | "at its trough")``
    per passage, sorted, found on 2000 samples of the cycle taken as periodic (a run of samples within
    ``tolerance_ml`` counts once, at its middle, so an end-inhale scan is found at the peak it
    touches); empty when the breath never reaches it."""
    n = 2000
    frac = np.arange(n) / n
    g = trace.sample(_folded(trace, schedule.t0_s + schedule.period_s * frac, schedule.period_s)) - above_ee_ml
    near = np.abs(g) <= tolerance_ml
    if near.all():
        return [(0.0, "throughout")]
    order = (int(np.argmin(near)) + np.arange(n)) % n  # start on a sample away from the scan
    out: list[tuple[float, str]] = []
    k = 0
    while k < n:
        a = order[k]
        if near[a]:
            j = k
            while j + 1 < n and near[order[j + 1]]:
                j += 1
            out.append((100.0 * frac[order[(k + j) // 2]], _direction(g[order[k - 1]], g[order[(j + 1) % n]])))
            k = j + 1
            continue
        b = order[(k + 1) % n]
        if not near[b] and g[a] * g[b] < 0:
            x = frac[a] + ((frac[b] - frac[a]) % 1.0) * g[a] / (g[a] - g[b])
            out.append(((100.0 * x) % 100.0, "inhaling" if g[b] > g[a] else "exhaling"))
        k += 1
    return sorted(out)


def _direction(before: float, after: float) -> str:
    """Whether the breath rises or falls through a run of samples at the scan's volume, or turns there
    (``before``, ``after``: the volume less the scan's on either side of the run)."""
    if before < 0 and after < 0:
        return "at its peak"
    if before > 0 and after > 0:
        return "at its trough"
    return "inhaling" if after > before else "exhaling"


def scan_phase_text(trace, schedule: PhaseSchedule, scan) -> str:
    """One line saying which phase the model's scan (:class:`lungdeform.model.scan_state.ScanState`) is:
    ``the scan (end-inhale, 500 mL above end-exhale) is phase 0 of 10 (0 %)`` …"""
    passes = scan_phases(trace, schedule, scan.above_ee_ml)
    who = f"the scan ({scan.describe()})"
    if not passes:
        lo, hi = float(np.min(trace.volume_ml)), float(np.max(trace.volume_ml))
        return (f"{who} lies outside this breath ({lo:.0f} to {hi:.0f} mL above end-exhale): no phase is the scan; "
                "give the breath the scan was taken in (build --tidal-ml, or the curve's volumes)")
    n = schedule.count
    parts = []
    for pct, how in passes:
        i = round(pct / 100.0 * n) % n
        exact = abs(pct - 100.0 * i / n) < 0.5 or abs(pct - 100.0 * i / n) > 99.5
        parts.append(f"{pct:.0f} % of the cycle ({how}): {'' if exact else 'nearest '}phase {i} of {n} "
                     f"({schedule.percent(i)} %)")
    return f"{who} is at " + "; at ".join(parts) + f"; phase 0 is {schedule.zero if schedule.zero != 'start' else 'the first sample'}"
