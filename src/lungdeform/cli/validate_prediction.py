"""``lungdeform validate prediction``: live breathing prediction scored on every trace under a folder.

The work is :mod:`lungdeform.validate.prediction` (protocol, metrics.json layout and targets there).
"""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.errors import InputError
from lungdeform.validate.prediction import HORIZONS_MS, TARGET_QUIET_HORIZON_MS, validate_prediction

from .common import STRICT_EXIT, check_output, figure_or_na, say


def _horizons(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--horizons must be comma-separated milliseconds, got {text!r}") from None


def register(apps) -> None:
    @apps.validate.command("prediction")
    def prediction(
        data: Path = typer.Option(..., "--data", help="Folder searched for .vxp / .csv breathing traces."),
        out: Path = typer.Option(..., "--out", help="Output folder: metrics.json and plots/."),
        horizons: str = typer.Option(",".join(str(h) for h in HORIZONS_MS), "--horizons",
                                     help="Prediction horizons in ms, comma-separated."),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when a target is not met (for CI)."),
    ):
        """Predict each trace 100–500 ms ahead, causally; RMS against no prediction and linear autoregressions."""
        check_output(out, [data], folder=True)

        m = validate_prediction(data, out, _horizons(horizons), progress=say)
        for name, err in m["errors"].items():
            typer.echo(f"skipped {name}: {err}", err=True)
        typer.echo(f"{m['n_traces']} traces ({m['n_quiet']} quiet); medians of per-trace RMS ratios:")
        typer.echo("  horizon   model/linear   model/linear_plain   model/none   linear/none   linear_plain/none"
                   "   quiet model/none")
        for h in m["horizons_ms"]:
            a, q = m["medians"][str(h)], m["quiet_medians"][str(h)]
            cells = [figure_or_na(v, 3) for v in (a["model_over_linear"], a["model_over_linear_plain"],
                                                    a["model_over_none"], a["linear_over_none"],
                                                    a["linear_plain_over_none"], q["model_over_none"])]
            typer.echo(f"  {h:>5} ms   {cells[0]:>12}   {cells[1]:>18}   {cells[2]:>10}   {cells[3]:>11}"
                       f"   {cells[4]:>17}   {cells[5]:>16}")
        typer.echo("90 % intervals, medians over traces (width: mean width / RMS of no prediction):")
        typer.echo("  horizon   coverage   width   linear coverage   linear width   score/linear")
        for h in m["horizons_ms"]:
            a = m["medians"][str(h)]
            cells = [figure_or_na(a[k], 3) for k in ("coverage", "width_over_none_rms", "linear_coverage",
                                                     "linear_width_over_none_rms", "interval_score_over_linear")]
            typer.echo(f"  {h:>5} ms   {cells[0]:>8}   {cells[1]:>5}   {cells[2]:>15}   {cells[3]:>12}   {cells[4]:>12}")
        t = m["targets"]
        lin, quiet, cov = t["model_over_linear_every_horizon"], t["quiet_model_over_none"], t["coverage_every_horizon"]
        typer.echo(f"target coverage in {cov['range'][0]:g}-{cov['range'][1]:g} at every horizon: "
                   f"{'met' if cov['met'] else 'not met'}")
        typer.echo(f"target model/linear <= {lin['threshold']} at every horizon: "
                   f"{'met' if lin['met'] else 'not met'} (worst {figure_or_na(lin['worst'], 3)})")
        typer.echo(f"target quiet model/none <= {quiet['threshold']} at {TARGET_QUIET_HORIZON_MS} ms: "
                   f"{'met' if quiet['met'] else 'not met'} ({figure_or_na(quiet['value'], 3)})")
        typer.echo(f"wrote {Path(out) / 'metrics.json'} and {len(m['plots'])} plots in {Path(out) / 'plots'}")
        if strict and not (lin["met"] and quiet["met"] and cov["met"]):
            raise typer.Exit(STRICT_EXIT)
