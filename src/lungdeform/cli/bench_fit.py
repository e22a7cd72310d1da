"""``lungdeform bench fit``: the model's fit of one COPDgene subject against elastix (Par0011) on the same masks.

The benchmark is :mod:`lungdeform.bench.fit`; the case files and the fit's settings are
``validate copd``'s (:func:`lungdeform.validate.copd.find_cases`, :func:`~lungdeform.validate.copd.copd_config`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import typer

from lungdeform.bench.fit import BenchSettings, CaseFiles, ElastixSchedule, bench_fit
from lungdeform.errors import InputError
from lungdeform.validate.copd import copd_config, find_cases

from .common import say, takes, write_bench_json


def case_files(data: Path, case: str | None) -> CaseFiles:
    """The files of ``case`` (``copdN`` or ``N``; None: the first case) in the COPDgene folder ``data``."""
    number = None
    if case is not None:
        text = case.strip().lower().removeprefix("copd")
        if not text.isdigit() or int(text) < 1:
            raise InputError(f"--case must be a COPDgene case such as copd1 or 1, got {case!r}")
        number = [int(text)]
    name, files = next(iter(find_cases(data, number).items()))
    return CaseFiles(name, *files)


@dataclass(frozen=True, kw_only=True)
class BenchFitOptions:
    """The options of ``lungdeform bench fit`` (an option group of :func:`lungdeform.cli.common.takes`)."""

    data: Annotated[Path, typer.Option("--data", help="Folder with copdN_{exp,insp}_mask.nii.gz and copdN_{exp,insp}_landmarks.txt (validate copd's).")]
    case: Annotated[Optional[str], typer.Option("--case", help="Case to run, e.g. copd1 or 1 (default: the first found).")] = None
    repeats: Annotated[int, typer.Option("--repeats", min=1, help="Timed runs of each, after one untimed warm-up on a phantom (the medians are compared).")] = 3
    threads: Annotated[int, typer.Option("--threads", min=1, help="Threads for both: ITK's pool threader, numba and the BLAS (NumPy's, SciPy's); the model's two lungs at once in two worker processes of one thread each when 2 or more.")] = os.cpu_count() or 1
    one_by_one: Annotated[bool, typer.Option("--one-lung-at-a-time", help="Fit the model's lungs one after the other in this process, with every thread (default with 2 threads or more: both at once, as validate copd --workers 2).")] = False
    evaluations: Annotated[int, typer.Option("--evaluations", min=1, help="The fit's optimiser budget per lung (validate copd's default).")] = 300
    elastix_resolutions: Annotated[Optional[int], typer.Option("--elastix-resolutions", min=1, max=5, hidden=True, help="Quick check only: the last N of Par0011's 5 resolutions.")] = None
    elastix_iterations: Annotated[Optional[int], typer.Option("--elastix-iterations", min=1, hidden=True, help="Quick check only: at most N iterations per resolution.")] = None
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Write results here.")] = None


def register(apps) -> None:
    @apps.bench.command("fit")
    @takes(BenchFitOptions)
    def fit(opts: BenchFitOptions):
        """The model's fit of both lungs (validate copd's settings) against elastix Par0011 (affine, then
        B-spline) on the same masks smoothed by 1.5 mm, same threads: median times, ratio, what each achieved."""

        files = case_files(opts.data, opts.case)
        settings = BenchSettings(opts.repeats, opts.threads,
                                 ElastixSchedule(opts.elastix_resolutions, opts.elastix_iterations),
                                 at_once=not opts.one_by_one)
        r = bench_fit(files, copd_config(opts.evaluations), settings, progress=say)
        load = r["load_average_1min"]
        lungs = (f"the model's lungs at once in {r['model_workers']} worker processes" if r["model_workers"]
                 else "the model's lungs one after the other")
        typer.echo(f"{r['case']}: {r['threads']} threads (ITK {r['itk_threader']} threader; {lungs}), {r['repeats']} "
                   f"repeat(s) after a warm-up; load average {load['start']:.1f} -> {load['end']:.1f}")
        surf = ", ".join(f"{s} {v:.2f}" for s, v in r["model_surface_mean_mm"].items())
        typer.echo(f"  model fit, both lungs: {r['model_median_s']:.1f} s median "
                   f"({', '.join(f'{t:.1f}' for t in r['model_seconds'])}); surface mean distance {surf} mm")
        typer.echo(f"  elastix Par0011:       {r['elastix_median_s']:.1f} s median "
                   f"({', '.join(f'{t:.1f}' for t in r['elastix_seconds'])}); warped-mask symmetric surface distance "
                   f"{', '.join(f'{k} {v:.2f}' for k, v in r['elastix_surface_mean_mm'].items())} mm")
        typer.echo(f"  ratio model / elastix: {r['ratio']:.3f}")
        typer.echo(f"  CPU seconds (the process and its workers, every thread): model {r['model_cpu_median_s']:.1f}, elastix "
                   f"{r['elastix_cpu_median_s']:.1f}; ratio {r['cpu_ratio']:.3f}; BLAS threads {r['blas_threads']}")
        if r["elastix_schedule"] != {"resolutions": None, "iterations": None}:
            typer.echo(f"  (elastix schedule cut for a quick check: {r['elastix_schedule']})")
        if opts.json_path:
            write_bench_json(opts.json_path, [r], "fit")
            typer.echo(f"results written to {opts.json_path}")
