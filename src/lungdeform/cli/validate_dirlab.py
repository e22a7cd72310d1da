"""``lungdeform validate dirlab``: test the paper's motion hypotheses on DIR-Lab 4-D CT landmarks."""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.errors import InputError
from lungdeform.validate.dirlab import MODELS, default_models
from lungdeform.validate.dirlab_experiment import DirlabRun, run_dirlab, write_metrics

from .common import check_output


def register(apps) -> None:
    @apps.validate.command("dirlab")
    def dirlab_command(
        data: Path = typer.Option(..., "--data", help="DIR-Lab folder: the one holding the case folders, a folder above it, or one case folder "
                                       "(cases are found by file name)."),
        out: Path = typer.Option(..., "--out", help="Output folder; metrics.json is written there."),
        folds: int = typer.Option(5, "--folds", help="Landmark folds for fitting held-out drivers."),
        published_spacing: bool = typer.Option(
            True, "--published-spacing/--no-published-spacing",
            help="For a case 1–10 that voxel_spacing.csv does not list (or with no table at all), use DIR-Lab's "
                 "published spacing, with a note; --no-published-spacing makes it an error.",
        ),
    ) -> None:
        """Predict T10–T40 landmarks from T00/T50 with one scalar per phase, and richer real-time models."""
        check_output(out, [data], folder=True)


        if folds < 2:
            raise InputError(f"--folds must be ≥ 2, got {folds}")
        run = run_dirlab(data, folds=folds, published_fallback=published_spacing)
        _print_table(run)
        for n in run.notes:
            typer.echo(f"note: {n}")
        typer.echo(f"magnitude set by one scalar per phase: {run.summary['magnitude_one_scalar']}")
        typer.echo(f"direction constant: {run.summary['direction_constant']}")
        path = write_metrics(run, out)  # an atomic write: its folder made for it, or none
        typer.echo(f"wrote {path} ({len(run.results)} case(s), {run.elapsed_s:.2f} s)")


def _print_table(run: DirlabRun) -> None:
    """One line per case: 300-pair means, the baselines and each model's held-out mean error (mm)."""
    names = list(MODELS)
    short = {m: m.replace("_landmark", "_lm").replace("_region", "_rg").replace("two_component", "two_comp") for m in names}
    typer.echo("DIR-Lab, mean errors in mm over T10–T40 (75 landmarks). T00 = end-inhale, T50 = end-exhale:")
    typer.echo("T10–T40 are exhale phases; the held-out columns leave one phase out. default: the model chosen on the")
    typer.echo("other cases (leave one case out); best: chosen on the case's own held-out errors (optimistic).")
    head = f"{'case':>4} {'300 mean':>8} {'publ.':>6} {'none':>6} {'1 scal':>6} {'floor':>6} | " + " ".join(
        f"{short[m]:>9}" for m in names
    ) + " | default (other cases) | best (diagnostic)"
    typer.echo(head)
    defaults = default_models(list(run.results))
    for r in run.results:
        disp = "-" if r.mean_displacement_300_mm is None else f"{r.mean_displacement_300_mm:.2f}"
        pub = "-" if r.published_300_mm is None else f"{r.published_300_mm:.2f}"
        if r.best_model is None:
            typer.echo(f"{r.case:>4} {disp:>8} {pub:>6}   (no 75-point phase files: motion models skipped)")
            continue
        typer.echo(
            f"{r.case:>4} {disp:>8} {pub:>6} {r.no_motion_mean_mm:>6.2f} {r.one_scalar_mean_mm:>6.2f} "
            f"{r.rounding_floor_mm:>6.2f} | "
            + " ".join(f"{r.heldout_mean_mm[m]:>9.3f}" for m in names)
            + f" | {_named(*defaults[r.case])} | {_named(r.best_model, r.best_model_heldout_mean_mm)}"
        )
    for case, why in sorted(run.discovery.skipped.items()):
        typer.echo(f"{case:>4}   (skipped: {why.split(': skipped: ', 1)[-1]})")


def _named(model: str | None, mm: float | None) -> str:
    return "-" if model is None else f"{model} ({mm:.3f})"
