"""Breathing-cycle detection on a surrogate trace: period, smoothing, turning points, cycle
anchors, and model-free diagnostics of the cycles found.

The signal is taken as it is: maxima = end-inhale (the readers in :mod:`lungdeform.breathing.trace` have
signed it inhalation-positive, with :func:`inspiratory_share` from here).

- :func:`dominant_period`: the breathing period from the autocorrelation; :func:`smooth`: the
  zero-phase low-pass; :func:`turning_points`: alternating maxima and minima above an excursion.
- :func:`cycle_anchors`: complete cycles, inspiration onset to onset, with the end-inhale peak of
  each — detected the same way for every format (the reading chosen is in its docstring), or taken
  from the RPM's recorded marks. Detection needs a uniform trace (:func:`lungdeform.breathing.trace.resample`).
- Diagnostics: :func:`cycle_flags` (irregular cycles), :func:`noise_level` (white measurement noise),
  :func:`mark_agreement` (recorded marks against the detected anchors).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Protocol

import numpy as np
from scipy.signal import butter, find_peaks, sosfiltfilt

from lungdeform.errors import InputError


class Trace(Protocol):
    """What cycle detection reads of a trace (:class:`lungdeform.breathing.trace.Trace` has it; this
    module cannot import that one, whose readers orient a trace with :func:`inspiratory_shares`)."""

    source: str
    t_s: np.ndarray
    amplitude: np.ndarray

    @property
    def n(self) -> int: ...

    @property
    def duration_s(self) -> float: ...

    @property
    def sample_interval_s(self) -> float: ...

    def mark_times(self, kind: str) -> np.ndarray: ...

#: Shortest cycle / longest cycle a breathing signal can have, s.
CYCLE_RANGE_S = (1.0, 20.0)


def _uniform(t_s, amplitude) -> tuple[np.ndarray, np.ndarray, float]:
    """The signal on a uniform grid at its median sample interval (linear interpolation).
    Returns (t (m,) s, a (m,), dt s)."""
    t = np.asarray(t_s, float)
    a = np.asarray(amplitude, float)
    dt = float(np.median(np.diff(t)))
    if np.allclose(np.diff(t), dt, rtol=1e-6, atol=1e-9):
        return t, a, dt
    tu = np.arange(t[0], t[-1] + 1e-9, dt)
    return tu, np.interp(tu, t, a), dt


def dominant_period(t_s, amplitude) -> float:
    """Breathing period (s) from the autocorrelation of a (near-)uniform signal.

    The signal is first high-passed at 1/CYCLE_RANGE_S[1] (zero phase), so that baseline drift does
    not dominate; the period is the first local maximum of the autocorrelation within CYCLE_RANGE_S
    that reaches half the highest one (the highest alone picks a multiple of the period on irregular
    traces), refined by a parabola through its three samples.
    """

    t, a, dt = _uniform(t_s, amplitude)
    n = a.size
    lo, hi = int(np.ceil(CYCLE_RANGE_S[0] / dt)), min(int(CYCLE_RANGE_S[1] / dt), n - 2)
    if hi <= lo + 1:
        raise InputError(f"trace of {t[-1] - t[0]:.1f} s is too short to hold one breathing cycle")
    wn = (1.0 / CYCLE_RANGE_S[1]) / (0.5 / dt)
    x = sosfiltfilt(_butter_sos(float(wn), "highpass"), a) if n > 12 else a - a.mean()
    x = x - x.mean()
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    if not ac[0] > 0:
        raise InputError("flat trace: no breathing motion")
    ac = ac / ac[0]
    _check_not_faster_than_breathing(ac, lo, dt)
    pk, _ = find_peaks(ac[: hi + 2])
    pk = pk[(pk >= lo) & (pk <= hi) & (ac[pk] > 0)]
    if pk.size == 0:  # no periodicity at all: fall back to the strongest lag
        k = lo + int(np.argmax(ac[lo:hi + 1]))
        return k * dt
    k = int(pk[np.argmax(ac[pk] >= 0.5 * ac[pk].max())])
    y0, y1, y2 = ac[k - 1], ac[k], ac[k + 1]
    den = y0 - 2.0 * y1 + y2
    return (k + (0.5 * (y0 - y2) / den if den < 0 else 0.0)) * dt


#: How far (of the autocorrelation at lag 0) the signal's autocorrelation must rise again, at a lag
#: shorter than the shortest breath, for the signal to be repeating faster than anyone breathes.
FAST_REPEAT_RISE = 0.5


def _check_not_faster_than_breathing(ac, lo: int, dt: float) -> None:
    """Refuse a signal (autocorrelation ``ac`` (n,), normalised to 1 at lag 0, sampled every ``dt`` s)
    that repeats faster than the shortest breath (``lo`` samples, :data:`CYCLE_RANGE_S`): its
    autocorrelation falls, rises again by :data:`FAST_REPEAT_RISE` and falls at a shorter lag. A breathing
    trace's autocorrelation only falls until half its period (0.5 s at the fastest); a 4 Hz
    oscillation (a tremor, a vibrating marker, a signal of another kind) would otherwise be read
    at a multiple of its own period, at least 1 s, as a breathing rhythm it does not have."""
    head = ac[: lo + 1]
    pk, _ = find_peaks(head)  # maxima inside: a breath of just over lo samples still rises at lag lo
    rise = head[pk] - np.minimum.accumulate(head)[pk]
    if pk.size and rise.max() >= FAST_REPEAT_RISE:
        lag = float(pk[int(np.argmax(rise >= FAST_REPEAT_RISE))] * dt)
        raise InputError(f"the signal repeats every {lag:.2g} s, faster than any breath (at least "
                         f"{CYCLE_RANGE_S[0]:g} s): not a breathing trace, or a vibration riding on one")


def smooth(amplitude, fs_hz: float, cutoff_hz: float = 1.0) -> np.ndarray:
    """Zero-phase low-pass (offline only): 2nd-order Butterworth, forward-backward."""

    wn = min(cutoff_hz / (0.5 * fs_hz), 0.99)
    return sosfiltfilt(_butter_sos(float(wn), "lowpass"), np.asarray(amplitude, float))


def _butter_sos(wn: float, btype: str) -> np.ndarray:
    """2nd-order Butterworth second-order sections at normalised cutoff ``wn`` (a copy of the cached
    design: designing costs more than filtering a trace, and the trace readers orient every trace with it)."""
    return _butter_design(wn, btype).copy()


@lru_cache(maxsize=512)
def _butter_design(wn: float, btype: str) -> np.ndarray:
    return butter(2, wn, btype, output="sos")


def turning_points(signal, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Alternating maxima and minima of ``signal`` (n,) whose every excursion is >= ``threshold``.

    Starts from all local extrema and repeatedly removes the adjacent max/min pair with the smallest
    excursion (a hysteresis / zig-zag filter), so a small wiggle on a breath never splits it while a
    real second breath of a double breath survives. Returns (indices (m,) int increasing,
    kinds (m,) int: +1 maximum, −1 minimum).
    """
    s = np.asarray(signal, float)
    d = np.sign(np.diff(s))
    nz = np.flatnonzero(d)
    if nz.size == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = d[nz[np.maximum(np.searchsorted(nz, np.arange(d.size), side="right") - 1, 0)]]  # carry over flats
    change = np.flatnonzero(np.diff(d) != 0) + 1
    tp = change.tolist()
    kind = [1 if d[i - 1] > 0 else -1 for i in tp]
    while len(tp) > 2:
        ex = np.abs(np.diff(s[tp]))
        j = int(np.argmin(ex))
        if ex[j] >= threshold:
            break
        if j == 0:
            del tp[0], kind[0]
        elif j + 1 == len(tp) - 1:
            del tp[-1], kind[-1]
        else:
            del tp[j: j + 2], kind[j: j + 2]
    return np.asarray(tp, int), np.asarray(kind, int)


