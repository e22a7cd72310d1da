"""A breathing curve from a named preset or fitted to a recorded trace, with its outputs.

``lungdeform breathe`` behind it. Both runs write into ``out``: ``curve.csv`` (:func:`curve_csv`:
t_s, volume_ml, flow_ml_s, pressure_cmH2O), ``metrics.json`` and three plots (:mod:`lungdeform.plot`):
``volume.png`` (volume against time), ``pv_loop.png`` (muscle pressure against volume) and
``residuals.png`` (for a preset, the ODE integrator against the exact periodic solution; for a fit,
the held-out residuals). The curve drives model playback as s(t) = (V(t) − V_EE)/ΔV
(:func:`lungdeform.breathing.pv.scale_from_volume`).

- :func:`run_preset`: the preset simulated over ``cycles`` breaths at ``fs_hz``; its summary numbers
  (tidal volume, peaks, end-expiratory volume once settled from rest) come from a finely sampled
  run so that they do not depend on ``fs_hz``.
- :func:`run_fit`: the held-out protocol of :mod:`lungdeform.breathing.holdout` on the trace, the PV
  model fitted to all its cycles (the curve written, :func:`fitted_curve`) and the causal streaming
  estimator replayed over it (:mod:`lungdeform.breathing.stream`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lungdeform.atomic import write_json, write_text
from lungdeform.errors import InputError
from lungdeform.plot.breathing import breathing_volume, pv_loop, residuals
from lungdeform.plot.figure import save_png
from lungdeform.progress import Progress

from . import inversion as inv
from . import pv as br
from .cycles import cycle_anchors
from .holdout import calibrate, evaluate
from .presets import Preset, get_preset
from .stream import StreamingVolumeEstimator, offline_volume, replay, signal_delay_s
from .trace import read_trace, resample

#: Fewest output samples per breath a preset run may be given (below, the curve does not show a breath).
MIN_SAMPLES_PER_BREATH = 8
#: Samples per breath of the run the summary numbers (tidal volume, peaks) are measured on.
METRICS_SAMPLES_PER_BREATH = 200
#: How a player turns the curve into the model's scale.
PLAYBACK = "s(t) = (volume_ml(t) - v_ee_ml) / unit_ml"
#: Volume the streaming estimator reads as end-exhale (mL); it scores the shape, not this level.
STREAM_V_EE_ML = 2400.0


def curve_csv(curve: br.BreathingCurve) -> str:
    """``curve`` as CSV text: a header ``t_s,volume_ml,flow_ml_s,pressure_cmH2O`` and one row per
    sample, 6 significant digits."""
    lines = ["t_s,volume_ml,flow_ml_s,pressure_cmH2O"]
    for row in zip(curve.t_s, curve.volume_ml, curve.flow_ml_s, curve.pressure_cmH2O):
        lines.append(",".join(f"{x:.6g}" for x in row))
    return "\n".join(lines) + "\n"


def check_sample_rate(preset: str, fs_hz: float, name: str = "fs_hz") -> Preset:
    """The preset named ``preset``; refuses a sample rate ``fs_hz`` (Hz) that gives fewer than
    :data:`MIN_SAMPLES_PER_BREATH` samples per breath. ``name``: how the message calls the rate."""
    chosen = get_preset(preset)
    period = chosen.params.period_s
    per_breath = fs_hz * period if np.isfinite(fs_hz) else float("nan")
    if not per_breath >= MIN_SAMPLES_PER_BREATH:
        raise InputError(f"{name} {fs_hz:g} Hz gives {per_breath:.2g} samples per {period:g} s breath of preset "
                         f"{chosen.name}; use at least {MIN_SAMPLES_PER_BREATH} ({name} ≥ "
                         f"{MIN_SAMPLES_PER_BREATH / period:.3g})")
    return chosen


def simulate_preset(preset: Preset, cycles: int, fs_hz: float) -> tuple[br.BreathingCurve, np.ndarray, dict]:
    """The preset's curve over ``cycles`` breaths at ``fs_hz``, the integrator minus the exact periodic
    (Fourier) solution of the same equation at its samples ``(t,) mL``, and the metrics."""
    p = preset.params
    curve = br.simulate(p, n_cycles=cycles, fs_hz=fs_hz)
    vol, _ = br.periodic_response(p.period_s, p.mechanics, p.insp_fraction, p.decay)
    exact = p.relaxation_ml + 1000.0 * br.interp_periodic(vol @ p.a, curve.t_s / p.period_s)
    resid = curve.volume_ml - exact
    # the summary numbers from a finely sampled run, so that they do not depend on fs_hz (at 1 Hz a
    # 4 s breath is 4 samples: its sampled range misses the peak)
    fine_fs = max(fs_hz, METRICS_SAMPLES_PER_BREATH / p.period_s)
    fine = curve if fine_fs == fs_hz else br.simulate(p, n_cycles=cycles, fs_hz=fine_fs)
    rest = br.simulate(p, n_cycles=max(cycles, 8), fs_hz=fine_fs, start="rest")
    last = rest.t_s >= rest.t_s[-1] - p.period_s
    end_exp = float(rest.volume_ml[last].min() - p.relaxation_ml)
    metrics = {
        "mode": "preset",
        "preset": preset.as_dict(),
        "cycles": cycles,
        "sample_rate_hz": fs_hz,
        "tidal_volume_ml": fine.tidal_volume_ml,
        "v_ee_ml": fine.v_ee_ml,
        "peak_flow_ml_s": float(fine.flow_ml_s.max()),
        "peak_pressure_cmH2O": float(fine.pressure_cmH2O.max()),
        # end-expiratory volume above the relaxation volume, once settled from rest: > 0 is air
        # trapping (expiration too short); < 0 is active expiration below it (e.g. the deep preset)
        "end_expiratory_above_relaxation_ml": end_exp,
        "air_trapping_ml": max(end_exp, 0.0),
        "integrator_vs_periodic_max_abs_ml": float(np.max(np.abs(resid))),
        "playback": PLAYBACK,
    }
    return curve, resid, metrics


def run_preset(name: str, out: Path, cycles: int, fs_hz: float) -> dict:
    """Simulate the preset ``name`` (:func:`simulate_preset`) and write its outputs into ``out``
    (created); returns the metrics. ``cycles`` ≥ 1; ``fs_hz``: output sample rate (:func:`check_sample_rate`)."""
    if cycles < 1:
        raise InputError(f"cycles must be >= 1, got {cycles}")
    preset = check_sample_rate(name, fs_hz)
    curve, resid, metrics = simulate_preset(preset, cycles, fs_hz)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "curve.csv", curve_csv(curve))
    save_png(breathing_volume(curve.t_s, curve.volume_ml, f"preset {preset.name}: {preset.description}"),
             out / "volume.png")
    save_png(pv_loop(curve.pressure_cmH2O, curve.volume_ml, f"PV loop, preset {preset.name}"),
             out / "pv_loop.png")
    save_png(residuals(curve.t_s, resid, "Radau integrator minus exact periodic solution",
                       "difference (mL)"), out / "residuals.png")
    write_json(out / "metrics.json", metrics, allow_nan=False)
    return metrics


def fitted_curve(fit: inv.BreathingFit, anchors) -> br.BreathingCurve:
    """The fitted model over the fitted cycles as a BreathingCurve (per-cycle gain/offset applied).
    ``anchors``: the cycles' onsets and end-inhale peaks (:class:`lungdeform.breathing.cycles.CycleAnchors`)."""
    p = fit.params
    t = fit.t_s
    starts = fit.cycle_starts_s
    rho = inv.insp_fractions(starts, anchors.peaks_s, fit.peak_lag_s) if fit.peak_lag_s is not None \
        else np.full(starts.size - 1, p.insp_fraction)
    idx = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, starts.size - 2)
    theta = (t - starts[idx]) / (starts[idx + 1] - starts[idx])
    pres = np.empty_like(t)
    for c in np.unique(idx):
        sel = idx == c
        pres[sel] = fit.gains[c] * (br.basis(theta[sel], rho[c], p.decay) @ p.a)
    flow = np.gradient(fit.model_ml, t)
    return br.BreathingCurve(t, fit.model_ml, flow, pres)


