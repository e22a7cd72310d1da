"""``lungdeform validate breathing``: fit every trace under a folder, score held-out cycles.

The work is :mod:`lungdeform.validate.breathing`: it finds RPM ``.vxp`` and marker ``.csv`` files under
``--data`` (recursively), runs the held-out protocol of :mod:`lungdeform.breathing.holdout` on each (PV
driver, Lujan cos^{2n}, per-cycle Fourier) and writes ``OUT/metrics.json``::

    {"traces": {"<file name>": {"model_rms_percent": …, "lujan_rms_percent": …,
                                "fourier_rms_percent": …, …}},
     "median_model_rms_percent": …, …}

Besides those keys: the medians of every calibration variant (shared_shape with drift = the
headline, shared_shape_no_drift, anchored, per_cycle_refit), the same error as a % of each held-out
trace's whole range, the score on model-free "regular" held-out cycles, the white-noise floor, and a
paired PV-vs-Lujan comparison (per trace; a comparison of two medians is not paired).
A trace that cannot be read or holds too few cycles is reported under "errors" and left out of the
medians; if no trace can be scored the command fails (exit 2).
"""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.breathing.holdout import MODELS
from lungdeform.validate.breathing import validate_breathing

from .common import STRICT_EXIT, say


def _pct(x) -> str:
    """A median for the summary lines: 'n/a' where undefined (None: no finite score)."""
    return "n/a" if x is None else f"{x:.2f}"


def register(apps) -> None:
    @apps.validate.command("breathing")
    def breathing(
        data: Path = typer.Option(..., "--data", help="Folder searched for .vxp / .csv traces."),
        out: Path = typer.Option(..., "--out", help="Output folder for metrics.json."),
        tidal_volume_ml: float = typer.Option(500.0, "--tidal-volume-ml"),
        train_fraction: float = typer.Option(0.5, "--train-fraction"),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when the median target is not met (for CI)."),
    ):
        """Fit the PV driver to every breathing trace; held-out RMS against Lujan and Fourier."""

        m = validate_breathing(data, out, tidal_volume_ml, train_fraction, progress=say)
        for name, r in m["traces"].items():
            typer.echo(f"{name}: PV {r['model_rms_percent']:.2f} %  Lujan {r['lujan_rms_percent']:.2f} %  "
                       f"Fourier/cycle {r['fourier_rms_percent']:.2f} %")
        for name, err in m["errors"].items():
            typer.echo(f"skipped {name}: {err}", err=True)
        typer.echo(f"median held-out RMS: PV {_pct(m['median_model_rms_percent'])} %, "
                   f"Lujan {_pct(m['median_lujan_rms_percent'])} %, "
                   f"Fourier per cycle {_pct(m['median_fourier_rms_percent'])} % (target PV < 5 %)")

        def f(d):
            return " / ".join(_pct(d[k]) for k in MODELS) + " %"

        typer.echo(f"medians PV / Lujan / Fourier: shared shape, no drift {f(m['median_shared_shape_no_drift'])}; "
                   f"anchored {f(m['median_anchored'])}; per-cycle refit {f(m['median_per_cycle_refit'])}")
        typer.echo(f"  as % of each held-out trace's whole range {f(m['median_percent_of_trace_range'])}; "
                   f"regular cycles only {f(m['median_regular_cycles'])}; "
                   f"white-noise floor {_pct(m['median_noise_floor_percent'])} %")
        p = m["paired_model_vs_lujan"]
        typer.echo(f"  PV better than Lujan on {p['traces_model_better']} of {p['traces']} traces "
                   f"(median difference {p['median_difference_percent']:+.2f} points)")
        typer.echo(f"wrote {Path(out) / 'metrics.json'}")
        median = m["median_model_rms_percent"]
        if strict and not (median is not None and median < m["target_median_model_rms_percent"]):  # NaN fails too
            raise typer.Exit(STRICT_EXIT)
