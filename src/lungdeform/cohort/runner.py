"""Fit every lung of a cohort on Dask (dask.distributed), resumably, one folder per lung.

Layout of the output folder ``OUT``::

    OUT/cohort.json                         summary of the last run (jobs, statuses, timings)
    OUT/subjects/<subject>/<side>/          one finished job: result.json (+ model.npz,
                                            metrics.json, report.html when the fit succeeded)

One job (one lung: its fit, its ``result.json`` record and schema, the fit options, the input
digest and the atomic publish of its folder) is :mod:`lungdeform.cohort.job`. The temporary and
moved-aside folders a killed run leaves are removed at the start of the next run
(:func:`clean_stale`).

Resuming: a job whose folder holds an ``ok`` result with the same
:func:`~lungdeform.cohort.job.input_digest` is skipped; failed jobs are run again unless
``skip_failed``. A run holds an exclusive lock on ``OUT/.lock`` so two runs never share an output
folder.

Progress: ``progress(event: dict)`` is called on the calling thread with
``{"event": "start", "jobs", "to_run", "skipped", "scheduler", "workers"}``, then
``{"event": "stage", "job", "stage"}`` as a job enters each of :data:`lungdeform.cohort.job.STAGES`
(reported by the workers through Dask's event log; the stage is read from run_fit's progress
messages), and ``{"event": "done", "job", "result", "skipped"}`` once per job (skipped jobs
first), and ``{"event": "population", "ok"}`` before the population statistics.

With ``scheduler=ADDRESS`` the workers of that cluster run the jobs: they need lungdeform
installed (the same version) and must see the manifest's input files and ``OUT`` at the same
paths (a shared file system). The default local cluster starts worker processes with
``spawn``: a script calling :func:`run_cohort` needs an ``if __name__ == "__main__":`` guard.
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
import queue
import signal
import socket
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

from lungdeform.atomic import write_json
from lungdeform.errors import InputError, require
from lungdeform.progress import silent

from .job import (
    FitOptions,
    _json_default,
    _one_line,
    _result,
    clean_partial,
    failed_result,
    fit_job,
    input_digest,
    job_folder,
    read_result,
)
from .manifest import Job, Manifest, read_manifest
from .population import write_population
from .recovery import add_recovery

SUMMARY_SCHEMA = "lungdeform.cohort.summary"
#: Dask event-log topic of the stage events sent by workers.
TOPIC = "lungdeform-cohort-stage"


@dataclass(frozen=True)
class CohortResult:
    """Outcome of :func:`run_cohort`.

    results : one ``result.json`` dictionary per job, manifest order (skipped jobs: the stored one).
    skipped : keys (``subject/side``) of the jobs not run because a valid result was there.
    """

    out: Path
    results: tuple[dict, ...]
    skipped: frozenset[str]
    seconds: float
    scheduler: str | None
    workers: int | None
    summary_path: Path
    population: dict | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def ok(self) -> list[dict]:
        return [r for r in self.results if r["status"] == "ok"]

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.results if r["status"] != "ok"]


def clean_stale(out: Path) -> list[Path]:
    """Remove the temporary and moved-aside folders a killed run left under ``out/subjects`` and
    half-written ``cohort.json`` temporaries; return what was removed."""
    removed = clean_partial(out)
    for p in Path(out).glob(".cohort.json.*"):
        p.unlink(missing_ok=True)
        removed.append(p)
    return removed


# --------------------------------------------------------------------------- the runner


@dataclass(frozen=True)
class Cluster:
    """Where :func:`run_cohort` runs the jobs.

    scheduler : address of a running Dask scheduler (``tcp://host:8786``), reached within
        ``connect_timeout_s``; default: a local cluster of ``workers`` processes (default: CPU
        count, at most one per job to run), one thread each (``processes=False``: threads in this
        process, for debugging and tests).
    """

    scheduler: str | None = None
    workers: int | None = None
    processes: bool = True
    connect_timeout_s: float = 30.0


def run_cohort(manifest, out, *, cluster: Cluster = Cluster(), options: FitOptions = FitOptions(),
               skip_failed: bool = False, population: bool = True,
               progress: Callable[[dict], None] | None = None) -> CohortResult:
    """Fit every job of ``manifest`` (a path or a read :class:`~lungdeform.cohort.manifest.Manifest`)
    into ``out``; write ``out/cohort.json``; then population statistics
    (:func:`lungdeform.cohort.population.write_population`) when at least one fit succeeded.

    cluster : where the jobs run (:class:`Cluster`; default: a local cluster of worker processes).
    skip_failed : do not re-run jobs whose stored result failed.
    population : compute population statistics afterwards.

    On Ctrl-C (KeyboardInterrupt) the jobs in flight are cancelled, the cluster is closed,
    ``cohort.json`` records what finished (``"interrupted": true``) and the KeyboardInterrupt is
    raised again; re-running resumes.
    """

    t_start = time.perf_counter()
    started = _now()
    scheduler, workers, processes = cluster.scheduler, cluster.workers, cluster.processes
    emit = progress or silent
    _check_cluster(scheduler, workers)
    m = manifest if isinstance(manifest, Manifest) else read_manifest(manifest)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    with _exclusive(out):
        clean_stale(out)
        results, skipped, to_run = _stored_results(m, out, options, skip_failed)
        n_workers = None
        if to_run and not scheduler:
            n_workers = int(workers) if workers else max(1, min(os.cpu_count() or 1, len(to_run)))
        emit({"event": "start", "jobs": len(m.jobs), "to_run": len(to_run), "skipped": len(skipped),
              "scheduler": scheduler or ("local" if to_run else None), "workers": n_workers})
        for job in m.jobs:
            if job.key in skipped:
                emit({"event": "done", "job": job.key, "result": results[job.key], "skipped": True})
        address = None

        def summary(interrupted: bool, pop: dict | None = None) -> dict:
            seconds = time.perf_counter() - t_start
            run = {"started": started, "finished": _now(), "seconds": seconds, "interrupted": interrupted,
                   "scheduler": address, "workers": n_workers,
                   "processes": processes if address and n_workers else None}
            return _summary(m, out, results, skipped, run, options, pop)

        try:
            if to_run:
                address = _run_on_dask(to_run, out, options, replace(cluster, workers=n_workers), results, emit)
        except KeyboardInterrupt:
            _collect_finished(to_run, out, options, results)
            write_json(out / "cohort.json", summary(True))
            raise
        summary_path = write_json(out / "cohort.json", summary(False))
        ordered = tuple(results[j.key] for j in m.jobs)
        pop = None
        if population and any(r["status"] == "ok" for r in ordered):
            emit({"event": "population", "ok": sum(r["status"] == "ok" for r in ordered)})
            pop = add_recovery(write_population(list(ordered), out, m.folder), list(ordered), out, m.folder)
            write_json(out / "cohort.json", summary(False, pop), default=_json_default)
    return CohortResult(out, ordered, frozenset(skipped), time.perf_counter() - t_start, address, n_workers,
                        summary_path, pop, m.notes)


def _check_cluster(scheduler: str | None, workers: int | None) -> None:
    """Refuse ``workers`` with a ``scheduler`` (the cluster's own workers run the jobs) or below 1."""
    if scheduler and workers is not None:
        raise InputError("workers sets the size of the local cluster; with a scheduler the cluster's own "
                         "workers run the jobs (leave workers out)")
    if workers is not None and int(workers) < 1:
        raise InputError(f"workers must be at least 1, got {workers}")


def _stored_results(m: Manifest, out: Path, options: FitOptions,
                    skip_failed: bool) -> tuple[dict[str, dict], set[str], list[Job]]:
    """``(results, skipped, to_run)``: the stored results of the jobs of ``m`` that need not run
    again (same input digest, and ``ok`` or ``skip_failed``) by job key, their keys, and the other
    jobs, manifest order."""
    results: dict[str, dict] = {}
    skipped: set[str] = set()
    to_run: list[Job] = []
    for job in m.jobs:
        stored = read_result(job_folder(out, job))
        valid = stored is not None and stored.get("input_digest") == input_digest(job, options)
        if valid and (stored.get("status") == "ok" or skip_failed):
            results[job.key] = stored
            skipped.add(job.key)
        else:
            to_run.append(job)
    return results, skipped, to_run


def _collect_finished(jobs: list[Job], out: Path, options: FitOptions, results: dict[str, dict]) -> None:
    """Add to ``results`` the valid stored results of ``jobs`` not in it: jobs that finished on a
    worker while this process was interrupted."""
    for job in jobs:
        stored = read_result(job_folder(out, job))
        if job.key not in results and stored and stored.get("input_digest") == input_digest(job, options):
            results[job.key] = stored


def _run_on_dask(jobs: list[Job], out: Path, options: FitOptions, cluster_spec: Cluster, results: dict,
                 emit) -> str:
    """Submit one task per job, relay stage events, record results as they finish; return the
    scheduler's address. ``cluster_spec.workers`` : the local cluster's size, resolved. Closes what
    it opened, also on Ctrl-C."""
    scheduler, n_workers = cluster_spec.scheduler, cluster_spec.workers
    processes, connect_timeout_s = cluster_spec.processes, cluster_spec.connect_timeout_s

    require("distributed", "lungdeform cohort", "dask[distributed]")
    from distributed import Client, LocalCluster

    cluster = client = None
    events: queue.Queue = queue.Queue()
    futures = {}
    interrupt, restore = _sigint_flag()
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout=connect_timeout_s, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise InputError(f"scheduler {scheduler}: cannot connect ({_one_line(exc)})") from None
        else:
            # one thread per worker (the fit is CPU-bound and holds the GIL at times). Every HTTP
            # endpoint (the dashboard, if bokeh is installed) on a free port of 127.0.0.1: the
            # scheduler's default, port 8787 on all interfaces, collides with any other Dask on the
            # machine, and distributed then leaks the socket it failed to bind (a ResourceWarning).
            # Workers' own log lines are silenced below CRITICAL: a failed job is reported from its
            # future, and on Ctrl-C a worker whose heartbeat met the closing scheduler printed an
            # ERROR and a traceback, breaking the one-line interruption message (seen under load).
            kw = {"host": "127.0.0.1"} if processes else {}
            with _sigint_ignored():  # inherited by the worker processes: Ctrl-C reaches this one only
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=processes,
                                       dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0",
                                       silence_logs=logging.CRITICAL, **kw)
            client = Client(cluster, set_as_default=False)
        address = client.scheduler.address
        client.subscribe_topic(TOPIC, events.put)
        for job in jobs:
            f = client.submit(_task, job, str(out), options, key=f"lungdeform-fit-{job.key}-{uuid.uuid4().hex[:8]}",
                              pure=False, retries=0)
            futures[f] = job
        pending, running = set(futures), {j.key for j in jobs}
        while pending:
            if interrupt.is_set():
                raise KeyboardInterrupt
            try:
                _, ev = events.get(timeout=0.2)
                if ev.get("job") in running:  # a stage event may arrive after its job's result: dropped
                    emit({k: v for k, v in ev.items() if k != "worker"})
                continue
            except queue.Empty:
                pass
            for f in [f for f in pending if f.done()]:
                pending.discard(f)
                job = futures[f]
                running.discard(job.key)
                results[job.key] = _collect(f, job, out, options)
                emit({"event": "done", "job": job.key, "result": results[job.key], "skipped": False})
        if interrupt.is_set():  # Ctrl-C after the last result: still an interruption
            raise KeyboardInterrupt
        return address
    finally:
        restore()
        if client is not None:
            if futures:
                client.cancel(list(futures), force=True)
            client.unsubscribe_topic(TOPIC)
            client.close()
        if cluster is not None:
            cluster.close()


def _sigint_flag():
    """While the jobs run, Ctrl-C (SIGINT) only sets a flag that the waiting loop turns into a
    KeyboardInterrupt: raised asynchronously inside the Dask client's own code (a blocking
    ``sync`` call, a lock) the interrupt could be lost and the run would go on. Returns
    ``(flag, restore)``; outside the main thread the flag is never set."""

    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        return flag, lambda: None
    previous = signal.signal(signal.SIGINT, lambda _signum, _frame: flag.set())
    return flag, lambda: signal.signal(signal.SIGINT, previous)


@contextmanager
def _sigint_ignored():
    """Ignore SIGINT while the local cluster starts its worker processes, which inherit it.

    A terminal's Ctrl-C goes to every process in the foreground group; without this each worker
    process dies printing a KeyboardInterrupt traceback while its nanny restarts it. With it only
    this process is interrupted and it closes the cluster itself (the interrupted job's temporary
    folder is removed on the next run). A Ctrl-C during the start-up (about a second) is ignored.
    """

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _task(job: Job, out: str, options: FitOptions) -> dict:
    """The Dask task: :func:`fit_job` with its stage events sent to the client via the event log."""
    from distributed import get_worker

    worker = get_worker()
    return fit_job(job, Path(out), options, progress=lambda ev: worker.log_event(TOPIC, ev))


def _collect(future, job: Job, out: Path, options: FitOptions) -> dict:
    """The task's result; a task that raised or was lost becomes a failed result on disk."""
    if future.status == "finished":
        return future.result()
    try:
        exc = future.exception()
    except BaseException as e:  # cancelled futures raise instead of returning their exception
        exc = e
    try:
        return failed_result(job, out, options, exc)
    except Exception as write_error:  # the folder cannot be written either: keep the failure in memory
        r = _result(job, "failed", input_digest(job, options), 0.0, error=exc)
        r["error"] += f" (and its result could not be written: {_one_line(write_error)})"
        return r


def _summary(m, out, results, skipped, run: dict, options, population) -> dict:
    """The ``cohort.json`` of ``m``; ``run`` : its started, finished, seconds, interrupted, scheduler,
    workers and processes entries."""
    per_job = []
    for job in m.jobs:
        r = results.get(job.key)
        per_job.append({
            "subject": job.subject, "side": job.side, "rows": job.rows,
            "folder": str(job_folder(out, job).relative_to(out)),
            "status": r["status"] if r else "not run",
            "skipped": job.key in skipped,
            "error": r["error"] if r else None,
            "error_type": r["error_type"] if r else None,
            "seconds": r["seconds"] if r else None,
        })
    ran = [p for p in per_job if not p["skipped"] and p["status"] != "not run"]
    return {
        "schema": SUMMARY_SCHEMA, "version": 1,
        "manifest": str(m.path), "out": str(out.resolve()),
        **run,
        "options": asdict(options),
        "jobs": {"total": len(per_job), "ok": sum(p["status"] == "ok" for p in per_job),
                 "failed": sum(p["status"] == "failed" for p in per_job),
                 "skipped": len(skipped), "ran": len(ran),
                 "not_run": sum(p["status"] == "not run" for p in per_job)},
        "fit_seconds_total": sum(p["seconds"] for p in ran if p["seconds"] is not None),
        "per_job": per_job, "notes": list(m.notes), "population": population,
    }


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


@contextmanager
def _exclusive(out: Path):
    """Hold an exclusive lock on ``out/.lock`` (released when the process ends, even if killed)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock
        yield
        return
    fd = os.open(out / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
            raise InputError(f"out {out}: in use by another cohort run ({holder}); wait for it to finish") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since {_now()}".encode(), 0)
        yield
    finally:
        os.close(fd)
