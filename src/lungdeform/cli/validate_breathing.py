"""``lungdeform validate breathing``: fit every trace under a folder, score held-out cycles.

The work is :mod:`lungdeform.validate.breathing` (its docstring gives the protocol and the layout of
``OUT/metrics.json``); this module parses the options, prints the per-trace and median figures and
picks the exit code (2 when no trace can be scored, 3 with ``--strict`` when the target is missed).
"""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.breathing.holdout import MODELS
from lungdeform.validate.breathing import validate_breathing

from .common import STRICT_EXIT, bounded, check_output, figure_or_na, renamed_tidal_ml, say, tidal_option


def register(apps) -> None:
    @apps.validate.command("breathing")
    def breathing(
        data: Path = typer.Option(..., "--data", help="Folder searched for .vxp / .csv traces."),
        out: Path = typer.Option(..., "--out", help="Output folder for metrics.json."),
        tidal_ml: float = typer.Option(None, "--tidal-ml", callback=tidal_option, help="Calibration tidal volume, both lungs (mL; default 500)."),
        tidal_volume_ml: float = typer.Option(None, "--tidal-volume-ml", hidden=True, callback=tidal_option),
        train_fraction: float = typer.Option(0.5, "--train-fraction", callback=bounded(0, 1, low_open=True, high_open=True)),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when the median target is not met (for CI)."),
    ):
        """Fit the PV driver to every breathing trace; held-out RMS against Lujan and Fourier."""
        tidal = renamed_tidal_ml(tidal_ml, tidal_volume_ml)
        check_output(out, [data], folder=True)

        m = validate_breathing(data, out, tidal, train_fraction, progress=say)
        for name, r in m["traces"].items():
            typer.echo(f"{name}: PV {r['model_rms_percent']:.2f} %  Lujan {r['lujan_rms_percent']:.2f} %  "
                       f"Fourier {r['shared_shape']['fourier']:.2f} %  (in-sample per-cycle Fourier fit "
                       f"{r['fourier_insample_rms_percent']:.2f} %)")
        for name, err in m["errors"].items():
            typer.echo(f"skipped {name}: {err}", err=True)

        def f(d):
            return " / ".join(figure_or_na(d[k]) for k in MODELS) + " %"

        typer.echo(f"median held-out RMS: PV {figure_or_na(m['median_model_rms_percent'])} %, "
                   f"Lujan {figure_or_na(m['median_lujan_rms_percent'])} %, "
                   f"Fourier {figure_or_na(m['median_shared_shape']['fourier'])} % (target PV < 5 %)")
        typer.echo(f"held-out medians PV / Lujan / Fourier: shared shape, no drift "
                   f"{f(m['median_shared_shape_no_drift'])}; anchored {f(m['median_anchored'])}")
        typer.echo(f"  as % of each held-out trace's whole range {f(m['median_percent_of_trace_range'])}; "
                   f"regular cycles only {f(m['median_regular_cycles'])}; "
                   f"white-noise floor {figure_or_na(m['median_noise_floor_percent'])} %")
        typer.echo(f"not held out (each held-out cycle fitted to itself): per-cycle refit "
                   f"{f(m['in_sample']['median_per_cycle_refit_insample'])}")
        p = m["paired_model_vs_lujan"]
        typer.echo(f"  PV better than Lujan on {p['traces_model_better']} of {p['traces']} traces "
                   f"(median difference {p['median_difference_percent']:+.2f} points)")
        typer.echo(f"wrote {Path(out) / 'metrics.json'}")
        median = m["median_model_rms_percent"]
        if strict and not (median is not None and median < m["target_median_model_rms_percent"]):  # NaN fails too
            raise typer.Exit(STRICT_EXIT)