def typical_excursion(signal, window: int) -> float:
    """Typical breath peak-to-peak: median of the range of ``signal`` over sliding windows of
    ``window`` samples (one period), step window/4. Robust to drift and to rare large events."""
    s = np.asarray(signal, float)
    w = int(np.clip(window, 2, s.size))
    v = np.lib.stride_tricks.sliding_window_view(s, w)[:: max(1, w // 4)]
    return float(np.median(v.max(axis=1) - v.min(axis=1)))


def _breaths(t, s, fine, period: float, onset_level: float, threshold: float = 0.3, excursion: float | None = None):
    """Breaths of a uniform signal: maxima found on the smoothed ``s`` (robust), then located on the
    less smoothed ``fine`` (accurate): each maximum within ±15 % of a period, and the inspiration
    onset before it, where ``fine`` last rises through ``onset_level`` of the excursion above the
    preceding minimum (linear interpolation). ``excursion``: the typical breath's (default that of
    ``s``, :func:`typical_excursion`). Returns (peak indices (m,) int into ``fine``, onset times
    (m−1,) s: onset j precedes peak j+1)."""
    dt = t[1] - t[0]
    if excursion is None:
        excursion = typical_excursion(s, int(round(period / dt)))
    tp, kind = turning_points(s, threshold * excursion)
    hw = max(1, int(round(0.15 * period / dt)))
    ipk = np.array([max(0, i - hw) + int(np.argmax(fine[max(0, i - hw): i + hw + 1])) for i in tp[kind == 1]],
                   dtype=int)
    if ipk.size:  # two maxima of a double breath may land on one sample of ``fine``: keep one
        ipk = ipk[ipk > np.maximum.accumulate(np.concatenate([[-1], ipk[:-1]]))]
    onsets = []
    for j in range(1, ipk.size):
        seg = fine[ipk[j - 1]: ipk[j] + 1]
        imin = int(np.argmin(seg))
        level = seg[imin] + onset_level * (seg[-1] - seg[imin])
        k = imin + int(np.flatnonzero(seg[imin:] <= level)[-1]) if seg[-1] > seg[imin] else imin
        k = min(k, seg.size - 2)
        x0, x1 = seg[k], seg[k + 1]
        frac = float(np.clip((level - x0) / (x1 - x0), 0.0, 1.0)) if x1 != x0 else 0.0
        onsets.append(t[ipk[j - 1] + k] + frac * dt)
    return ipk, np.asarray(onsets)


#: The fine signal that locates onsets and peaks is low-passed at this multiple of the detection cutoff.
FINE_FACTOR = 2.0


def _smoothed(a, period: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(detection signal, fine signal) of a uniform amplitude (see :func:`cycle_anchors`)."""
    cut = _smoothing_cutoff(period, fs)
    return smooth(a, fs, cut), smooth(a, fs, min(FINE_FACTOR * cut, 0.45 * fs))


def _smoothing_cutoff(period: float, fs: float) -> float:
    """Low-pass cutoff (Hz) for cycle detection: 2.5 harmonics of the breathing rate, in [0.3, 1] Hz."""
    return float(min(np.clip(2.5 / period, 0.3, 1.0), 0.45 * fs))


def inspiratory_share(t_s, amplitude, onset_level: float = 0.05) -> tuple[float, int]:
    """Median over breaths of (t_peak − t_onset)/(t_peak − t_previous peak): the share of each breath
    from the end of the end-exhale dwell to end-inhale, with the signal taken as it is (maxima =
    end-inhale). Returns (share, number of breaths); (nan, n) with fewer than 3 breaths."""
    t, s, fine, period = _detection_signals(t_s, amplitude)
    return _share(t, s, fine, period, onset_level)


def inspiratory_shares(t_s, amplitude, onset_level: float = 0.05) -> tuple[float, float, int]:
    """:func:`inspiratory_share` of the trace as recorded and negated, ``(share, negated share,
    breaths as recorded)``: the period and the (linear) low-passes do not depend on the sign, so
    they are computed once. The phase with the smaller share is inspiration."""
    t, s, fine, period = _detection_signals(t_s, amplitude)
    keep, n = _share(t, s, fine, period, onset_level)
    flip, _ = _share(t, -s, -fine, period, onset_level)
    return keep, flip, n


def _detection_signals(t_s, amplitude):
    """``(t, detection signal, fine signal, period s)`` on the trace's uniform grid (:func:`_smoothed`)."""
    t, a, dt = _uniform(t_s, amplitude)
    period = dominant_period(t, a)
    return (t, *_smoothed(a, period, 1.0 / dt), period)


def _share(t, s, fine, period: float, onset_level: float) -> tuple[float, int]:
    """:func:`inspiratory_share` from the detection and fine signals (see :func:`_breaths`)."""
    ipk, onsets = _breaths(t, s, fine, period, onset_level)
    if onsets.size < 3:
        return float("nan"), int(onsets.size)
    tpk = t[ipk]
    share = (tpk[1:] - onsets) / np.diff(tpk)
    return float(np.median(share)), int(share.size)

@dataclass(frozen=True)
class Detector:
    """What :func:`cycle_anchors` learns of a trace before it splits it: ``period_s`` (s, the
    :func:`dominant_period`) and ``excursion`` (trace unit, the :func:`typical_excursion` of the
    detection signal). :func:`detector_of` measures them on one trace (a training part) so that
    another part is split with them, without its own period or excursion."""

    period_s: float
    excursion: float


def detector_of(trace: Trace) -> Detector:
    """The :class:`Detector` of a uniform trace (InputError when it holds no breathing period)."""
    t, a = trace.t_s, trace.amplitude
    try:
        period = dominant_period(t, a)
    except InputError as exc:
        raise InputError(f"{trace.source}: {exc}") from None
    s, _ = _smoothed(a, period, 1.0 / trace.sample_interval_s)
    return Detector(period, typical_excursion(s, int(round(period / (t[1] - t[0])))))


@dataclass(frozen=True)
class CycleAnchors:
    """Timing of complete breathing cycles.

    starts_s : (k+1,) float, s: inspiration onsets (end of the end-exhale dwell); cycle c runs
    starts_s[c]..starts_s[c+1]. peaks_s : (k,) float, s: end-inhale time inside each cycle.
    source : where they came from.
    """

    starts_s: np.ndarray
    peaks_s: np.ndarray
    source: str

    @property
    def n_cycles(self) -> int:
        return int(self.peaks_s.size)

    def subset(self, first: int, last: int) -> "CycleAnchors":
        """Cycles first..last-1."""
        return CycleAnchors(self.starts_s[first: last + 1], self.peaks_s[first:last], self.source)


def cycle_anchors(trace: Trace, use_marks: bool = False, onset_level: float = 0.05,
                  detector: Detector | None = None) -> CycleAnchors:
    """Split a uniform, inhalation-positive trace into complete cycles: inspiration onsets and
    end-inhale peaks.

    Detected (the default; the same for every format): the breaths are found on the signal
    low-passed at 2.5 harmonics of the :func:`dominant_period` (zero phase, 0.3–1 Hz): its end-inhale
    maxima are the maxima of :func:`turning_points` with a threshold of 30 % of the
    :func:`typical_excursion` (a typical breath, not the whole range: drift and large non-breathing
    events neither hide breaths nor add false ones). They are then located on the signal low-passed
    at ``FINE_FACTOR`` (2) times that cutoff, which keeps the timing of an asymmetric peak (on a
    rise-35 %/fall-65 % test breath: 0.06 s from the true peak instead of 0.14 s): each peak within
    ±15 % of a period, refined to sub-sample precision by a parabola through three samples; between
    two peaks the onset of inspiration is where the signal last rises through ``onset_level`` of
    that excursion above the minimum (linear interpolation) — robust to the variable end-expiratory
    pause, where a minimum would be arbitrary.

    ``use_marks`` with recorded RPM marks (>= 2 'Z'): the cycles are the 'Z' (end-exhale) marks and
    each peak the 'P' mark inside the cycle (the maximum where none). The RPM marks are placed at the
    amplitude extremes (so a cycle then starts at the start of the dwell, not at the onset), and
    they can be wrong (see :func:`mark_agreement`).
    ``detector`` (:func:`detector_of` of another part of the recording, e.g. its training part):
    the period and the typical excursion used instead of this trace's own.
    Raises InputError if the trace holds no complete cycle.
    """
    t, a = trace.t_s, trace.amplitude
    if trace.n < 8 or trace.duration_s < 2 * CYCLE_RANGE_S[0]:
        raise InputError(f"{trace.source}: trace of {trace.duration_s:.1f} s is too short to hold one "
                         "breathing cycle")
    fs = 1.0 / trace.sample_interval_s
    z = trace.mark_times("Z") if use_marks else np.array([])
    if z.size >= 2:
        z = np.unique(z)
        pm = trace.mark_times("P")
        peaks = []
        for c in range(z.size - 1):
            inside = pm[(pm > z[c]) & (pm < z[c + 1])]
            if inside.size:
                peaks.append(inside[0])
            else:
                sel = (t >= z[c]) & (t < z[c + 1])
                peaks.append(t[sel][np.argmax(a[sel])])
        return CycleAnchors(z, np.asarray(peaks), "recorded Z/P marks")
    if not np.allclose(np.diff(t), 1.0 / fs, rtol=1e-3):
        raise InputError(f"{trace.source}: cycle detection needs a uniform trace: resample() it first")
    det = detector if detector is not None else detector_of(trace)
    period = det.period_s
    if period * 1.5 > trace.duration_s:
        raise InputError(f"{trace.source}: trace of {trace.duration_s:.1f} s is too short to hold one "
                         f"breathing cycle (period ≈ {period:.1f} s)")
    s, fine = _smoothed(a, period, fs)
    ipk, onsets = _breaths(t, s, fine, period, onset_level, excursion=det.excursion)
    if onsets.size < 2:
        raise InputError(f"{trace.source}: fewer than 2 inspiration onsets found: the trace holds no "
                         "complete breathing cycle")
    peaks = []
    for i in ipk[1: onsets.size]:
        y0, y1, y2 = fine[max(i - 1, 0)], fine[i], fine[min(i + 1, fine.size - 1)]
        den = y0 - 2.0 * y1 + y2
        peaks.append(t[i] + (0.5 * (y0 - y2) / den / fs if den < 0 else 0.0))
    peaks = np.asarray(peaks)
    ok = (peaks > onsets[:-1]) & (peaks < onsets[1:])
    if not np.all(ok):
        raise InputError(f"{trace.source}: inconsistent cycle detection (a peak outside its cycle)")
    return CycleAnchors(onsets, peaks, "detected onsets and peaks")


# --------------------------------------------------------------------------- diagnostics
#: Bounds of a regular cycle relative to the trace's median (duration, peak-to-peak).
REGULAR_DURATION = (2.0 / 3.0, 1.5)
REGULAR_AMPLITUDE = (0.5, 2.0)


def cycle_flags(trace: Trace, anchors: CycleAnchors, cutoff_hz: float = 1.0,
                second_peak: float = 0.25) -> list[tuple[str, ...]]:
    """Model-free irregularity flags of each cycle (signal and timing only; no model is involved).

    On the trace low-passed at ``cutoff_hz`` (uniform trace): 'duration' (outside REGULAR_DURATION ×
    the median cycle), 'amplitude' (peak minus the lower end-exhale level outside REGULAR_AMPLITUDE ×
    the median), 'baseline step' (end-exhale levels at the two ends differ by more than half the
    cycle's excursion) and 'multi-peak' (a second maximum inside the cycle with a prominence above
    ``second_peak`` × the excursion: double breath, sigh, cough, speech). Returns one tuple per cycle
    (empty = regular).
    """

    t = trace.t_s
    s = smooth(trace.amplitude, 1.0 / trace.sample_interval_s, cutoff_hz)
    st, pk = anchors.starts_s, anchors.peaks_s
    dur = np.diff(st)
    lv0, lv1, lp = np.interp(st[:-1], t, s), np.interp(st[1:], t, s), np.interp(pk, t, s)
    exc = lp - np.minimum(lv0, lv1)
    med_d, med_a = np.median(dur), np.median(exc)
    out = []
    for c in range(dur.size):
        f = []
        if not REGULAR_DURATION[0] <= dur[c] / med_d <= REGULAR_DURATION[1]:
            f.append("duration")
        if not (med_a > 0 and REGULAR_AMPLITUDE[0] <= exc[c] / med_a <= REGULAR_AMPLITUDE[1]):
            f.append("amplitude")
        if abs(lv1[c] - lv0[c]) > 0.5 * max(exc[c], 0.0):
            f.append("baseline step")
        seg = s[(t >= st[c]) & (t <= st[c + 1])]
        if seg.size > 2 and exc[c] > 0 and find_peaks(seg, prominence=second_peak * exc[c])[0].size > 1:
            f.append("multi-peak")
        out.append(tuple(f))
    return out


def noise_level(trace: Trace, band: float = 0.6) -> float:
    """White measurement noise σ (trace unit) of a uniform trace, from its spectrum above ``band`` ×
    the Nyquist frequency (3–5 Hz at 10 Hz, 7.5–12.5 Hz at 25 Hz), where breathing has no power left:
    a Hann-windowed periodogram there is flat at σ²·Σw² for white noise, and its median (robust to
    spectral lines) is ln 2 times that level."""
    a = np.asarray(trace.amplitude, float)
    if a.size < 32:
        raise InputError(f"{trace.source}: too few samples ({a.size}) to estimate the noise")
    w = np.hanning(a.size)
    x = np.fft.rfft((a - a.mean()) * w)
    f = np.arange(x.size) / a.size  # cycles per sample; Nyquist = 0.5
    p = np.abs(x[f >= 0.5 * band]) ** 2
    return float(np.sqrt(np.median(p) / np.log(2.0) / np.sum(w * w)))


def mark_agreement(trace: Trace, anchors: CycleAnchors, tolerance_s: float = 0.5) -> dict | None:
    """How the recorded marks agree with the detected anchors: for 'P' (end-inhale) marks the offset to
    the nearest detected peak, for 'Z' (end-exhale) marks to the nearest detected onset (the RPM puts
    'Z' at the amplitude extreme, inside the end-exhale dwell, so an offset of up to the dwell is
    expected). Returns None when the trace holds no marks, else per kind: n, median |offset| s,
    share within ``tolerance_s``, and the largest |offset| s."""
    out = {}
    for kind, ref in (("P", anchors.peaks_s), ("Z", anchors.starts_s)):
        m = trace.mark_times(kind)
        if m.size == 0 or ref.size == 0:
            continue
        d = np.abs(ref[np.argmin(np.abs(ref[None, :] - m[:, None]), axis=1)] - m)
        out[kind] = {"n": int(m.size), "median_abs_offset_s": float(np.median(d)),
                     f"within_{tolerance_s:g}_s": float(np.mean(d <= tolerance_s)),
                     "max_abs_offset_s": float(d.max())}
    return out or None
