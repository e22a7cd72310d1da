"""``lungdeform bench fit``: the model's fit of one COPDgene subject against elastix (Par0011) on the same masks.

The benchmark is :mod:`lungdeform.bench.fit`; the case files and the fit's settings are
``validate copd``'s (:func:`lungdeform.validate.copd.find_cases`, :func:`~lungdeform.validate.copd.copd_config`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer

from lungdeform.bench.fit import BenchSettings, CaseFiles, ElastixSchedule, bench_fit
from lungdeform.errors import InputError
from lungdeform.validate.copd import copd_config, find_cases

from .common import say, write_bench_json


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


def register(apps) -> None:
    @apps.bench.command("fit")
    def fit(
        data: Path = typer.Option(..., "--data", help="Folder with copdN_{exp,insp}_mask.nii.gz and copdN_{exp,insp}_landmarks.txt (validate copd's)."),
        case: Optional[str] = typer.Option(None, "--case", help="Case to run, e.g. copd1 or 1 (default: the first found)."),
        repeats: int = typer.Option(3, "--repeats", min=1, help="Timed runs of each, after one untimed warm-up on a phantom (the medians are compared)."),
        threads: int = typer.Option(os.cpu_count() or 1, "--threads", min=1, help="Threads for both: ITK's pool threader, numba and the BLAS (NumPy's, SciPy's)."),
        evaluations: int = typer.Option(300, "--evaluations", min=1, help="The fit's optimiser budget per lung (validate copd's default)."),
        elastix_resolutions: Optional[int] = typer.Option(None, "--elastix-resolutions", min=1, max=5, hidden=True, help="Quick check only: the last N of Par0011's 5 resolutions."),
        elastix_iterations: Optional[int] = typer.Option(None, "--elastix-iterations", min=1, hidden=True, help="Quick check only: at most N iterations per resolution."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write results here."),
    ):
        """The model's fit of both lungs (validate copd's settings) against elastix Par0011 (affine, then
        B-spline) on the same masks smoothed by 1.5 mm, same threads: median times, ratio, what each achieved."""

        files = case_files(data, case)
        settings = BenchSettings(repeats, threads, ElastixSchedule(elastix_resolutions, elastix_iterations))
        r = bench_fit(files, copd_config(evaluations), settings, progress=say)
        load = r["load_average_1min"]
        typer.echo(f"{r['case']}: {r['threads']} threads (ITK {r['itk_threader']} threader), {r['repeats']} repeat(s) "
                   f"after a warm-up; load average {load['start']:.1f} -> {load['end']:.1f}")
        surf = ", ".join(f"{s} {v:.2f}" for s, v in r["model_surface_mean_mm"].items())
        typer.echo(f"  model fit, both lungs: {r['model_median_s']:.1f} s median "
                   f"({', '.join(f'{t:.1f}' for t in r['model_seconds'])}); surface mean distance {surf} mm")
        typer.echo(f"  elastix Par0011:       {r['elastix_median_s']:.1f} s median "
                   f"({', '.join(f'{t:.1f}' for t in r['elastix_seconds'])}); warped-mask symmetric surface distance "
                   f"{', '.join(f'{k} {v:.2f}' for k, v in r['elastix_surface_mean_mm'].items())} mm")
        typer.echo(f"  ratio model / elastix: {r['ratio']:.3f}")
        typer.echo(f"  CPU seconds (the process, every thread): model {r['model_cpu_median_s']:.1f}, elastix "
                   f"{r['elastix_cpu_median_s']:.1f}; ratio {r['cpu_ratio']:.3f}; BLAS threads {r['blas_threads']}")
        if r["elastix_schedule"] != {"resolutions": None, "iterations": None}:
            typer.echo(f"  (elastix schedule cut for a quick check: {r['elastix_schedule']})")
        if json_path:
            write_bench_json(json_path, [r], "fit")
            typer.echo(f"results written to {json_path}")
