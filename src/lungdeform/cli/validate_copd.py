"""``lungdeform validate copd``: the model fitted per lung on the DIR-Lab COPDgene lung masks.

The experiment is :mod:`lungdeform.validate.copd`; this module parses the options, prints the
per-lung table and the medians, and picks the exit code.
"""

from __future__ import annotations

import shlex
from pathlib import Path

import typer

from lungdeform.atomic import made_folder
from lungdeform.errors import InputError
from lungdeform.validate.copd import (
    COHORT_OPTIONS,
    TABLE_ROWS,
    copd_config,
    find_cases,
    incomplete_cases,
    parse_cases,
    run_copd,
)
from lungdeform.validate.subjects import find_subjects, incomplete_subjects, write_cohort_manifest

from .common import FIT_OPTIONS, check_output, option_names, say

#: The files validate copd writes in ``--out`` (beside a folder per case).
COPD_FILES = ("metrics.json", "report.html", "manifest.csv")


def _fmt(v) -> str:
    return "     -" if v is None else f"{v:6.2f}"


def print_table(result: dict) -> None:
    """One line per lung and the medians: landmark mean error (mm) per method, the model's surface
    mean error and the seconds."""
    names = list(TABLE_ROWS)
    typer.echo("landmark mean error (mm), expiration → inspiration; model_surface = the model's surface mean (mm)")
    typer.echo(f"{'lung':14s} " + " ".join(f"{n[:20]:>20s}" for n in names) + f" {'model_surface':>13s} {'s':>6s}")
    rows = [(f"{c} {s}", r) for c, case in result["cases"].items() for s, r in case.items()]
    rows.append((f"median ({result['summary']['n_lungs']})", result["summary"]))
    for label, r in rows:
        cells = " ".join(f"{_fmt(r.get(n, {}).get('landmark_mean_mm')):>20s}" for n in names)
        typer.echo(f"{label:14s} {cells} {_fmt(r.get('model', {}).get('surface_mean_mm')):>13s} "
                   f"{_fmt(r.get('seconds')):>6s}")


def register(apps) -> None:
    @apps.validate.command("copd")
    def copd_command(
        data: Path = typer.Option(..., "--data", help="Folder with copdN_{exp,insp}_mask.nii.gz and "
                                                        "copdN_{exp,insp}_landmarks.txt (with --manifest-only: any "
                                                        "folder of NAME_exp_mask / NAME_insp_mask pairs, landmarks "
                                                        "optional)."),
        out: Path = typer.Option(..., "--out", help="Output folder: copdN/<side>/ per lung, metrics.json, "
                                                      "report.html."),
        cases: str = typer.Option(None, "--cases", help="Case numbers to run, e.g. 1,3 (default: every case found)."),
        evaluations: int = typer.Option(300, "--evaluations", help="Optimiser budget per lung."),
        workers: int = typer.Option(1, "--workers", min=1, help="Worker processes: 2 fits a case's two lungs at once "
                                                                  "(one core each; default 1: one after the other)."),
        manifest_only: bool = typer.Option(False, "--manifest-only",
                                           help="Fit nothing: write OUT/manifest.csv, these cases as a manifest for "
                                                "'lungdeform cohort' (population statistics against Table I), and "
                                                "print the cohort command."),
    ) -> None:
        """Fit both lungs of every DIR-Lab COPDgene case (expiration → inspiration, translation fitted)
        and compare with mask-only baselines; a lung already fitted with the same settings is kept."""
        with option_names({**FIT_OPTIONS, "cases": "--cases"}):
            config = copd_config(evaluations)
            wanted = parse_cases(cases)
            check_output(out, [data], folder=True, writes=COPD_FILES)
            if manifest_only:
                _write_manifest(_manifest_subjects(data, wanted), out, evaluations)
                return
            find_cases(data, wanted)  # a bad data folder leaves no output folder
            for name, missing in incomplete_cases(data, wanted).items():
                typer.echo(f"warning: {data}: {name} skipped: it lacks {', '.join(missing)}", err=True)
            with made_folder(out) as folder:  # a refused run leaves no folder; a finished lung is kept (resumed)
                result = run_copd(data, folder, config, wanted, progress=say, workers=workers)
        print_table(result)
        wall = result["summary"].get("model_fit_wall_seconds")
        if wall is not None:
            typer.echo(f"the model's fit of a case, both lungs at once: {wall:.1f} s wall (median over the cases)")
        done = result["refitted"]
        typer.echo(f"fitted {len(done)} lung(s) this run" + (f" ({', '.join(done)})" if done else " (all resumed)"))
        typer.echo(f"wrote {folder / 'metrics.json'}, {folder / 'report.html'}")


def _manifest_subjects(data: Path, wanted: list[int] | None):
    """The two-volume subjects of ``data`` (:func:`lungdeform.validate.subjects.find_subjects`; a subject
    lacking a file named, one line each), or the cases ``copdN`` numbered in ``wanted``, all of which
    must be there (a bad data folder leaves no output folder)."""
    found = find_subjects(data)
    lacking = incomplete_subjects(data)
    if wanted is not None:
        names = {s.name for s in found}
        for n in wanted:
            if f"copd{n}" not in names:
                raise InputError(f"{data}: case {n} is missing (no copd{n}_exp_mask and copd{n}_insp_mask)")
        found = [s for s in found if s.name in {f"copd{n}" for n in wanted}]
        lacking = {k: v for k, v in lacking.items() if k in {s.name for s in found}}
    for name, lacks in lacking.items():
        typer.echo(f"warning: {data}: {name}: lacks {'; '.join(lacks)}", err=True)
    return found


def _write_manifest(found, out: Path, evaluations: int) -> None:
    """``--manifest-only``: OUT/manifest.csv for ``lungdeform cohort`` of the subjects ``found``
    (:func:`lungdeform.validate.subjects.find_subjects`), and the command that fits it."""
    path = write_cohort_manifest(found, Path(out) / "manifest.csv")  # its folder made by the atomic write
    budget = [] if evaluations == 300 else ["--evaluations", str(evaluations)]
    command = ["lungdeform", "cohort", str(path), "--out", str(Path(out) / "cohort"), *COHORT_OPTIONS, *budget]
    typer.echo(f"wrote {path}")
    typer.echo(f"fit with: {shlex.join(command)}")
