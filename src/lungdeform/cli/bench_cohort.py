"""``lungdeform bench cohort --subjects N --workers 1 --workers 2 [--json FILE]``.

Throughput (subjects per minute) of the cohort fit, in one run: a plain serial loop (the yardstick),
then the Dask path at each worker count (:mod:`lungdeform.bench.cohort`). The ratio to the serial
loop is what to compare across machines (this one is shared and noisy).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Optional

import typer

from lungdeform.bench.cohort import bench_cohort, make_bench_cohort
from lungdeform.cohort.job import FitOptions
from lungdeform.errors import InputError

from .common import say, write_bench_json


def register(apps) -> None:
    @apps.bench.command("cohort")
    def cohort(
        subjects: int = typer.Option(4, "--subjects", "-n", help="Subjects in the generated cohort (one lung each)."),
        workers: list[int] = typer.Option([1, 2], "--workers", help="Dask worker counts (repeat the option)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write results here."),
        evaluations: int = typer.Option(100, "--evaluations", help="Optimiser budget per fit."),
        vertices: Optional[int] = typer.Option(None, "--vertices", help="Decimate the lungs to about this many vertices (default: as embedded, about 3000)."),
        baselines: bool = typer.Option(False, "--baselines/--no-baselines", help="Measure the baselines in each fit too."),
    ):
        """Cohort throughput (subjects/min): a serial loop against Dask at each worker count, same run."""

        if subjects < 1:
            raise InputError(f"--subjects must be at least 1, got {subjects}")
        if any(w < 1 for w in workers):
            raise InputError(f"--workers must be at least 1, got {min(workers)}")
        if vertices is not None and vertices < 100:
            raise InputError(f"--vertices must be at least 100, got {vertices}")
        options = FitOptions(max_evaluations=evaluations, baselines=baselines)
        with tempfile.TemporaryDirectory(prefix="lungdeform-bench-cohort-") as tmp:
            say(f"building a cohort of {subjects} subjects in {tmp}")
            manifest = make_bench_cohort(Path(tmp) / "cohort", subjects, vertices=vertices)
            rows = bench_cohort(manifest, Path(tmp) / "out", list(workers), options, progress=say)
        typer.echo(f"{'method':<8}{'workers':>8}{'subjects':>9}{'ok':>4}{'seconds':>9}{'subj/min':>10}"
                   f"{'ratio':>7}{'overhead s':>11}")
        for r in rows:
            typer.echo(f"{r['method']:<8}{r['workers']:>8}{r['subjects']:>9}{r['ok']:>4}{r['seconds']:>9.1f}"
                       f"{r['subjects_per_min']:>10.2f}{r['ratio_to_serial']:>7.2f}{r['overhead_seconds']:>11.1f}")
        typer.echo("ratio: wall time / serial loop's (below 1: faster); overhead: wall − fit time per worker")
        for r in rows:
            for e in r["errors"]:
                typer.echo(f"failed in the {r['method']} run ({r['workers']} workers): {e}")
        if json_path:
            write_bench_json(json_path, rows, "cohort")
            typer.echo(f"results written to {json_path}")
