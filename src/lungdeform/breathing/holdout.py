"""Held-out evaluation of breathing models on a real surrogate trace.

Protocol (one trace):

1. Resample to a uniform grid at the trace's own rate (the readers have already signed it
   inhalation-positive, :func:`lungdeform.breathing.trace.orient_inhale_positive`); split into cycles at the
   detected inspiration onsets with the detected end-inhale peaks (:func:`lungdeform.breathing.cycles.cycle_anchors`,
   the same detector for every format; the RPM's own marks are compared with it, not used: in the
   real .vxp file one in five is off by more than 0.5 s).
2. Calibrate amplitude to volume linearly: the median peak-to-peak of the *training* cycles maps to
   the given tidal volume (default 500 mL), their median end-exhale level to ``relaxation_ml``.
3. Training = the first ``train_fraction`` of the cycles; held out = all later cycles. Every shape
   parameter is fitted on the training cycles only (PV driver: τ = R/E, I/E, the drive-to-peak lag
   δ, κ and the five a_k; Lujan: n, φ; Fourier: the K = 2 mean-cycle coefficients). Nothing fitted
   ever sees a held-out sample (tests/breathing/test_holdout.py corrupts them and checks).
4. What each held-out cycle is given — the same for the three shared-shape models, because one
   function calibrates all three shapes:

   - its timing: the two inspiration onsets around it and its end-inhale time (what an RPM's
     marks or a causal onset/peak detector give a user);
   - **shared_shape** (the headline): a per-cycle least-squares gain, offset and, with ``drift``
     (default), a linear baseline drift across the cycle — 3 numbers fitted to that cycle's own
     samples, like a per-cycle amplitude calibration of an external surrogate;
   - **shared_shape_no_drift**: gain and offset only (2 numbers; the protocol before drift);
   - **anchored** (strict): no held-out sample is used but the levels of the 1-Hz low-passed volume
     at the three anchors (onset, peak, next onset): gain, offset and drift solve those 3 points
     exactly. Only information at the cycle boundaries a user would have.

   Plus the **per-cycle refit**: each held-out cycle fitted on its own (PV: the five a_k with the
   training mechanics; Lujan: n, φ, c0, b; Fourier K = 2: five coefficients). This is an in-sample
   fit of unseen cycles — a measure of expressiveness, not of prediction; ``fourier_rms_percent`` is
   this figure (the "per-cycle Fourier fit" of ``lungdeform validate breathing``).

The error is the RMS over all held-out samples as a percentage of the median per-cycle peak-to-peak
of the held-out cycles (``of="cycle"``; the breath amplitude — smaller than the whole trace's range
when the baseline drifts or when non-breathing events occur, so a stricter figure); the same RMS as
a % of the held-out trace's whole range is reported alongside (``percent_of_trace_range``). Also
reported, to explain the figures, never used by any fit: the white-noise floor (% of the breath
amplitude), the score on held-out cycles that model-free flags call regular
(:func:`lungdeform.breathing.cycles.cycle_flags`; same denominator), and the agreement of recorded marks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lungdeform.breathing import curve_models as rb
from lungdeform.breathing import inversion as inv
from lungdeform.errors import InputError
from lungdeform.progress import Progress

from .cycles import CycleAnchors, cycle_anchors, cycle_flags, mark_agreement, noise_level, smooth
from .trace import Trace, resample

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


# --------------------------------------------------------------------------- evaluation
def _split_cycles(trace: Trace, train_fraction: float, fs_hz, use_marks: bool, anchors):
    """Resample ``trace`` at ``fs`` Hz and split its cycles into training and held-out ones.

    Returns ``(fs, resampled trace, all anchors, n_train, train anchors, held-out anchors)``."""
    if not (0.0 < train_fraction < 1.0):
        raise InputError(f"train_fraction must lie in (0, 1), got {train_fraction!r}")
    fs = fs_hz or float(np.round(1.0 / trace.sample_interval_s))
    tr = resample(trace, fs)
    anchors = anchors if anchors is not None else cycle_anchors(tr, use_marks=use_marks)
    k = anchors.n_cycles
    if k < 3:
        raise InputError(f"{trace.source}: {k} complete breathing cycle(s); a held-out test needs >= 3")
    n_train = int(np.clip(np.floor(k * train_fraction), 2, k - 1))
    return fs, tr, anchors, n_train, anchors.subset(0, n_train), anchors.subset(n_train, k)


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
    """The error figures of the report (% of the breath amplitude unless named otherwise)."""
    shared = models["shared"]
    sc = _scores(shared, vt, s_test, tt)
    ref = _scores(refit, vt, s_test, tt)
    return {
        "model_rms_percent": sc["model"],
        "lujan_rms_percent": sc["lujan"],
        "fourier_rms_percent": ref["fourier"],
        "shared_shape": sc,
        "shared_shape_no_drift": _scores(models["no_drift"], vt, s_test, tt),
        "anchored": _scores(models["anchored"], vt, s_test, tt),
        "per_cycle_refit": ref,
        "percent_of_trace_range": {"model": rms_percent(shared["model"], vt, s_test, tt, of="trace"),
                                   "lujan": rms_percent(shared["lujan"], vt, s_test, tt, of="trace"),
                                   "fourier": rms_percent(refit["fourier"], vt, s_test, tt, of="trace")},
        "regular_cycles": {**_scores(shared, vt, s_test, tt, keep=regular), "held_out_cycles": int(regular.size),
                           "flagged": int((~regular).sum()), "reasons": reasons},
    }


def evaluate(trace: Trace, tidal_volume_ml: float = 500.0, train_fraction: float = 0.5, *,
             settings: HoldoutSettings = HoldoutSettings(), anchors: CycleAnchors | None = None,
             progress: Progress | None = None) -> dict:
    """Fit the PV driver and the baselines on early cycles, score them on later ones (see module doc).

    anchors : the cycles of the resampled trace, if known (else detected); ``settings`` : resampling
    rate, elastance, cycles from marks, drift (:class:`HoldoutSettings`).
    """
    fs_hz, elastance, use_marks, drift = settings.fs_hz, settings.elastance, settings.use_marks, settings.drift
    fs, tr, anchors, n_train, train, test = _split_cycles(trace, train_fraction, fs_hz, use_marks, anchors)
    s_train, s_test = train.starts_s, test.starts_s
    t = tr.t_s
    vol, gain, offset = calibrate(tr, s_train, tidal_volume_ml)
    in_train = (t >= s_train[0]) & (t < s_train[-1])
    in_test = (t >= s_test[0]) & (t < s_test[-1])
    tt, vt = t[in_test], vol[in_test]
    level = smooth(vol, fs, ANCHOR_LEVEL_CUTOFF_HZ)

    def level_fn(x):
        return np.interp(x, t, level)

    if progress:
        progress(f"{trace.source}: fits on {n_train} cycles")
    models = _held_out_models(_Samples(t[in_train], vol[in_train], train), _Samples(tt, vt, test), level_fn,
                              elastance, drift)
    if progress:
        progress(f"{trace.source}: per-cycle refits")
    fits = models["fits"]
    refit = _per_cycle_refits(fits, tt, vt, test)
    flags = cycle_flags(tr, anchors)
    regular, reasons = _flag_counts(flags[n_train:])
    idx_t, _ = rb.cycle_phase(tt, s_test)
    p2p_cycle = float(np.median([np.ptp(vt[idx_t == c]) for c in np.unique(idx_t[idx_t >= 0])]))
    fit = fits["pv"]
    return {
        **_score_table(models, refit, vt, tt, s_test, regular, reasons),
        "noise_floor_percent": float(noise_level(tr) * gain / p2p_cycle * 100.0),
        "p2p_median_cycle_ml": p2p_cycle,
        "p2p_trace_range_ml": float(np.ptp(vt[idx_t >= 0])),
        "drift": bool(drift),
        "model_train_rms_percent": fit.rms_percent,
        "fit_success": fit.success,
        "fit_message": fit.message,
        "params": fit.params.as_dict(),
        "peak_lag_s": fit.peak_lag_s,
        "lujan": {"n": fits["lujan"].n, "phi_rad": fits["lujan"].phi},
        "cycles_train": n_train,
        "cycles_held_out": anchors.n_cycles - n_train,
        "cycle_source": anchors.source,
        "marks": mark_agreement(tr, anchors),
        "sample_rate_hz": fs,
        "calibration_ml_per_unit": gain,
        "amplitude_unit": trace.unit,
        "fixes": list(tr.fixes),
        "_curves": {"t_s": t, "volume_ml": vol, "train": in_train, "test": in_test,
                    "pv_held_out_ml": models["shared"]["model"], "fit": fit, "fits": fits,
                    "fits_no_drift": models["fits_no_drift"], "anchors": anchors, "flags": flags},
    }
