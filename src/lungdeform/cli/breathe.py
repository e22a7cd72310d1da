"""``lungdeform breathe``: a breathing curve from a preset or fitted to a recorded trace.

Writes into ``--out``: curve.csv (t_s, volume_ml, flow_ml_s, pressure_cmH2O), metrics.json, and PNG
plots volume.png (volume against time), pv_loop.png (P_mus against volume) and residuals.png (fit
residuals; for a preset, the ODE integrator against the exact periodic solution): the work is
:mod:`lungdeform.breathing.run`. The curve drives model playback as s(t) = (V(t) − V_EE)/ΔV
(:func:`lungdeform.breathing.pv.scale_from_volume`).
"""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.atomic import staged_dir
from lungdeform.breathing.run import check_sample_rate, run_fit, run_preset
from lungdeform.errors import InputError

from .common import bounded, check_cycle_count, check_output, renamed_tidal_ml, say, tidal_option

#: The files breathe writes in ``--out``.
BREATHE_FILES = ("curve.csv", "metrics.json", "volume.png", "pv_loop.png", "residuals.png")


def register(apps) -> None:
    @apps.root.command("breathe")
    def breathe(
        out: Path = typer.Option(..., "--out", help="Output folder (created)."),
        preset: str = typer.Option(None, "--preset", help="normal | deep | copd | restrictive | dyspnoea | pneumothorax"),
        fit: Path = typer.Option(None, "--fit", help="A trace to fit: RPM .vxp or marker .csv."),
        cycles: int = typer.Option(3, "--cycles", help="Preset: number of breathing cycles."),
        fs: float = typer.Option(50.0, "--fs", callback=bounded(0, 10000, "Hz", low_open=True), help="Preset: output sample rate (Hz)."),
        tidal_ml: float = typer.Option(None, "--tidal-ml", callback=tidal_option, help="Fit: calibration tidal volume, both lungs (mL; default 500)."),
        tidal_volume_ml: float = typer.Option(None, "--tidal-volume-ml", hidden=True, callback=tidal_option),
        train_fraction: float = typer.Option(0.5, "--train-fraction", callback=bounded(0, 1, low_open=True, high_open=True), help="Fit: share of cycles fitted."),
    ):
        """Breathing curve (volume, flow, pressure) from a preset or fitted to a trace."""

        if (preset is None) == (fit is None):
            raise InputError("breathe: give exactly one of --preset NAME or --fit TRACE")
        if preset is not None and (tidal_ml, tidal_volume_ml) != (None, None):
            raise InputError("--tidal-ml applies to --fit (the calibration); a --preset has its own tidal volume")
        tidal = renamed_tidal_ml(tidal_ml, tidal_volume_ml)
        check_output(out, [fit], folder=True, writes=BREATHE_FILES)
        if preset is not None:
            check_cycle_count(cycles)
            check_sample_rate(preset, fs, name="--fs")  # the option's name in the message
            with staged_dir(out) as staged:  # curve, metrics and figures together at the end, or none
                m = run_preset(preset, staged, cycles, fs)
            ee = m["end_expiratory_above_relaxation_ml"]
            settled = (f"air trapping {ee:.0f} mL" if ee > -1.0 else
                       f"active expiration to {-ee:.0f} mL below the relaxation volume")
            typer.echo(f"preset {m['preset']['name']}: V_T {m['tidal_volume_ml']:.0f} mL, "
                       f"period {m['preset']['params']['period_s']:.2f} s, {settled}")
        else:
            with staged_dir(out) as staged:
                m = run_fit(fit, staged, tidal, train_fraction, progress=say)
            for fix in m.get("fixes", []):
                typer.echo(f"note: {fix}", err=True)
            typer.echo(f"{m['trace']}: held-out RMS % of p2p: PV {m['model_rms_percent']:.2f}, "
                       f"Lujan {m['lujan_rms_percent']:.2f}, Fourier {m['shared_shape']['fourier']:.2f} "
                       f"(in-sample per-cycle Fourier fit {m['fourier_insample_rms_percent']:.2f}); "
                       f"stream latency {m['stream']['latency_per_sample_us_median']:.1f} µs/sample")
        typer.echo(f"wrote {out}/curve.csv, metrics.json, volume.png, pv_loop.png, residuals.png")
