"""``lungdeform fit``: fit a lung model to surfaces, masks or CTs at two or more volumes.

The pipeline itself (reading, alignment, fits, baselines, outputs) is
:func:`lungdeform.evaluate.pipeline.run_fit`; this module parses the options into its
:class:`~lungdeform.fit.config.FitInputs` and :class:`~lungdeform.fit.config.FitConfig` and prints the table.
"""

from __future__ import annotations

from pathlib import Path

import typer

from lungdeform.errors import InputError
from lungdeform.evaluate.pipeline import check_prior, run_fit
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.fit.cycle import HysteresisPair
from lungdeform.interior.motion_prior import load_prior

from .common import (
    DIRECTION_DEGREE_HELP,
    FIT_OPTIONS,
    SIDE_CHECK_HELP,
    bounded,
    check_output,
    option_names,
    print_fit_table,
    print_fit_warnings,
    say,
)

#: The files fit writes in ``--out``.
FIT_FILES = ("model.npz", "metrics.json", "report.html", "landmarks.npz")


def register(apps) -> None:
    @apps.root.command("fit")
    def fit_command(
        inputs: list[Path] = typer.Argument(..., help="Surfaces, masks or CTs of one lung, end-exhale first, volumes increasing (equal ones allowed); or one folder holding a 4-D CT (all phases of a cycle, docs/FITTING.md, \"4-D CT input\")."),
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
        align: str = typer.Option("auto", "--align", help="auto (default): none when every phase of a 4-D CT shares one DICOM "
                                  "Frame of Reference, else apex; apex: rigid alignment on the apex cap (scans with a table shift); "
                                  "joint: a translation per target fitted with the constants, started from apex; "
                                  "none: inputs already in one frame (e.g. synthetic). docs/FITTING.md, \"4-D CT input\"."),
        interior: str = typer.Option("auto", "--interior",
                                     help="Surface part of the interior field: correspondence (a smooth map of the "
                                          "end-exhale lung onto the largest volume's), sliding (the sliding "
                                          "interpolation of the fitted surface's normal motion) or auto "
                                          "(correspondence unless the scans are cropped)."),
        motion_prior: Path | None = typer.Option(None, "--motion-prior",
                                                 help="A population motion prior (JSON, e.g. the motion_prior.json "
                                                      "of validate copd) folded into the correspondence field."),
        refine_mm: float = typer.Option(5.0, "--refine-mm", callback=bounded(0, 100, "mm"),
                                        help="Finest smoothing width (mm) of the surface refinement, which brings "
                                             "the fitted displacement onto the target surfaces (docs/FITTING.md); "
                                             "0: none (the fitted k·F·d only)."),
    ) -> None:
        """Fit c1…c9 of one lung to two or more volumes; write the model, metrics and an HTML report."""

        vols = None
        if volumes:
            try:
                vols = [float(v) for v in volumes.split(",")]
            except ValueError:
                raise InputError(f"--volumes must be numbers in mL separated by commas, got {volumes!r}") from None
        with option_names(FIT_OPTIONS):
            fit_inputs = FitInputs(inputs, side, vols, landmarks)
            config = FitConfig(grid=grid, stiffness=stiffness, baselines=baselines, max_evaluations=evaluations,
                               landmark_fit=landmark_fit, folds=folds, align=align, direction_degree=direction_degree,
                               landmark_comparisons=landmark_comparisons, side_check=side_check, interior=interior,
                               refine_mm=refine_mm)
            prior = None if motion_prior is None else load_prior(motion_prior)
            check_prior(config, prior)
            # created by run_fit once the inputs are read: a bad input leaves no folder
            folder = check_output(out, [*inputs, *(landmarks or []), motion_prior], folder=True, writes=FIT_FILES)
            m = run_fit(fit_inputs, folder, config, progress=say, prior=prior)
        for text in m.get("notes") or []:
            typer.echo(f"note: {text}")
        choice = m["alignment_choice"]
        typer.echo(f"alignment: {choice['used']} ({choice['why']})")
        for pair in (m.get("cycle") or {}).get("hysteresis", []):
            typer.echo(f"hysteresis: {hysteresis_line(pair)}")
        if m.get("cycle") and not m["cycle"]["hysteresis"]:
            typer.echo("hysteresis: no phase on the exhale branch (volumes monotone in phase order)")
        print_fit_table(m)
        typer.echo(f"wrote {folder / 'model.npz'}, {folder / 'metrics.json'}, {folder / 'report.html'}")
        print_fit_warnings(m)


def hysteresis_line(pair: dict) -> str:
    """One line of ``metrics["cycle"]["hysteresis"]`` (:class:`lungdeform.fit.cycle.HysteresisPair`)."""
    return HysteresisPair(**pair).line()
