"""``lungdeform validate single-scan`` and ``lungdeform learn-default``: the population default.

The experiment and the learning are :mod:`lungdeform.validate.single_scan` (what is learned:
:mod:`lungdeform.cohort.default`); this module parses the options, prints the table and picks the
exit code.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lungdeform.errors import InputError
from lungdeform.model.population import resolve_default, save_default
from lungdeform.validate.single_scan import ROWS, SingleScanConfig, find_subjects, learn_from_folders, run_single_scan

from .common import check_output, option_names, output_dir, say


def print_table(result: dict) -> None:
    """Per lung and the medians: surface / landmark mean error (mm) of each row."""
    rows = [r for r in ROWS if r in result["summary"]]
    typer.echo("surface / landmark mean error (mm) at the larger volume, from the smaller scan alone")
    typer.echo(f"{'lung':14s} " + " ".join(f"{r:>15s}" for r in rows))
    for lung, row in result["lungs"].items():
        typer.echo(f"{lung:14s} " + " ".join(
            f"{row[r]['surface_mean_mm']:6.2f} / {row[r]['landmark_mean_mm']:6.2f}" if r in row else f"{'-':>15s}"
            for r in rows))
    s = result["summary"]
    typer.echo(f"{'median (' + str(s['n_lungs']) + ')':14s} " + " ".join(
        f"{s[r]['surface_mean_mm']:6.2f} / {s[r]['landmark_mean_mm']:6.2f}" for r in rows))
    if "isotropic" in s:
        typer.echo(f"{'÷ isotropic':14s} " + " ".join(
            f"{s[r]['surface_vs_isotropic']:6.2f} / {s[r]['landmark_vs_isotropic']:6.2f}" for r in rows))
    for name, d in result["defaults"].items():
        typer.echo(f"default for {name}: {d['how']} ({d['name']}, {d['digest']})")


def register(apps) -> None:
    @apps.validate.command("single-scan")
    def single_scan_command(
        data: Path = typer.Option(..., "--data", help="Folder of two-volume subjects: DIR-Lab COPDgene masks "
                                                        "(copdN_{exp,insp}_mask.nii.gz and landmarks) or the ITK "
                                                        "right lung pair."),
        out: Path = typer.Option(..., "--out", help="Output folder: metrics.json, report.html."),
        default: Optional[str] = typer.Option(None, "--default", help="The default scored as 'default': "
                                              "'population', 'paper' or a learned default file (JSON). Without "
                                              "it: the shipped default, learned leave one subject out for the "
                                              "subjects it was learned from."),
        with_fitted: bool = typer.Option(False, "--with-fitted", help="Add the two-scan fit of each lung (a "
                                                                       "ceiling; slower)."),
        train: Optional[list[Path]] = typer.Option(None, "--train", help="Folder of further two-volume subjects, "
                                                   "not scored, that a leave-one-subject-out default also learns "
                                                   "from (e.g. the COPDgene folder when DIR is the ITK pair)."),
    ) -> None:
        """Build each lung from its smaller-volume scan alone, predict the larger volume from that volume
        only, and score the defaults (population, Table I) and isotropic scaling on the real surface and
        landmarks."""
        for folder in [data, *(train or [])]:
            find_subjects(folder)  # a folder without subjects leaves no output folder
        if default is not None:
            with option_names({"constants": "--default"}):
                resolve_default(default)
        config = SingleScanConfig(default=default, with_fitted=with_fitted, train=tuple(train or ()))
        check_output(out, [data, *(train or [])], folder=True, writes=("metrics.json", "report.html", "fits"))
        folder = output_dir(out)
        result = run_single_scan(data, folder, config, progress=say)
        print_table(result)
        typer.echo(f"wrote {folder / 'metrics.json'}, {folder / 'report.html'}")

    @apps.root.command("learn-default")
    def learn_default_command(
        data: list[Path] = typer.Option(..., "--data", help="Folder of two-volume subjects (as for 'validate "
                                                              "single-scan'); repeat for several folders."),
        out: Path = typer.Option(..., "--out", help="The learned default to write (JSON)."),
        name: str = typer.Option("population", "--name", help="Name recorded in the file and in every model "
                                                               "built with it."),
    ) -> None:
        """Learn a population default (c1…c9 and a direction correction, in the lung frame) from every
        two-volume subject in the folders; use it with 'build --constants FILE'."""
        if out.exists() and out.is_dir():
            raise InputError(f"--out {out}: is a folder; name the JSON file to write")
        check_output(out, data)
        for folder in data:
            find_subjects(folder)  # every folder checked before the (slow) fits
        learned = learn_from_folders(data, name, progress=say)
        path = save_default(out, learned)
        subjects = learned.provenance["subjects"]
        typer.echo(f"learned from {len(learned.provenance['lungs'])} lungs of {len(subjects)} subjects "
                   f"({', '.join(subjects)})")
        c = learned.constants["right"]
        typer.echo("c1…c9 (lung frame): " + " ".join(f"{v:.3f}" for v in c))
        typer.echo(f"wrote {path} (digest {learned.digest})")
