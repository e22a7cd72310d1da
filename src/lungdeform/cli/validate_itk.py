"""``lungdeform validate itk-pair``: fit and measure the model on the ITK right lung at two volumes.

The experiment (data, fit, targets) is :mod:`lungdeform.validate.itk_pair`; this module parses the
options, prints the table, the protocols and the targets with pass/fail, and picks the exit code
(0 when the run completes; with ``--strict``, 3 when a target is not met).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.atomic import staged_dir
from lungdeform.validate.itk_pair import find_pair, pair_config, run_itk_pair

from .common import (
    DIRECTION_DEGREE_HELP,
    FIT_OPTIONS,
    STRICT_EXIT,
    check_output,
    option_names,
    print_fit_table,
    print_fit_warnings,
    say,
    takes,
)


@dataclass(frozen=True, kw_only=True)
class ItkPairOptions:
    """The options of ``lungdeform validate itk-pair`` (:func:`register`)."""

    data: Annotated[Path, typer.Option("--data", help="Folder with the ITK right-lung pair (or its parent).")]
    out: Annotated[Path, typer.Option("--out", help="Output folder: metrics.json, model.npz, report.html.")]
    grid: Annotated[bool, typer.Option("--grid/--no-grid", help="Also run the grid mode for comparison.")] = True
    stiffness: Annotated[bool, typer.Option("--stiffness/--no-stiffness", help="Also fit a stiffness field (the paper's uniform model is then reported as model_uniform_stiffness).")] = True
    evaluations: Annotated[int, typer.Option("--evaluations", help="Optimiser budget.")] = 300
    landmark_fit: Annotated[bool, typer.Option("--landmark-fit/--no-landmark-fit", help="With the landmarks: the model's interior landmark correction, and the landmark-informed comparison fits (slower), scored held out (k-fold).")] = True
    folds: Annotated[int, typer.Option("--folds", help="Folds of the landmark cross-validation.")] = 5
    direction_degree: Annotated[int, typer.Option("--direction-degree", help=DIRECTION_DEGREE_HELP)] = 3
    strict: Annotated[bool, typer.Option("--strict", help="Exit with code 3 when a target is not met (for CI).")] = False


def register(apps) -> None:
    @apps.validate.command("itk-pair")
    @takes(ItkPairOptions)
    def itk_pair_command(opts: ItkPairOptions) -> None:
        """Fit the model to the ITK right lung (3.36 → 3.97 L) and compare with baselines."""
        check_output(opts.out, [opts.data], folder=True)

        files = find_pair(opts.data)
        with option_names(FIT_OPTIONS):
            config = pair_config(grid=opts.grid, stiffness=opts.stiffness, max_evaluations=opts.evaluations,
                                 landmark_fit=opts.landmark_fit, folds=opts.folds, direction_degree=opts.direction_degree)
            folder = opts.out
            with staged_dir(folder) as staged:  # metrics, model and report together at the end, or none
                metrics = run_itk_pair(files, staged, config, progress=say)
        print_fit_table(metrics)
        print_fit_warnings(metrics)
        for name, text in metrics.get("protocols", {}).items():
            typer.echo(f"  {name}: {text}")
        rays = metrics["ray_throughput"]
        typer.echo(f"ray casting: {rays['rays_per_s'] / 1e6:.2f} M rays/s (1 M rays, {rays['faces']} faces)")
        for name, ok in metrics["targets_met"].items():
            typer.echo(f"target {name}: {'met' if ok else 'NOT met'}")
        typer.echo(f"wrote {folder / 'metrics.json'}, {folder / 'model.npz'}, {folder / 'report.html'}")
        if opts.strict and not all(metrics["targets_met"].values()):
            raise typer.Exit(STRICT_EXIT)
