"""Cohort-fit throughput: a serial loop (the yardstick) against the Dask path at each worker count.

:func:`make_bench_cohort` writes a cohort of one-lung subjects from the embedded lungs;
:func:`bench_cohort` times, on that cohort and in one run, a plain serial loop of
:func:`lungdeform.cohort.job.fit_job` in this process, then :func:`lungdeform.cohort.runner.run_cohort`
(a fresh local cluster of worker processes) at each worker count. The Dask figures include
everything a user waits for: cluster start-up, worker imports, scheduling and the transfer of
results. The ratio to the serial loop is what to compare across machines (they are shared and noisy).

Each record (:func:`throughput_record`): ``method`` ("serial" or "dask"), ``workers``, ``subjects``,
``ok`` (fits that succeeded), ``seconds`` (wall), ``subjects_per_min``, ``ratio_to_serial`` and
``speedup_vs_serial`` (against the serial loop of the same run), ``fit_seconds_sum`` (time inside
the fits), ``overhead_seconds`` (wall − fit time per worker) and ``errors`` (one line per failed fit).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_text
from lungdeform.cohort.job import FitOptions, fit_job
from lungdeform.cohort.manifest import read_manifest
from lungdeform.cohort.runner import Cluster, run_cohort
from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.geometry.mesh import Surface
from lungdeform.io.meshfile import write_mesh
from lungdeform.model.lung import BuildSettings, build_lung
from lungdeform.progress import Progress, silent

from .kernels import lung_with_vertices

#: Volume added by the model to make each subject's second scan (mL).
INSPIRATION_ML = 400.0


def make_bench_cohort(folder: Path, subjects: int, *, vertices: int | None = None, seed: int = 0) -> Path:
    """Write a cohort of ``subjects`` one-lung subjects into ``folder``; return its manifest.

    Subject ``i`` is an embedded Coronacases lung (:func:`lungdeform.data.default_lungs`; sides
    alternate), optionally decimated to about ``vertices`` vertices, scaled about its centroid by
    a factor in [0.9, 1.1] (end-exhale), and the same surface moved by the model with Table I
    constants by +:data:`INSPIRATION_ML` mL (the second scan). Volumes are left to be measured.
    """
    if subjects < 1:
        raise InputError(f"subjects must be at least 1, got {subjects}")
    rng = np.random.default_rng(seed)
    lungs = default_lungs()
    if vertices:
        lungs = {side: lung_with_vertices(vertices, s) for side, s in lungs.items()}
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows = ["subject,side,volume_ml,path"]
    for i in range(subjects):
        side = ("right", "left")[i % 2]
        base = lungs[side]
        c = base.vertices.mean(axis=0)
        ee = Surface(c + (base.vertices - c) * rng.uniform(0.9, 1.1), base.faces, f"bench{i:03d}")
        model = build_lung(ee, side, settings=BuildSettings(INSPIRATION_ML, INSPIRATION_ML))
        name = f"B{i:03d}"
        write_mesh(folder / name / "ee.ply", ee.vertices, ee.faces)
        write_mesh(folder / name / "ei.ply", ee.vertices + model.displacement, ee.faces)
        rows += [f"{name},{side},,{name}/ee.ply", f"{name},{side},,{name}/ei.ply"]
    return write_text(folder / "manifest.csv", "\n".join(rows) + "\n")


def bench_cohort(manifest: Path, work: Path, workers: list[int], options: FitOptions, *,
                 progress: Progress | None = None) -> list[dict]:
    """Serial loop then Dask at each of ``workers`` (counts ≥ 1) on the same cohort, results under
    ``work``; one :func:`throughput_record` per run, the serial loop's first."""
    if any(w < 1 for w in workers):
        raise InputError(f"workers must be at least 1, got {min(workers)}")
    say = progress or silent
    work = Path(work)
    m = read_manifest(manifest)
    n = len(m.jobs)
    say(f"serial loop: {n} subjects")
    t0 = time.perf_counter()
    serial = [fit_job(job, work / "serial", options) for job in m.jobs]
    serial_s = time.perf_counter() - t0
    rows = [throughput_record("serial", 1, n, serial_s, serial, serial_s)]
    for w in workers:
        say(f"dask: {n} subjects on {w} worker process{'es' if w != 1 else ''}")
        t0 = time.perf_counter()
        r = run_cohort(m, work / f"dask-{w}", cluster=Cluster(workers=w), options=options, population=False)
        rows.append(throughput_record("dask", w, n, time.perf_counter() - t0, list(r.results), serial_s))
    return rows


def throughput_record(method: str, workers: int, n: int, seconds: float, results: list[dict],
                      serial_s: float) -> dict:
    """The record of one run of ``n`` subjects in ``seconds`` (wall), against the serial loop's
    ``serial_s`` of the same run; ``results`` are the fits' records (``seconds``, ``status``, …)."""
    fit_s = sum(r["seconds"] for r in results)
    return {"method": method, "workers": workers, "subjects": n, "ok": sum(r["status"] == "ok" for r in results),
            "seconds": seconds, "subjects_per_min": 60.0 * n / seconds, "ratio_to_serial": seconds / serial_s,
            "speedup_vs_serial": serial_s / seconds, "fit_seconds_sum": fit_s,
            # time not spent inside the fits, per worker: start-up, imports, scheduling, transfers
            "overhead_seconds": seconds - fit_s / workers,
            "errors": [f"{r['subject']}/{r['side']}: {r['error_type']}: {r['error']}" for r in results
                       if r["status"] != "ok"]}
