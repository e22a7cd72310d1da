"""``lungdeform fit``: fit a lung model to surfaces, masks or CTs at two or more volumes.

The pipeline itself (reading, alignment, fits, baselines, outputs) is
:func:`lungdeform.evaluate.pipeline.run_fit`; this module parses the options into its
:class:`~lungdeform.fit.config.FitInputs` and :class:`~lungdeform.fit.config.FitConfig` and prints the table.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.atomic import staged_dir
from lungdeform.errors import InputError
from lungdeform.evaluate.pipeline import check_prior, run_fit
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.fit.cycle import HysteresisPair
from lungdeform.interior.motion_prior import load_prior

from .common import (
    DIRECTION_DEGREE_HELP,
    FIT_OPTIONS,
    SIDE_CHECK_HELP,
    SeriesFlags,
    bounded,
    check_output,
    dicom_input,
    option_names,
    print_fit_table,
    print_fit_warnings,
    say,
    takes,
)

#: The files fit writes in ``--out``.
FIT_FILES = ("model.npz", "metrics.json", "report.html", "landmarks.npz")


@dataclass(frozen=True, kw_only=True)
class FitOptions:
    """The options of ``lungdeform fit`` (:func:`register`)."""

    inputs: Annotated[list[Path], typer.Argument(help="Surfaces, masks or CTs of one lung, end-exhale first, volumes increasing (equal ones allowed); or one folder holding a 4-D CT (all phases of a cycle, docs/FITTING.md, \"4-D CT input\").")]
    out: Annotated[Path, typer.Option("--out", help="Output folder: model.npz, metrics.json, report.html.")]
    side: Annotated[str, typer.Option("--side", help="'left' or 'right'.")]
    side_check: Annotated[bool, typer.Option("--side-check/--no-side-check", help=SIDE_CHECK_HELP)] = True
    volumes: Annotated[str, typer.Option("--volumes", help="Lung volumes in mL, comma-separated (default: measured from the surfaces).")] = None
    landmarks: Annotated[list[Path], typer.Option("--landmarks", help="elastix point-set file per input (world mm), rows corresponding.")] = None
    grid: Annotated[bool, typer.Option("--grid", help="Also run the paper's grid search (step 0.01) for comparison.")] = False
    stiffness: Annotated[bool, typer.Option("--stiffness/--no-stiffness", help="Fit a heterogeneous stiffness field (inverse expandability), kept only if it lowers the objective; --no-stiffness: uniform, faster.")] = True
    baselines: Annotated[bool, typer.Option("--baselines/--no-baselines", help="Measure the baselines too.")] = True
    evaluations: Annotated[int, typer.Option("--evaluations", help="Optimiser budget (objective evaluations).")] = 300
    landmark_fit: Annotated[bool, typer.Option("--landmark-fit/--no-landmark-fit", help="With --landmarks: the model's interior landmark correction (stored in model.npz), landmark errors held out (k-fold).")] = True
    folds: Annotated[int, typer.Option("--folds", help="Folds of the landmark cross-validation.")] = 5
    direction_degree: Annotated[int, typer.Option("--direction-degree", help=DIRECTION_DEGREE_HELP)] = 3
    landmark_comparisons: Annotated[bool, typer.Option("--landmark-comparisons", help="With --landmarks: also the landmark-informed fits of c1…c9 (k-fold, slow) as comparison rows.")] = False
    align: Annotated[str, typer.Option("--align", help="auto (default): none when every phase of a 4-D CT shares one DICOM "
        "Frame of Reference, else apex; apex: rigid alignment on the apex cap (scans with a table shift); "
        "joint: a translation per target fitted with the constants, started from apex; "
        "none: inputs already in one frame (e.g. synthetic). docs/FITTING.md, \"4-D CT input\".")] = "auto"
    interior: Annotated[str, typer.Option("--interior", help="Surface part of the interior field: correspondence (a smooth map of the "
        "end-exhale lung onto the largest volume's), sliding (the sliding "
        "interpolation of the fitted surface's normal motion) or auto "
        "(correspondence unless the scans are cropped).")] = "auto"
    motion_prior: Annotated[Path | None, typer.Option("--motion-prior", help="A population motion prior (JSON, e.g. the motion_prior.json "
        "of validate copd) added to the correspondence field, tapered to zero at the surface (30 mm).")] = None
    refine_mm: Annotated[float, typer.Option("--refine-mm", callback=bounded(0, 100, "mm"), help="Finest smoothing width (mm) of the surface refinement, which brings "
        "the fitted displacement onto the target surfaces (docs/FITTING.md); "
        "0: none (the fitted k·F·d only).")] = 5.0
    dicom: SeriesFlags = SeriesFlags()  # --series / --series-description: in every input folder holding several CT series


def register(apps) -> None:
    @apps.root.command("fit")
    @takes(FitOptions)
    def fit_command(opts: FitOptions) -> None:
        """Fit c1…c9 of one lung to two or more volumes; write the model, metrics and an HTML report."""

        vols = None
        if opts.volumes:
            try:
                vols = [float(v) for v in opts.volumes.split(",")]
            except ValueError:
                raise InputError(f"--volumes must be numbers in mL separated by commas, got {opts.volumes!r}") from None
        series = opts.dicom.choice(several_only=True)
        if series is not None and len(opts.inputs) == 1:
            raise InputError(f"{series}: one input is a 4-D CT folder, whose series are its phases; --series and "
                             "--series-description choose among the series of an input folder of two or more inputs")
        for path in opts.inputs if len(opts.inputs) > 1 else []:  # one folder is a 4-D CT: its phases are its series
            dicom_input(path, series)
        with option_names(FIT_OPTIONS):
            fit_inputs = FitInputs(opts.inputs, opts.side, vols, opts.landmarks, series=series)
            config = FitConfig(grid=opts.grid, stiffness=opts.stiffness, baselines=opts.baselines, max_evaluations=opts.evaluations,
                               landmark_fit=opts.landmark_fit, folds=opts.folds, align=opts.align, direction_degree=opts.direction_degree,
                               landmark_comparisons=opts.landmark_comparisons, side_check=opts.side_check, interior=opts.interior,
                               refine_mm=opts.refine_mm)
            prior = None if opts.motion_prior is None else load_prior(opts.motion_prior)
            check_prior(config, prior)
            # created by run_fit once the inputs are read: a bad input leaves no folder
            folder = check_output(opts.out, [*opts.inputs, *(opts.landmarks or []), opts.motion_prior], folder=True, writes=FIT_FILES)
            with staged_dir(folder) as staged:  # model, metrics and report appear together at the end, or none
                m = run_fit(fit_inputs, staged, config, progress=say, prior=prior)
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