def stream_metrics(t_s: np.ndarray, amplitude: np.ndarray, tidal_volume_ml: float) -> dict:
    """Replay a uniformly resampled trace ``(t,)`` s, ``(t,)`` amplitude sample by sample through the
    causal estimator and compare it with its non-causal twin after the first window: latency per
    sample (µs), signal delay (s) and RMS difference (% of ``tidal_volume_ml``)."""
    est = StreamingVolumeEstimator(tidal_volume_ml=tidal_volume_ml, v_ee_ml=STREAM_V_EE_ML)
    svol, secs = replay(t_s, amplitude, est)
    ref = offline_volume(t_s, amplitude, tidal_volume_ml, STREAM_V_EE_ML, est.window_s)
    warm = t_s >= est.window_s
    delay = signal_delay_s(t_s[warm], ref[warm], svol[warm])
    rms = float(np.sqrt(np.mean((svol[warm] - ref[warm]) ** 2)) / tidal_volume_ml * 100.0)
    return {"latency_per_sample_us_median": float(np.median(secs) * 1e6),
            "latency_per_sample_us_p99": float(np.percentile(secs, 99) * 1e6),
            "signal_delay_s": delay,
            "rms_vs_noncausal_percent_of_tidal_volume": rms,
            "window_s": est.window_s, "smoothing_s": est.smoothing_s}


