"""``lungdeform validate gating``: amplitude gating of a beam simulated on every trace under a folder.

The work is :mod:`lungdeform.validate.gating` (protocol, metrics.json layout and targets there).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.breathing.gating import GateRule, RiskControl, parse_window
from lungdeform.breathing.predict_interval import IntervalConfig
from lungdeform.validate.gating import STRATEGIES, GatingConfig, validate_gating

from .common import STRICT_EXIT, bounded, check_output, figure_or_na, say, takes


@dataclass(frozen=True, kw_only=True)
class GatingOptions:
    """The options of ``lungdeform validate gating`` (:func:`register`)."""

    data: Annotated[Path, typer.Option("--data", help="Folder searched for .vxp / .csv breathing traces.")]
    out: Annotated[Path, typer.Option("--out", help="Output folder: metrics.json and plots/.")]
    latency_ms: Annotated[float, typer.Option("--latency-ms", callback=bounded(0, 10000, "ms", low_open=True), help="Latency between decision and beam (ms).")] = 300.0
    window: Annotated[str, typer.Option("--window", help="Gating window KIND:PERCENT, KIND end-exhale or end-inhale.")] = "end-exhale:30"
    confident: Annotated[bool, typer.Option("--confident", help="model_intervals: the whole interval must be inside the window.")] = False
    coverage: Annotated[float, typer.Option("--coverage", callback=bounded(0, 1, low_open=True, high_open=True), help="Coverage of the prediction intervals (0-1).")] = 0.9
    target_error: Annotated[float, typer.Option("--target-error", callback=bounded(0, 1, low_open=True, high_open=True), help="Tolerated beam-on error (0-1): the window-probability threshold "
        "adapts online so the realised beam-on error tends to it.")] = 0.05
    min_probability: Annotated[float | None, typer.Option("--min-probability", callback=bounded(0, 1, low_open=True, high_open=True), help="Fix the window-probability threshold (0-1) instead of "
        "adapting it to --target-error.")] = None
    strict: Annotated[bool, typer.Option("--strict", help="Exit with code 3 when a target is not met (for CI).")] = False


def register(apps) -> None:
    @apps.validate.command("gating")
    @takes(GatingOptions)
    def gating(opts: GatingOptions) -> None:
        """Gate a beam on each trace: no compensation, linear (tuned, plain), model, model with intervals, oracle."""
        check_output(opts.out, [opts.data], folder=True)
        risk = RiskControl(target_error=opts.target_error) if opts.min_probability is None else None
        rule = GateRule(parse_window(opts.window), opts.confident, 0.5 if opts.min_probability is None else opts.min_probability,
                        IntervalConfig(coverage=opts.coverage), risk)
        config = GatingConfig(latency_ms=opts.latency_ms, rule=rule)
        m = validate_gating(opts.data, opts.out, config, progress=say)
        for name, err in m["errors"].items():
            typer.echo(f"skipped {name}: {err}", err=True)
        typer.echo(f"{m['n_traces']} traces, window {m['window']}, latency {m['latency_ms']:g} ms; medians over traces:")
        typer.echo("  strategy          duty cycle   beam-on error   residual RMS")
        for k in STRATEGIES:
            r = m["summary"][k]
            typer.echo(f"  {k:<16}  {figure_or_na(r['duty_cycle'], 3):>10}   {figure_or_na(r['beam_on_error'], 3):>13}"
                       f"   {figure_or_na(r['residual_rms'], 3):>12}")
        c = m["linear_duty_causal"]
        if c is not None:
            cs, cl = c["summary"], c["linear"]
            typer.echo(f"  at linear's duty cycle, threshold learned on the other traces: model duty "
                       f"{figure_or_na(cs['duty_cycle'], 3)}, beam-on error {figure_or_na(cs['beam_on_error'], 3)} "
                       f"(linear {figure_or_na(cl['duty_cycle'], 3)} / {figure_or_na(cl['beam_on_error'], 3)})")
        mt = m["summary"]["oracle_matched"]
        typer.echo(f"  oracle (hindsight ranking, not a gate): the model's highest window probabilities at linear's "
                   f"duty cycle err {figure_or_na(mt['model_intervals_beam_on_error'], 3)}")
        lo = m["leave_one_trace_out"]
        if lo is not None:
            typer.echo(f"  leave-one-trace-out (step chosen on the other traces): model_intervals duty "
                       f"{figure_or_na(lo['summary']['duty_cycle'], 3)}, beam-on error "
                       f"{figure_or_na(lo['summary']['beam_on_error'], 3)} (target {lo['target_error']:g}); step "
                       f"chosen on all traces {lo['gamma_all']:g}, default {lo['gamma_default']:g}")
        t = m["targets"]
        for key, text in (("error_vs_none", "beam-on error <= 0.5 x none's"),
                          ("duty_vs_none", "duty cycle >= 0.9 x none's"),
                          ("better_than_linear", "better than linear at equal or higher duty"),
                          ("better_than_linear_same_rule", "better than linear_intervals (same rule) on both"),
                          ("better_than_linear_at_linear_duty_causal",
                           "better than linear at linear's duty (threshold from the other traces)")):
            if key in t:
                typer.echo(f"target model_intervals {text}: {'met' if t[key]['met'] else 'not met'}")
        typer.echo(f"wrote {Path(opts.out) / 'metrics.json'} and {len(m['plots'])} plots in {Path(opts.out) / 'plots'}")
        if opts.strict and not all(v["met"] for v in t.values()):
            raise typer.Exit(STRICT_EXIT)
