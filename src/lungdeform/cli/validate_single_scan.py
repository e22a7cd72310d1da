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
from lungdeform.geometry.regions import REGIONS
from lungdeform.model.population import resolve_default, save_default
from lungdeform.validate.single_scan import SingleScanConfig, learn_from_folders, run_single_scan
from lungdeform.validate.single_scan_report import row_names
from lungdeform.validate.subjects import find_subjects, incomplete_subjects

from .common import check_output, option_names, output_dir, say

CACHE_HELP = ("Folder where each lung as read and its two-scan fit are kept (pairs/, fits/), under digests of their "
              "inputs: a rerun, another output folder or the other command reuses them (e.g. a shared folder).")


def _fmt(v) -> str:
    return f"{'-':>6s}" if v is None else f"{v:6.2f}"


def print_table(result: dict) -> None:
    """Per lung and the medians: surface / landmark mean error (mm) of each row (``-``: no landmarks)."""
    rows = row_names(result["lungs"])
    typer.echo("surface / landmark mean error (mm) at the larger volume, from the smaller scan alone")
    typer.echo(f"{'lung':16s} " + " ".join(f"{r:>15s}" for r in rows))
    for lung, row in result["lungs"].items():
        mark = "*" if row.get("lung_info", {}).get("cut") else " "
        typer.echo(f"{lung + mark:16s} " + " ".join(
            f"{_fmt(row[r]['surface_mean_mm'])} / {_fmt(row[r].get('landmark_mean_mm'))}" if r in row else f"{'-':>15s}"
            for r in rows))
    s = result["summary"]
    typer.echo(f"{'median (' + str(s['n_lungs']) + ')':16s} " + " ".join(
        f"{_fmt(s[r]['surface_mean_mm'])} / {_fmt(s[r]['landmark_mean_mm'])}" for r in rows))
    if "isotropic" in s:
        typer.echo(f"{'÷ isotropic':16s} " + " ".join(
            f"{_fmt(s[r]['surface_vs_isotropic'])} / {_fmt(s[r]['landmark_vs_isotropic'])}" for r in rows))
    typer.echo(f"landmark medians over the {s['n_lungs_landmarks']} lungs with landmarks; "
               f"* cut by the field of view ({s['n_lungs_cut']}: the cut left out of the surface distance)")
    typer.echo("median distance per surface region (mm; docs/DEFAULTS.md):")
    for region in REGIONS:
        typer.echo(f"{region:16s} " + " ".join(f"{_fmt(s[r]['regions_mm'][region]):>15s}" for r in rows))
    for name, d in result["defaults"].items():
        typer.echo(f"default for {name}: {d['how']} ({d['name']}, {d['digest']})")


def check_folders(folders) -> None:
    """Every folder holds two-volume subjects (a folder without any leaves no output); a subject that
    lacks a file is named, one line each."""
    for folder in folders:
        find_subjects(folder)
        for name, lacks in incomplete_subjects(folder).items():
            typer.echo(f"warning: {folder}: {name}: lacks {'; '.join(lacks)}", err=True)


def register(apps) -> None:
    @apps.validate.command("single-scan")
    def single_scan_command(
        data: list[Path] = typer.Option(..., "--data", help="Folder of two-volume subjects: NAME_exp_mask and "
                                                               "NAME_insp_mask images (.nii.gz, .mha, .nrrd; landmarks "
                                                               "NAME_{exp,insp}_landmarks.txt optional), e.g. the DIR-Lab "
                                                               "COPDgene masks, or the ITK right lung pair; repeat for "
                                                               "several folders."),
        out: Path = typer.Option(..., "--out", help="Output folder: metrics.json, report.html."),
        default: Optional[str] = typer.Option(None, "--default", help="The default scored as 'default': "
                                              "'population' or 'paper' (as they are, for every lung) or a learned "
                                              "default file (JSON). Without it: the shipped default. The shipped "
                                              "default and a file are learned anew without each subject they saw, "
                                              "from their other subjects (leave one subject out)."),
        with_fitted: bool = typer.Option(False, "--with-fitted", help="Add the two-scan fit of each lung (a "
                                                                       "ceiling; slower)."),
        train: Optional[list[Path]] = typer.Option(None, "--train", help="Folder of further two-volume subjects, "
                                                   "not scored, that a leave-one-subject-out default also learns "
                                                   "from when the default saw them (e.g. the COPDgene folder when DIR "
                                                   "is the ITK pair)."),
        cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP + " Default: OUT."),
    ) -> None:
        """Build each lung from its smaller-volume scan alone, predict the larger volume from that volume
        only, and score the defaults (population, Table I) and isotropic scaling on the real surface and
        landmarks."""
        check_folders([*data, *(train or [])])
        if default is not None:
            with option_names({"constants": "--default"}):
                resolve_default(default)
        config = SingleScanConfig(default=default, with_fitted=with_fitted, train=tuple(train or ()), cache=cache)
        check_output(out, [*data, *(train or [])], folder=True, writes=("metrics.json", "report.html", "fits", "pairs"))
        if cache is not None:
            check_output(cache, [*data, *(train or [])], folder=True, writes=("fits", "pairs"), option="--cache")
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
        cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP + " Default: none (every lung fitted)."),
    ) -> None:
        """Learn a population default (c1…c9 and an interior prior, in the lung frame) from every
        two-volume subject in the folders; use it with 'build --constants FILE'."""
        if out.exists() and out.is_dir():
            raise InputError(f"--out {out}: is a folder; name the JSON file to write")
        check_output(out, data)
        if cache is not None:
            check_output(cache, data, folder=True, writes=("fits", "pairs"), option="--cache")
        check_folders(data)  # every folder checked before the (slow) fits
        learned = learn_from_folders(data, name, cache=cache, progress=say)
        path = save_default(out, learned)
        subjects = learned.provenance["subjects"]
        typer.echo(f"learned from {len(learned.provenance['lungs'])} lungs of {len(subjects)} subjects "
                   f"({', '.join(subjects)})")
        c = learned.constants["right"]
        typer.echo("c1…c9 (lung frame): " + " ".join(f"{v:.3f}" for v in c))
        typer.echo(f"wrote {path} (digest {learned.digest})")