def run_fit(path: Path, out: Path, tidal_volume_ml: float, train_fraction: float,
            progress: Progress | None = None) -> dict:
    """Fit the trace at ``path`` (RPM ``.vxp`` or marker ``.csv``) and write its outputs into ``out``
    (created); returns the metrics. ``tidal_volume_ml``: the calibration (mL); ``train_fraction``:
    the share of cycles fitted, later ones held out; ``progress``: a callable given progress lines."""
    trace = read_trace(path)
    res = evaluate(trace, tidal_volume_ml=tidal_volume_ml, train_fraction=train_fraction, progress=progress)
    curves = res.pop("_curves")
    # the whole trace, all cycles, for the curve the viewer plays back (no held-out score is made of it)
    tr = resample(trace, res["sample_rate_hz"])
    anchors = cycle_anchors(tr)
    vol, _, _ = calibrate(tr, anchors.starts_s, tidal_volume_ml)
    full = inv.invert(tr.t_s, vol, anchors.starts_s, peaks_s=anchors.peaks_s,
                      settings=inv.InversionSettings(per_cycle_calibration=True))
    curve = fitted_curve(full, anchors)
    metrics = {
        "mode": "fit",
        "trace": trace.source,
        "amplitude_unit": trace.unit,
        "tidal_volume_ml": tidal_volume_ml,
        **res,
        "full_fit": {"params": full.params.as_dict(), "peak_lag_s": full.peak_lag_s,
                     "rms_percent": full.rms_percent, "success": full.success, "message": full.message,
                     "shared": list(full.shared), "per_cycle": list(full.per_cycle),
                     "cycles": int(anchors.n_cycles)},
        "stream": stream_metrics(tr.t_s, tr.amplitude, tidal_volume_ml),
        "playback": PLAYBACK,
    }
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "curve.csv", curve_csv(curve))
    save_png(breathing_volume(curve.t_s, curve.volume_ml, f"PV fit to {trace.source}", data=(tr.t_s, vol)),
             out / "volume.png")
    save_png(pv_loop(curve.pressure_cmH2O, curve.volume_ml, f"PV loop, fit to {trace.source}"),
             out / "pv_loop.png")
    test = curves["test"]
    resid = curves["volume_ml"][test] - curves["pv_held_out_ml"]
    save_png(residuals(curves["t_s"][test], resid, f"held-out residuals (shared shape), "
                       f"RMS {res['model_rms_percent']:.1f} % of p2p"), out / "residuals.png")
    write_json(out / "metrics.json", metrics, strict=True)
    return metrics
