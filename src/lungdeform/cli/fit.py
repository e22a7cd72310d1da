"""``lungdeform fit``: fit a lung model to surfaces, masks or CTs at two or more volumes.

The pipeline itself (reading, alignment, fits, baselines, outputs) is
:func:`lungdeform.fit.pipeline.run_fit`; this module parses the options and prints the table.
"""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.errors import InputError
from lungdeform.fit.pipeline import run_fit

from .common import DIRECTION_DEGREE_HELP, SIDE_CHECK_HELP, output_dir, say


def register(apps) -> None:
    @apps.root.command("fit")
    def fit_command(
        inputs: list[Path] = typer.Argument(..., help="Surfaces, masks or CTs of one lung, end-exhale first, volumes increasing."),
        out: Path = typer.Option(..., "--out", help="Output folder: model.npz, metrics.json, report.html."),
        side: str = typer.Option(..., "--side", help="'left' or 'right'."),
        side_check: bool = typer.Option(True, "--side-check/--no-side-check", help=SIDE_CHECK_HELP),
        volumes: str = typer.Option(None, "--volumes", help="Lung volumes in mL, comma-separated (default: measured from the surfaces)."),
        landmarks: list[Path] = typer.Option(None, "--landmarks", help="elastix point-set file per input (world mm), rows corresponding."),
        grid: bool = typer.Option(False, "--grid", help="Also run the paper's grid search (step 0.01) for comparison."),
        stiffness: bool = typer.Option(True, "--stiffness/--no-stiffness", help="Fit a heterogeneous stiffness field (inverse expandability), kept only if it lowers the objective; --no-stiffness: uniform, faster."),
        baselines: bool = typer.Option(True, "--baselines/--no-baselines", help="Measure the baselines too."),
        evaluations: int = typer.Option(300, "--evaluations", help="Optimiser budget (objective evaluations)."),
        landmark_fit: bool = typer.Option(True, "--landmark-fit/--no-landmark-fit",
                                          help="With --landmarks: the model's interior landmark correction (stored in model.npz), landmark errors held out (k-fold)."),
        folds: int = typer.Option(5, "--folds", help="Folds of the landmark cross-validation."),
        direction_degree: int = typer.Option(3, "--direction-degree", help=DIRECTION_DEGREE_HELP),
        landmark_comparisons: bool = typer.Option(False, "--landmark-comparisons", help="With --landmarks: also the landmark-informed fits of c1…c9 (k-fold, slow) as comparison rows."),
        align: str = typer.Option("apex", "--align", help="apex: rigid alignment on the apex cap (scans with a table shift); "
                                  "joint: a translation per target fitted with the constants, started from apex; "
                                  "none: inputs already in one frame (e.g. synthetic)."),
    ) -> None:
        """Fit c1…c9 of one lung to two or more volumes; write the model, metrics and an HTML report."""

        if evaluations < 1:
            raise InputError(f"--evaluations must be ≥ 1, got {evaluations}")
        vols = None
        if volumes:
            try:
                vols = [float(v) for v in volumes.split(",")]
            except ValueError:
                raise InputError(f"--volumes must be numbers in mL separated by commas, got {volumes!r}") from None
        folder = output_dir(out)
        m = run_fit(list(inputs), side=side, out=folder, volumes=vols, landmarks=list(landmarks) if landmarks else None,
                    grid=grid, stiffness=stiffness, baselines=baselines, max_evaluations=evaluations, progress=say,
                    landmark_fit=landmark_fit, folds=folds, align=align,
                    direction_degree=direction_degree, landmark_comparisons=landmark_comparisons,
                    side_check=side_check)
        _print_table(m)
        typer.echo(f"wrote {folder / 'model.npz'}, {folder / 'metrics.json'}, {folder / 'report.html'}")
        warn(m)


def warn(m: dict) -> None:
    """One line on stderr per input warning of the pipeline and per fit that stopped before
    converging (metrics.json holds them too)."""
    for text in m.get("warnings") or []:
        typer.echo(f"warning: {text}", err=True)
    for name, fit in (m.get("fit") or {}).items():
        if isinstance(fit, dict) and fit.get("success") is False:
            advice = ("it is the paper's comparison search, not the saved model" if name == "grid"
                      else "the model is its best point so far: raise --evaluations")
            typer.echo(f"warning: the {name} fit did not converge ({fit.get('message', 'no message')}); {advice}",
                       err=True)


def _print_table(m: dict) -> None:
    for tname, per in m["targets"].items():
        typer.echo(f"target {tname}: surface mean/rms/p95 mm, landmark mean/median/max mm")
        for name, v in per.items():
            typer.echo(f"  {name:<26} {v['surface_mean_mm']:6.2f} {v['surface_rms_mm']:6.2f} {v['surface_p95_mm']:6.2f}"
                       f"   {v['landmark_mean_mm']:6.2f} {v.get('landmark_median_mm', float('nan')):6.2f}"
                       f" {v['landmark_max_mm']:6.2f}")
