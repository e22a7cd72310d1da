"""``lungdeform breathe``: a breathing curve from a preset or fitted to a recorded trace.

Writes into ``--out``: curve.csv (t_s, volume_ml, flow_ml_s, pressure_cmH2O), metrics.json, and PNG
plots volume.png (volume against time), pv_loop.png (P_mus against volume) and residuals.png (fit
residuals; for a preset, the ODE integrator against the exact periodic solution). The curve drives
model playback as s(t) = (V(t) − V_EE)/ΔV (:func:`lungdeform.breathing.pv.scale_from_volume`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from lungdeform.atomic import atomic_path, write_json, write_text
from lungdeform.breathing import inversion as inv
from lungdeform.breathing import pv as br
from lungdeform.breathing.holdout import calibrate, evaluate
from lungdeform.breathing.presets import get_preset
from lungdeform.breathing.stream import StreamingVolumeEstimator, offline_volume, replay, signal_delay_s
from lungdeform.breathing.trace import read_trace, resample
from lungdeform.errors import InputError

from .common import say


# --------------------------------------------------------------------------- atomic outputs
def atomic_savefig(fig, path: Path) -> None:

    with atomic_path(path, ".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")


def curve_csv(curve) -> str:
    lines = ["t_s,volume_ml,flow_ml_s,pressure_cmH2O"]
    for row in zip(curve.t_s, curve.volume_ml, curve.flow_ml_s, curve.pressure_cmH2O):
        lines.append(",".join(f"{x:.6g}" for x in row))
    return "\n".join(lines) + "\n"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_curve(curve, path: Path, title: str, data=None, held_out_from=None) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 3.6))
    if data is not None:
        ax.plot(data[0], data[1], lw=0.7, color="0.5", label="trace (calibrated)")
    ax.plot(curve.t_s, curve.volume_ml, lw=1.0, color="C0", label="PV model")
    if held_out_from is not None:
        ax.axvspan(held_out_from, curve.t_s[-1], color="C1", alpha=0.08, label="held-out cycles")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("volume (mL)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def plot_pv_loop(curve, path: Path, title: str) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.8, 4.2))
    ax.plot(curve.pressure_cmH2O, curve.volume_ml, lw=0.8)
    ax.set_xlabel("muscle pressure P_mus (cmH2O)")
    ax.set_ylabel("volume (mL)")
    ax.set_title(title)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


def plot_residuals(t, resid, path: Path, title: str, ylabel: str = "residual (mL)") -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 3.0))
    ax.plot(t, resid, lw=0.7)
    ax.axhline(0.0, color="0.4", lw=0.5)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    fig.tight_layout()
    atomic_savefig(fig, path)
    plt.close(fig)


# --------------------------------------------------------------------------- the work
#: Fewest output samples per breath ``--fs`` may give (below, the curve does not show a breath).
MIN_SAMPLES_PER_BREATH = 8
#: Samples per breath of the run the summary numbers (tidal volume, peaks) are measured on.
METRICS_SAMPLES_PER_BREATH = 200


def run_preset(name: str, out: Path, cycles: int, fs_hz: float) -> dict:



    preset = get_preset(name)
    p = preset.params
    per_breath = fs_hz * p.period_s if np.isfinite(fs_hz) else float("nan")
    if per_breath < MIN_SAMPLES_PER_BREATH:
        raise InputError(f"--fs {fs_hz:g} Hz gives {per_breath:.2g} samples per {p.period_s:g} s breath of preset "
                         f"{preset.name}; use at least {MIN_SAMPLES_PER_BREATH} (--fs ≥ "
                         f"{MIN_SAMPLES_PER_BREATH / p.period_s:.3g})")
    curve = br.simulate(p, n_cycles=cycles, fs_hz=fs_hz)
    # check: the integrator against the exact periodic (Fourier) solution of the same equation
    vol, _ = br.periodic_response(p.period_s, p.mechanics, p.insp_fraction, p.decay)
    exact = p.relaxation_ml + 1000.0 * br.interp_periodic(vol @ p.a, curve.t_s / p.period_s)
    resid = curve.volume_ml - exact
    # the summary numbers from a finely sampled run, so that they do not depend on --fs (at 1 Hz a
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
        "playback": "s(t) = (volume_ml(t) - v_ee_ml) / unit_ml",
    }
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "curve.csv", curve_csv(curve))
    plot_curve(curve, out / "volume.png", f"preset {preset.name}: {preset.description}")
    plot_pv_loop(curve, out / "pv_loop.png", f"PV loop, preset {preset.name}")
    plot_residuals(curve.t_s, resid, out / "residuals.png",
                   "Radau integrator minus exact periodic solution", "difference (mL)")
    write_json(out / "metrics.json", metrics, allow_nan=False)
    return metrics


def fitted_curve(fit, anchors):
    """The fitted model over the fitted cycles as a BreathingCurve (per-cycle gain/offset applied)."""


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


def run_fit(path: Path, out: Path, tidal_volume_ml: float, train_fraction: float, progress=None) -> dict:


    trace = read_trace(path)
    res = evaluate(trace, tidal_volume_ml=tidal_volume_ml, train_fraction=train_fraction, progress=progress)
    curves = res.pop("_curves")
    anchors = curves["anchors"]
    # the whole trace, all cycles, for the curve the viewer plays back
    fs = res["sample_rate_hz"]
    tr = resample(trace, fs)
    vol, _, _ = calibrate(tr, anchors.starts_s, tidal_volume_ml)
    full = inv.invert(tr.t_s, vol, anchors.starts_s, peaks_s=anchors.peaks_s, per_cycle_calibration=True)
    curve = fitted_curve(full, anchors)

    # streaming: replay the trace sample by sample; compare with the non-causal twin of the estimator
    est = StreamingVolumeEstimator(tidal_volume_ml=tidal_volume_ml, v_ee_ml=2400.0)
    svol, secs = replay(tr.t_s, tr.amplitude, est)
    ref = offline_volume(tr.t_s, tr.amplitude, tidal_volume_ml, 2400.0, est.window_s)
    warm = tr.t_s >= est.window_s
    delay = signal_delay_s(tr.t_s[warm], ref[warm], svol[warm])
    stream_rms = float(np.sqrt(np.mean((svol[warm] - ref[warm]) ** 2)) / tidal_volume_ml * 100.0)
    metrics = {
        "mode": "fit",
        "trace": trace.source,
        "amplitude_unit": trace.unit,
        "tidal_volume_ml": tidal_volume_ml,
        **{k: v for k, v in res.items()},
        "full_fit": {"params": full.params.as_dict(), "peak_lag_s": full.peak_lag_s,
                     "rms_percent": full.rms_percent, "success": full.success, "message": full.message,
                     "shared": list(full.shared), "per_cycle": list(full.per_cycle),
                     "cycles": int(anchors.n_cycles)},
        "stream": {"latency_per_sample_us_median": float(np.median(secs) * 1e6),
                   "latency_per_sample_us_p99": float(np.percentile(secs, 99) * 1e6),
                   "signal_delay_s": delay,
                   "rms_vs_noncausal_percent_of_tidal_volume": stream_rms,
                   "window_s": est.window_s, "smoothing_s": est.smoothing_s},
        "playback": "s(t) = (volume_ml(t) - v_ee_ml) / unit_ml",
    }
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "curve.csv", curve_csv(curve))
    plot_curve(curve, out / "volume.png", f"PV fit to {trace.source}", data=(tr.t_s, vol),
               held_out_from=None)
    plot_pv_loop(curve, out / "pv_loop.png", f"PV loop, fit to {trace.source}")
    test = curves["test"]
    r_t = curves["t_s"][test]
    r_v = curves["volume_ml"][test] - curves["pv_held_out_ml"]
    plot_residuals(r_t, r_v, out / "residuals.png",
                   f"held-out residuals (shared shape), RMS {res['model_rms_percent']:.1f} % of p2p")
    write_json(out / "metrics.json", metrics, strict=True)
    return metrics


def register(apps) -> None:
    @apps.root.command("breathe")
    def breathe(
        out: Path = typer.Option(..., "--out", help="Output folder (created)."),
        preset: str = typer.Option(None, "--preset", help="normal | deep | copd | restrictive | dyspnoea | pneumothorax"),
        fit: Path = typer.Option(None, "--fit", help="A trace to fit: RPM .vxp or marker .csv."),
        cycles: int = typer.Option(3, "--cycles", help="Preset: number of breathing cycles."),
        fs: float = typer.Option(50.0, "--fs", help="Preset: output sample rate (Hz)."),
        tidal_volume_ml: float = typer.Option(500.0, "--tidal-volume-ml", help="Fit: calibration tidal volume."),
        train_fraction: float = typer.Option(0.5, "--train-fraction", help="Fit: share of cycles fitted."),
    ):
        """Breathing curve (volume, flow, pressure) from a preset or fitted to a trace."""

        if (preset is None) == (fit is None):
            raise InputError("breathe: give exactly one of --preset NAME or --fit TRACE")
        if preset is not None:
            if cycles < 1:
                raise InputError(f"--cycles must be >= 1, got {cycles}")
            m = run_preset(preset, out, cycles, fs)
            ee = m["end_expiratory_above_relaxation_ml"]
            settled = (f"air trapping {ee:.0f} mL" if ee > -1.0 else
                       f"active expiration to {-ee:.0f} mL below the relaxation volume")
            typer.echo(f"preset {m['preset']['name']}: V_T {m['tidal_volume_ml']:.0f} mL, "
                       f"period {m['preset']['params']['period_s']:.2f} s, {settled}")
        else:

            m = run_fit(fit, out, tidal_volume_ml, train_fraction, progress=say)
            for fix in m.get("fixes", []):
                typer.echo(f"note: {fix}", err=True)
            typer.echo(f"{m['trace']}: held-out RMS % of p2p: PV {m['model_rms_percent']:.2f}, "
                       f"Lujan {m['lujan_rms_percent']:.2f}, Fourier per-cycle {m['fourier_rms_percent']:.2f}; "
                       f"stream latency {m['stream']['latency_per_sample_us_median']:.1f} µs/sample")
        typer.echo(f"wrote {out}/curve.csv, metrics.json, volume.png, pv_loop.png, residuals.png")
