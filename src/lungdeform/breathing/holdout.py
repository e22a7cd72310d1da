"""Held-out evaluation of breathing models on a real surrogate trace.

Protocol (one trace):

1. Split in time: the training part is the first ``train_fraction`` of the recording's duration, the
   held-out part the rest. **Nothing computed from a held-out sample feeds a fit**: the signal itself
   (a marker's principal axis and centre, :func:`lungdeform.breathing.trace.principal_motion`; the
   inhalation-positive sign, :func:`lungdeform.breathing.trace.inhale_sign`), the sampling rate, the
   cycle detector's period and typical excursion (:func:`lungdeform.breathing.cycles.detector_of`)
   and the amplitude → volume calibration are all taken from the training part
   (:func:`training_signal`, :func:`split`). ``tests/breathing/test_holdout.py`` corrupts every
   held-out sample, cycle detection included, and checks that every fitted number is unchanged.
2. Resample to a uniform grid; the training part's grid samples are those at or before its last
   recorded sample. Split into cycles at the detected inspiration onsets with the detected
   end-inhale peaks (:func:`lungdeform.breathing.cycles.cycle_anchors`, the same detector for every
   format, with the training part's period and excursion for both parts; the RPM's own marks are
   compared with it, not used: in the real .vxp file one in five is off by more than 0.5 s).
   Training cycles: the complete cycles detected in the training part alone. Held out: the cycles
   detected from the last training onset to the end that start after the training part (a training
   sample may time the first held-out onset; a cycle across the split is in neither).
3. Calibrate amplitude to volume linearly: the median peak-to-peak of the *training* cycles maps to
   the given tidal volume (default 500 mL), their median end-exhale level to ``relaxation_ml``.
   Every shape parameter is fitted on the training cycles only (PV driver: τ = R/E, I/E, the
   drive-to-peak lag δ, κ and the five a_k; Lujan: n, φ; Fourier: the K = 2 mean-cycle coefficients).
4. What each held-out cycle is given — the same for the three shared-shape models, because one
   function calibrates all three shapes:

   - its timing: the two inspiration onsets around it and its end-inhale time (what an RPM's
     marks or a causal onset/peak detector give a user);
   - **shared_shape** (the headline): a per-cycle least-squares gain, offset and, with ``drift``
     (default), a linear baseline drift across the cycle — 3 numbers fitted to that cycle's own
     samples, like a per-cycle amplitude calibration of an external surrogate;
   - **shared_shape_no_drift**: gain and offset only (2 numbers; the protocol before drift);
   - **anchored** (strict): no held-out sample is used but the levels of the 1-Hz low-passed volume
     (of the held-out part) at the three anchors (onset, peak, next onset): gain, offset and drift
     solve those 3 points exactly. Only information at the cycle boundaries a user would have.

   Plus, **not held out**, the per-cycle refit (``per_cycle_refit_insample``): each held-out cycle
   fitted on its own (PV: the five a_k with the training mechanics; Lujan: n, φ, c0, b; Fourier K =
   2: five coefficients). This is an in-sample fit of unseen cycles — a measure of expressiveness,
   not of prediction; ``fourier_insample_rms_percent`` is its Fourier figure (the "per-cycle Fourier
   fit" of ``lungdeform validate breathing``, until 0.8 named ``fourier_rms_percent``).

The error is the RMS over all held-out samples as a percentage of the median per-cycle peak-to-peak
of the held-out cycles (``of="cycle"``; the breath amplitude — smaller than the whole trace's range
when the baseline drifts or when non-breathing events occur, so a stricter figure); the same RMS as
a % of the held-out trace's whole range is reported alongside (``percent_of_trace_range``). Also
reported, to explain the figures, never used by any fit: the white-noise floor of the held-out part
(% of the breath amplitude), the score on held-out cycles that model-free flags call regular
(:func:`lungdeform.breathing.cycles.cycle_flags` over the held-out cycles; same denominator), and the
agreement of recorded marks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lungdeform.breathing import curve_models as rb
from lungdeform.breathing import inversion as inv
from lungdeform.errors import InputError
from lungdeform.progress import Progress

from .cycles import CycleAnchors, cycle_anchors, cycle_flags, detector_of, mark_agreement, noise_level, smooth
from .trace import Trace, inhale_sign, negated, principal_motion, resample

MODELS = ("model", "lujan", "fourier")
#: Low-pass (Hz) for the anchor levels of the "anchored" calibration.
ANCHOR_LEVEL_CUTOFF_HZ = 1.0


@dataclass(frozen=True)
class HoldoutSettings:
    """How :func:`evaluate` fits: ``fs_hz`` the resampling rate (None: the trace's own); ``elastance``
    cmH2O/L of the PV fit; ``use_marks`` takes the cycles from recorded RPM marks instead of the
    detector; ``drift``: the headline calibration includes a per-cycle linear drift (the fits then
    allow it too)."""

    fs_hz: float | None = None
    elastance: float = 10.0
    use_marks: bool = False
    drift: bool = True


@dataclass(frozen=True)
class _Samples:
    """One side of the split: times ``t_s (n,)`` s, volumes ``volume_ml (n,)`` mL, and their cycles."""

    t_s: np.ndarray
    volume_ml: np.ndarray
    anchors: CycleAnchors


def rms_percent(model, values, cycle_starts_s, t_s, of: str = "cycle", keep=None) -> float:
    """RMS(model − values) over samples where the model is defined, as % of the median cycle
    peak-to-peak (``of="cycle"``, the headline) or of the scored trace's whole peak-to-peak range
    (``of="trace"``). ``keep`` : (k,) bool, score only those cycles (the denominator still uses all)."""
    idx, _ = rb.cycle_phase(t_s, cycle_starts_s)
    ok = (idx >= 0) & np.isfinite(model)
    if not ok.any():
        raise InputError("no samples to score")
    if of == "trace":
        p2p = np.ptp(values[ok])
    else:
        p2p = np.median([np.ptp(values[idx == c]) for c in np.unique(idx[ok])])
    if keep is not None:
        ok &= np.asarray(keep, bool)[np.clip(idx, 0, None)]
        if not ok.any():
            return float("nan")
    return float(np.sqrt(np.mean((model[ok] - values[ok]) ** 2)) / p2p * 100.0)


def calibrate(trace: Trace, cycle_starts_s, tidal_volume_ml: float = 500.0, relaxation_ml: float = 2400.0):
    """Linear amplitude -> volume (mL) map fixed on the given cycles. Returns (volume (n,), gain, offset)."""
    if not (np.isfinite(tidal_volume_ml) and tidal_volume_ml > 0):
        raise InputError(f"tidal_volume_ml must be > 0, got {tidal_volume_ml!r}")
    idx, _ = rb.cycle_phase(trace.t_s, cycle_starts_s)
    cycles = np.unique(idx[idx >= 0])
    a = trace.amplitude
    p2p = np.median([np.ptp(a[idx == c]) for c in cycles])
    if not p2p > 0:
        raise InputError(f"{trace.source}: the trace does not move (peak-to-peak 0)")
    ee = np.median([a[idx == c].min() for c in cycles])
    gain = tidal_volume_ml / p2p
    return relaxation_ml + gain * (a - ee), gain, relaxation_ml - gain * ee


# --------------------------------------------------------------------------- per-cycle calibration
def calibrate_lsq(shape, t_s, values, cycle_starts_s, drift: bool = True) -> np.ndarray:
    """Each cycle's least-squares gain, offset (and linear drift in the cycle fraction) of ``shape``
    (n,) to ``values`` (n,). Returns the calibrated model (n,), NaN outside the cycles."""
    idx, frac = rb.cycle_phase(t_s, cycle_starts_s)
    return rb.calibrated(idx, shape, values, frac, drift)


def calibrate_anchored(shape_fn, t_s, anchors: CycleAnchors, level_fn) -> np.ndarray:
    """Each cycle's gain, offset and drift solved exactly from three points: the model shape and the
    measured level at the onset, the peak and the next onset. ``shape_fn(times) -> (m,)`` shape;
    ``level_fn(times) -> (m,)`` measured levels. No other sample of the cycle is used."""
    st, pk = anchors.starts_s, anchors.peaks_s
    k = pk.size
    span = np.diff(st)
    eps = 1e-6 * span
    ta = np.concatenate([st[:-1] + eps, pk, st[1:] - eps])
    sa, la = shape_fn(ta), level_fn(ta)
    idx, frac = rb.cycle_phase(t_s, st)
    shape = shape_fn(t_s)
    out = np.full(np.shape(t_s), np.nan)
    pk_frac = (pk - st[:-1]) / span
    for c in range(k):
        A = np.array([[sa[c], 1.0, -0.5], [sa[k + c], 1.0, pk_frac[c] - 0.5], [sa[2 * k + c], 1.0, 0.5]])
        coef = np.linalg.lstsq(A, la[[c, k + c, 2 * k + c]], rcond=None)[0]
        sel = idx == c
        out[sel] = inv.calibration_design(shape[sel], frac[sel], True) @ coef
    return out


# --------------------------------------------------------------------------- fits
def fit_shapes(t_s, volume_ml, train: CycleAnchors, elastance: float, drift: bool) -> dict:
    """Fit the three shared shapes on the training cycles only. Returns {"pv": BreathingFit,
    "lujan": LujanFit, "fourier": (4,) coefficients, "peak_phase": float}."""
    ph = rb.median_peak_phase(train.starts_s, train.peaks_s)
    pv = inv.invert(t_s, volume_ml, train.starts_s, peaks_s=train.peaks_s,
                    settings=inv.InversionSettings(elastance=elastance, per_cycle_calibration=True, drift=drift))
    lj = rb.fit_lujan(t_s, volume_ml, train.starts_s, peaks_s=train.peaks_s, peak_phase=ph, drift=drift)
    fo = rb.fit_fourier_shape(t_s, volume_ml, train.starts_s, peaks_s=train.peaks_s, peak_phase=ph, drift=drift)
    return {"pv": pv, "lujan": lj, "fourier": fo, "peak_phase": ph}


def shape_functions(fits: dict, cycles: CycleAnchors) -> dict:
    """Uncalibrated shape of each fitted model on the given cycles: name -> f(times (m,)) -> (m,)."""
    st, pk, ph = cycles.starts_s, cycles.peaks_s, fits["peak_phase"]
    lj, fo = fits["lujan"], np.asarray(fits["fourier"])

    def warped(x):
        return rb.cycle_phase(x, st, pk, ph)[1]

    return {
        "model": lambda x: inv.predict_cycles(fits["pv"], x, st, peaks_s=pk, calibrate=False),
        "lujan": lambda x: rb.lujan_shape(warped(x), lj.n, lj.phi),
        "fourier": lambda x: rb.fourier_design(warped(x), fo.size // 2)[:, 1:] @ fo,
    }


# --------------------------------------------------------------------------- the split
def split_time(trace: Trace, train_fraction: float) -> float:
    """The time (s) that ends the training part: the first ``train_fraction`` of the duration."""
    if not (0.0 < train_fraction < 1.0):
        raise InputError(f"train_fraction must lie in (0, 1), got {train_fraction!r}")
    return float(trace.t_s[0] + train_fraction * trace.duration_s)


def training_signal(trace: Trace, t_split_s: float) -> Trace:
    """``trace`` with its amplitude defined by the samples before ``t_split_s`` only (step 1): a
    marker trace (with ``positions``) projected on the principal axis of its training positions,
    and every trace signed inhalation-positive by the rule of
    :func:`lungdeform.breathing.trace.orient_inhale_positive` applied to the training samples (marks
    swapped with the sign). A sign opposite to the one the reader chose on the whole trace is noted
    in ``fixes``."""
    fit = trace.t_s < t_split_s
    out = trace
    if trace.positions is not None and np.all(np.isfinite(trace.positions)):
        out = replace(trace, amplitude=principal_motion(trace.positions, fit=fit))
    if inhale_sign(out.t_s[fit], out.amplitude[fit]) < 0:
        out = negated(out)
    agree = np.dot(out.amplitude - out.amplitude.mean(), trace.amplitude - trace.amplitude.mean())
    if agree < 0:
        note = ("held-out protocol: the training part's inhalation-positive sign is the opposite of the one "
                "chosen on the whole trace; the training part's is used")
        out = replace(out, fixes=(*out.fixes, note))
    return out


@dataclass(frozen=True)
class Split:
    """A trace split for the held-out protocol (:func:`split`): ``trace`` the whole recording
    resampled at ``fs_hz`` with its amplitude from the training part (:func:`training_signal`);
    its first ``n_train`` samples are the training part; ``train`` and ``test`` the cycles of the
    two parts; ``t_split_s`` the time that ends the training part."""

    trace: Trace
    fs_hz: float
    n_train: int
    train: CycleAnchors
    test: CycleAnchors
    t_split_s: float

    def part(self, held_out: bool) -> Trace:
        """The training part (``held_out`` False) or the held-out part of :attr:`trace`."""
        return _slice(self.trace, slice(self.n_train, None) if held_out else slice(0, self.n_train))


def _slice(trace: Trace, sl: slice) -> Trace:
    return replace(trace, t_s=trace.t_s[sl], amplitude=trace.amplitude[sl], marks=trace.marks[sl])


def _given_cycles(anchors: CycleAnchors, end_train_s: float, start_test_s: float):
    """Given anchors split: the cycles that end by ``end_train_s``, and those starting from ``start_test_s``."""
    st = anchors.starts_s
    k_train = int(np.sum(st[1:] <= end_train_s))
    first = int(np.searchsorted(st[:-1], start_test_s, side="left"))
    return anchors.subset(0, k_train), anchors.subset(first, anchors.n_cycles)


def _part_cycles(part: Trace, name: str, use_marks: bool, detector=None):
    """``(cycles, detector)`` of one part (``detector``: another part's, else this part's own), or
    InputError naming the part and why."""
    try:
        det = detector if detector is not None else detector_of(part)
        return cycle_anchors(part, use_marks=use_marks, detector=det), det
    except InputError as exc:
        why = str(exc).removeprefix(f"{part.source}: ")
        raise InputError(f"{part.source}: {name} part ({part.t_s[0]:.1f}–{part.t_s[-1]:.1f} s): {why}") from None


def split(trace: Trace, train_fraction: float, settings: HoldoutSettings, anchors: CycleAnchors | None = None) -> Split:
    """Steps 1–2 of the protocol: ``trace`` (as read) split into its training and held-out parts and
    their cycles. ``anchors``: the cycles of the whole resampled trace, if known (the training
    cycles are those that end by the end of the training part, the held-out ones those that start
    after it); else detected per part with the training part's detector."""
    t_split = split_time(trace, train_fraction)
    raw_train = trace.t_s < t_split
    if raw_train.sum() < 8:
        raise InputError(f"{trace.source}: {raw_train.sum()} sample(s) before {t_split:.1f} s: too few to train on")
    fs = settings.fs_hz or float(np.round(1.0 / np.median(np.diff(trace.t_s[raw_train]))))
    tr = resample(training_signal(trace, t_split), fs)
    n_train = int(np.searchsorted(tr.t_s, trace.t_s[raw_train][-1] + 1e-9, side="right"))
    if n_train >= tr.n:
        raise InputError(f"{trace.source}: no sample after the training part (0–{t_split:.1f} s)")
    if anchors is not None:
        train, test = _given_cycles(anchors, tr.t_s[n_train - 1], tr.t_s[n_train])
    else:
        train, det = _part_cycles(_slice(tr, slice(0, n_train)), "training", settings.use_marks)
        # the held-out cycles are found from the last training onset on (a training sample may time a
        # held-out onset: nothing flows the other way), and kept from the first held-out sample on
        first = int(np.searchsorted(tr.t_s, train.starts_s[-1], side="left")) if train.n_cycles else n_train
        found, _ = _part_cycles(_slice(tr, slice(min(first, n_train), None)), "held-out", settings.use_marks, det)
        test = found.subset(int(np.searchsorted(found.starts_s[:-1], tr.t_s[n_train], side="left")), found.n_cycles)
    if train.n_cycles < 2 or test.n_cycles < 1:
        raise InputError(f"{trace.source}: {train.n_cycles} complete breathing cycle(s) in the training part and "
                         f"{test.n_cycles} in the held-out part; a held-out test needs >= 2 and >= 1")
    return Split(tr, fs, n_train, train, test, t_split)


# --------------------------------------------------------------------------- evaluation
def _held_out_models(training: _Samples, held_out: _Samples, level_fn, elastance: float, drift: bool) -> dict:
    """The shared shapes fitted on the ``training`` samples and calibrated three ways on the
    ``held_out`` samples ``tt, vt`` (s, mL): ``{"fits", "fits_no_drift", "shared", "no_drift",
    "anchored"}``, the last three name -> model (mL) at ``tt``."""
    train, test, tt, vt = training.anchors, held_out.anchors, held_out.t_s, held_out.volume_ml
    s_test = test.starts_s
    fits = fit_shapes(training.t_s, training.volume_ml, train, elastance, drift)
    shapes = shape_functions(fits, test)
    shared = {m: calibrate_lsq(f(tt), tt, vt, s_test, drift) for m, f in shapes.items()}
    if drift:
        fits_nd = fit_shapes(training.t_s, training.volume_ml, train, elastance, False)
        no_drift = {m: calibrate_lsq(f(tt), tt, vt, s_test, False)
                    for m, f in shape_functions(fits_nd, test).items()}
    else:
        fits_nd, no_drift = fits, shared
    anchored = {m: calibrate_anchored(f, tt, test, level_fn) for m, f in shapes.items()}
    return {"fits": fits, "fits_no_drift": fits_nd, "shared": shared, "no_drift": no_drift, "anchored": anchored}


def _per_cycle_refits(fits: dict, tt, vt, test: CycleAnchors) -> dict:
    """Each held-out cycle fitted on its own (in-sample; see the module doc): name -> model (mL)."""
    s_test = test.starts_s
    pv_refit, _ = inv.refit_control(fits["pv"], tt, vt, s_test, peaks_s=test.peaks_s)
    lj_refit = rb.predict_lujan(rb.fit_lujan(tt, vt, s_test, per_cycle=True), tt, vt, s_test)
    fo_refit, _ = rb.fit_fourier_per_cycle(tt, vt, s_test)
    return {"model": pv_refit, "lujan": lj_refit, "fourier": fo_refit}


def _flag_counts(flags) -> tuple[np.ndarray, dict]:
    """``(regular (k,) bool, {reason: count})`` of the held-out cycles' flags."""
    regular = np.array([not f for f in flags])
    reasons: dict = {}
    for f in flags:
        for r in f:
            reasons[r] = reasons.get(r, 0) + 1
    return regular, reasons


def _scores(curves: dict, vt, s_test, tt, **kw) -> dict:
    return {m: rms_percent(curves[m], vt, s_test, tt, **kw) for m in MODELS}


def _score_table(models: dict, refit: dict, vt, tt, s_test, regular, reasons) -> dict:
    """The error figures of the report (% of the breath amplitude unless named otherwise): held out,
    except ``fourier_insample_rms_percent`` and ``per_cycle_refit_insample`` (module doc)."""
    shared = models["shared"]
    sc = _scores(shared, vt, s_test, tt)
    ref = _scores(refit, vt, s_test, tt)
    return {
        "model_rms_percent": sc["model"],
        "lujan_rms_percent": sc["lujan"],
        "shared_shape": sc,
        "shared_shape_no_drift": _scores(models["no_drift"], vt, s_test, tt),
        "anchored": _scores(models["anchored"], vt, s_test, tt),
        "percent_of_trace_range": _scores(shared, vt, s_test, tt, of="trace"),
        "regular_cycles": {**_scores(shared, vt, s_test, tt, keep=regular), "held_out_cycles": int(regular.size),
                           "flagged": int((~regular).sum()), "reasons": reasons},
        "fourier_insample_rms_percent": ref["fourier"],
        "per_cycle_refit_insample": ref,
    }


def evaluate(trace: Trace, tidal_volume_ml: float = 500.0, train_fraction: float = 0.5, *,
             settings: HoldoutSettings = HoldoutSettings(), anchors: CycleAnchors | None = None,
             progress: Progress | None = None) -> dict:
    """Fit the PV driver and the baselines on the training part, score them on the held-out cycles
    (see module doc). ``trace``: as read (its samples, and a marker trace's positions);
    ``train_fraction``: the training part's share of the duration.

    anchors : the cycles of the resampled trace, if known (else detected per part, :func:`split`);
    ``settings`` : resampling rate, elastance, cycles from marks, drift (:class:`HoldoutSettings`).
    """
    sp = split(trace, train_fraction, settings, anchors)
    tr, train, test, fs = sp.trace, sp.train, sp.test, sp.fs_hz
    s_train, s_test = train.starts_s, test.starts_s
    t = tr.t_s
    vol, gain, _ = calibrate(tr, s_train, tidal_volume_ml)  # from the training cycles' samples only
    in_train = (t >= s_train[0]) & (t < s_train[-1])
    in_test = (t >= s_test[0]) & (t < s_test[-1])
    tt, vt = t[in_test], vol[in_test]
    held_t = t[sp.n_train:]
    level = smooth(vol[sp.n_train:], fs, ANCHOR_LEVEL_CUTOFF_HZ)  # the held-out part's own levels

    def level_fn(x):
        return np.interp(x, held_t, level)

    if progress:
        progress(f"{trace.source}: fits on {train.n_cycles} cycles")
    models = _held_out_models(_Samples(t[in_train], vol[in_train], train), _Samples(tt, vt, test), level_fn,
                              settings.elastance, settings.drift)
    if progress:
        progress(f"{trace.source}: per-cycle refits")
    fits = models["fits"]
    refit = _per_cycle_refits(fits, tt, vt, test)
    held = sp.part(True)
    flags = cycle_flags(held, test)
    regular, reasons = _flag_counts(flags)
    idx_t, _ = rb.cycle_phase(tt, s_test)
    p2p_cycle = float(np.median([np.ptp(vt[idx_t == c]) for c in np.unique(idx_t[idx_t >= 0])]))
    fit = fits["pv"]
    both = CycleAnchors(np.concatenate([s_train, s_test]), np.concatenate([train.peaks_s, test.peaks_s]), train.source)
    return {
        **_score_table(models, refit, vt, tt, s_test, regular, reasons),
        "noise_floor_percent": float(noise_level(held) * gain / p2p_cycle * 100.0),
        "p2p_median_cycle_ml": p2p_cycle,
        "p2p_trace_range_ml": float(np.ptp(vt[idx_t >= 0])),
        "drift": bool(settings.drift),
        "model_train_rms_percent": fit.rms_percent,
        "fit_success": fit.success,
        "fit_message": fit.message,
        "params": fit.params.as_dict(),
        "peak_lag_s": fit.peak_lag_s,
        "lujan": {"n": fits["lujan"].n, "phi_rad": fits["lujan"].phi},
        "cycles_train": train.n_cycles,
        "cycles_held_out": test.n_cycles,
        "split_s": sp.t_split_s,
        "cycle_source": train.source,
        "marks": mark_agreement(tr, both),
        "sample_rate_hz": fs,
        "calibration_ml_per_unit": gain,
        "amplitude_unit": trace.unit,
        "fixes": list(tr.fixes),
        "_curves": {"t_s": t, "volume_ml": vol, "train": in_train, "test": in_test,
                    "pv_held_out_ml": models["shared"]["model"], "fit": fit, "fits": fits,
                    "fits_no_drift": models["fits_no_drift"], "train_anchors": train, "test_anchors": test,
                    "flags": flags},
    }
