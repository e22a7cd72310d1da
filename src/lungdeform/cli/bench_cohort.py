"""``lungdeform bench cohort --subjects N --workers 1 --workers 2 [--json FILE]``.

Throughput (subjects per minute) of the cohort fit, in one run: a plain serial loop of
:func:`lungdeform.cohort.job.fit_job` in this process (the yardstick), then the Dask path
(:func:`lungdeform.cohort.runner.run_cohort`, a fresh local cluster of worker processes) at each worker
count. The Dask figures include everything a user waits for: cluster start-up, worker imports,
scheduling and the transfer of results. The ratio to the serial loop is what to compare across
machines (this one is shared and noisy).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lungdeform.atomic import write_text
from lungdeform.bench.kernels import lung_with_vertices
from lungdeform.cohort.job import FitOptions, fit_job
from lungdeform.cohort.manifest import read_manifest
from lungdeform.cohort.runner import run_cohort
from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.geometry.mesh import Surface
from lungdeform.io.meshfile import write_mesh
from lungdeform.model.lung import build_lung

from .bench import _write_json
from .common import say

#: Volume added by the model to make each subject's second scan (mL).
INSPIRATION_ML = 400.0


def make_bench_cohort(folder: Path, subjects: int, *, vertices: int | None = None, seed: int = 0) -> Path:
    """Write a cohort of ``subjects`` one-lung subjects into ``folder``; return its manifest.

    Subject ``i`` is an embedded Coronacases lung (:func:`lungdeform.data.default_lungs`; sides
    alternate), optionally decimated to about ``vertices`` vertices, scaled about its centroid by
    a factor in [0.9, 1.1] (end-exhale), and the same surface moved by the model with Table I
    constants by +:data:`INSPIRATION_ML` mL (the second scan). Volumes are left to be measured.
    """

    rng = np.random.default_rng(seed)
    lungs = default_lungs()
    if vertices:
        lungs = {side: lung_with_vertices(vertices, s) for side, s in lungs.items()}
    folder.mkdir(parents=True, exist_ok=True)
    rows = ["subject,side,volume_ml,path"]
    for i in range(subjects):
        side = ("right", "left")[i % 2]
        base = lungs[side]
        c = base.vertices.mean(axis=0)
        ee = Surface(c + (base.vertices - c) * rng.uniform(0.9, 1.1), base.faces, f"bench{i:03d}")
        model = build_lung(ee, side, calibration_ml=INSPIRATION_ML, unit_ml=INSPIRATION_ML)
        name = f"B{i:03d}"
        write_mesh(folder / name / "ee.ply", ee.vertices, ee.faces)
        write_mesh(folder / name / "ei.ply", ee.vertices + model.displacement, ee.faces)
        rows += [f"{name},{side},,{name}/ee.ply", f"{name},{side},,{name}/ei.ply"]
    return write_text(folder / "manifest.csv", "\n".join(rows) + "\n")


def bench_cohort(manifest: Path, work: Path, workers: list[int], options, *, progress=None) -> list[dict]:
    """Serial loop then Dask at each worker count on the same cohort; one record per run."""

    say = progress or (lambda _m: None)
    m = read_manifest(manifest)
    n = len(m.jobs)
    say(f"serial loop: {n} subjects")
    t0 = time.perf_counter()
    serial = [fit_job(job, work / "serial", options) for job in m.jobs]
    serial_s = time.perf_counter() - t0
    rows = [_row("serial", 1, n, serial_s, serial, serial_s)]
    for w in workers:
        say(f"dask: {n} subjects on {w} worker process{'es' if w != 1 else ''}")
        t0 = time.perf_counter()
        r = run_cohort(m, work / f"dask-{w}", workers=w, options=options, population=False)
        rows.append(_row("dask", w, n, time.perf_counter() - t0, list(r.results), serial_s))
    return rows


def _row(method: str, workers: int, n: int, seconds: float, results: list[dict], serial_s: float) -> dict:
    fit_s = sum(r["seconds"] for r in results)
    return {"method": method, "workers": workers, "subjects": n, "ok": sum(r["status"] == "ok" for r in results),
            "seconds": seconds, "subjects_per_min": 60.0 * n / seconds, "ratio_to_serial": seconds / serial_s,
            "speedup_vs_serial": serial_s / seconds, "fit_seconds_sum": fit_s,
            # time not spent inside the fits, per worker: start-up, imports, scheduling, transfers
            "overhead_seconds": seconds - fit_s / workers,
            "errors": [f"{r['subject']}/{r['side']}: {r['error_type']}: {r['error']}" for r in results
                       if r["status"] != "ok"]}


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
            _write_json(json_path, rows, "cohort")
            typer.echo(f"results written to {json_path}")
