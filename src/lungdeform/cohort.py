"""Fit every lung of a cohort on Dask (dask.distributed), resumably, one folder per lung.

Layout of the output folder ``OUT``::

    OUT/cohort.json                         summary of the last run (jobs, statuses, timings)
    OUT/subjects/<subject>/<side>/          one finished job: result.json (+ model.npz,
                                            metrics.json, report.html when the fit succeeded)

A job (:class:`lungdeform.manifest.Job`) runs :func:`lungdeform.pipeline.run_fit` into a hidden
temporary folder next to its final one (``.<side>.partial-<hex>``) and renames it into place when
complete, so a folder under ``subjects/`` is always whole; one that existed before is moved aside
(``.<side>.old-<hex>``) and removed. Both kinds of leftover (after a kill) are removed at the start
of the next run. Every job ends with a ``result.json`` (:data:`RESULT_SCHEMA`), ``status`` ``ok``
or ``failed``: an exception in one job is recorded there and never stops the others.

Resuming: a job whose folder holds an ``ok`` result with the same :func:`input_digest` (inputs'
paths, sizes and modification times, volumes, landmarks and fit options) is skipped; failed jobs
are run again unless ``skip_failed``. A run holds an exclusive lock on ``OUT/.lock`` so two runs
never share an output folder.

Progress: ``progress(event: dict)`` is called on the calling thread with
``{"event": "start", "jobs", "to_run", "skipped", "scheduler", "workers"}``, then
``{"event": "stage", "job", "stage"}`` as a job enters each of :data:`STAGES` (reported by the
workers through Dask's event log; the stage is read from run_fit's progress messages), and
``{"event": "done", "job", "result", "skipped"}`` once per job (skipped jobs first), and
``{"event": "population", "ok"}`` before the population statistics.

Fit options (:class:`FitOptions`, part of the digest): the budget, baselines, grid and stiffness,
``align`` (``apex`` for scans with a table shift; ``none`` or ``joint`` for inputs already in one
frame, e.g. a synthetic cohort from ``lungdeform synth-cohort``, whose truth the apex alignment
would shift), ``landmark_fit`` / ``folds`` (with landmarks, the interior landmark correction with its
k-fold cross-validation) and
``direction_degree``. ``result.json``'s ``constants`` are those of the fit ``model.npz`` holds
(``fit_kind``: the key of that fit in ``metrics.json``'s ``fit``, ``optimizer``).

With ``scheduler=ADDRESS`` the workers of that cluster run the jobs: they need lungdeform
installed (the same version) and must see the manifest's input files and ``OUT`` at the same
paths (a shared file system). The default local cluster starts worker processes with
``spawn``: a script calling :func:`run_cohort` needs an ``if __name__ == "__main__":`` guard.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import math
import os
import queue
import shutil
import socket
import time
import traceback
import uuid
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .atomic import write_json
from .errors import InputError
from .manifest import Job, read_manifest

RESULT_SCHEMA = "lungdeform.cohort.result"
RESULT_VERSION = 1
SUMMARY_SCHEMA = "lungdeform.cohort.summary"
#: Stages a job goes through, in order (one progress bar each in the CLI).
STAGES = ("read", "align", "fit", "write")
#: Dask event-log topic of the stage events sent by workers.
TOPIC = "lungdeform-cohort-stage"
_PARTIAL, _OLD, _MARK = ".partial-", ".old-", ".lungdeform-partial"


@dataclass(frozen=True)
class FitOptions:
    """Fit settings shared by every job (part of the input digest)."""

    max_evaluations: int = 300
    baselines: bool = True
    grid: bool = False
    stiffness: bool = False
    #: how targets reach the end-exhale frame: "apex", "joint" or "none" (lungdeform.pipeline.ALIGN_MODES);
    #: synthetic cohorts (already in one frame) want "none" or "joint"
    align: str = "apex"
    #: with landmarks: the interior landmark correction, cross-validated over ``folds`` folds
    landmark_fit: bool = True
    folds: int = 5
    #: degree of the smooth correction of the paper's directions (lungdeform.direction_correction; 0: none)
    direction_degree: int = 3

    def __post_init__(self):
        from .direction_correction import MAX_DEGREE
        from .pipeline import ALIGN_MODES

        def whole(x) -> bool:
            return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))

        for name in ("baselines", "grid", "stiffness", "landmark_fit"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"{name} must be True or False, got {getattr(self, name)!r}")
        if not (whole(self.max_evaluations) and self.max_evaluations >= 1):
            raise InputError(f"max_evaluations (--evaluations) must be a whole number >= 1, got {self.max_evaluations!r}")
        if self.align not in ALIGN_MODES:
            raise InputError(f"align (--align) must be one of {', '.join(ALIGN_MODES)}, got {self.align!r}")
        if not (whole(self.folds) and self.folds >= 2):
            raise InputError(f"folds (--folds) must be a whole number >= 2, got {self.folds!r}")
        if not (whole(self.direction_degree) and 0 <= self.direction_degree <= MAX_DEGREE):
            raise InputError(f"direction_degree (--direction-degree) must be a whole number 0…{MAX_DEGREE}, "
                             f"got {self.direction_degree!r}")
        for name in ("max_evaluations", "folds", "direction_degree"):  # plain ints: the digest is JSON
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in ("baselines", "grid", "stiffness", "landmark_fit"):
            object.__setattr__(self, name, bool(getattr(self, name)))


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


# --------------------------------------------------------------------------- one job


def job_folder(out: Path, job: Job) -> Path:
    return Path(out) / "subjects" / job.subject / job.side


def input_digest(job: Job, options: FitOptions) -> str:
    """SHA-256 of what a job's result depends on: each input's and landmark file's absolute path,
    size and modification time (a DICOM folder: every file in it), the volumes, the order, the
    fit options and the lungdeform version (an upgrade re-fits: results from another version are
    not reused)."""
    from . import __version__

    def stat(p: Path):
        p = Path(p)
        if p.is_dir():
            return [str(p), [_stat(q) for q in sorted(p.rglob("*")) if q.is_file()]]
        return _stat(p)

    doc = {"subject": job.subject, "side": job.side, "inputs": [stat(p) for p in job.inputs],
           "landmarks": [stat(p) for p in job.landmarks] if job.landmarks else None,
           "volumes_ml": job.volumes_ml, "ordered_by": job.ordered_by, "options": asdict(options),
           "lungdeform": __version__}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _stat(p: Path):
    try:
        st = p.stat()
    except OSError:
        return [str(p), None, None]
    return [str(p), st.st_size, st.st_mtime_ns]


def fit_job(job: Job, out_dir, options: FitOptions = FitOptions(), *, progress: Callable[[dict], None] | None = None) -> dict:
    """Fit one job into ``out_dir/subjects/<subject>/<side>/`` atomically; return its result.

    Never raises for a failed fit (the result says ``failed`` with the error); raises only if the
    result itself cannot be written (e.g. the disk is full), leaving no folder half-written.
    """
    from .pipeline import run_fit

    out_dir = Path(out_dir)
    emit = progress or (lambda _e: None)
    t0 = time.perf_counter()
    digest = input_digest(job, options)
    stage = {"now": None}

    def enter(name: str) -> None:
        if stage["now"] != name and (stage["now"] is None or STAGES.index(name) > STAGES.index(stage["now"])):
            stage["now"] = name
            emit({"event": "stage", "job": job.key, "stage": name})

    def say(message: str) -> None:
        m = str(message).lower()
        if m.startswith(("model mesh", "aligned")):
            enter("align")
        elif m.startswith("fitting"):
            enter("fit")

    enter("read")
    with _partial_folder(job_folder(out_dir, job)) as tmp:
        metrics, error = None, None
        try:
            metrics = run_fit(list(job.inputs), side=job.side, out=tmp, volumes=job.volumes_ml,
                              landmarks=job.landmarks, grid=options.grid, stiffness=options.stiffness,
                              baselines=options.baselines, max_evaluations=int(options.max_evaluations),
                              command="cohort", progress=say, align=options.align,
                              landmark_fit=options.landmark_fit, folds=int(options.folds),
                              direction_degree=int(options.direction_degree))
        except Exception as exc:  # isolate: any failure of this job becomes its result
            error = exc
        enter("write")
        if error is None:
            result = _result(job, "ok", digest, time.perf_counter() - t0, metrics=metrics)
        else:
            _empty(tmp)
            (tmp / "traceback.txt").write_text("".join(traceback.format_exception(error)), encoding="utf-8")
            result = _result(job, "failed", digest, time.perf_counter() - t0, error=error)
        write_json(tmp / "result.json", result, default=_json_default)
        _publish(tmp, job_folder(out_dir, job))
    return result


def failed_result(job: Job, out_dir, options: FitOptions, error: BaseException, seconds: float = 0.0) -> dict:
    """Write (atomically) and return a failed result for a job whose task never returned (its
    worker died, the task was lost); raises only if the folder cannot be written."""
    out_dir = Path(out_dir)
    result = _result(job, "failed", input_digest(job, options), seconds, error=error)
    with _partial_folder(job_folder(out_dir, job)) as tmp:
        write_json(tmp / "result.json", result, default=_json_default)
        _publish(tmp, job_folder(out_dir, job))
    return result


def read_result(folder) -> dict | None:
    """The ``result.json`` in ``folder`` if it is a valid cohort result, else None."""
    try:
        r = json.loads((Path(folder) / "result.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(r, dict) or r.get("schema") != RESULT_SCHEMA or r.get("version") != RESULT_VERSION:
        return None
    return r


def _result(job: Job, status: str, digest: str, seconds: float, *, metrics: dict | None = None,
            error: BaseException | None = None) -> dict:
    m = metrics or {}
    model = m.get("model", {})
    # the constants of the fit model.npz holds (metrics['headline_fit'], the optimiser's)
    fit_kind = m.get("headline_fit", "optimizer") if metrics else None
    headline = m.get("fit", {}).get(fit_kind, {})
    constants = headline.get("constants") if metrics else None
    volumes = m.get("volumes_ml", job.volumes_ml) or []
    return {
        "schema": RESULT_SCHEMA,
        "version": RESULT_VERSION,
        "subject": job.subject,
        "side": job.side,
        "status": status,
        "error": None if error is None else _one_line(error),
        "error_type": None if error is None else type(error).__name__,
        "inputs": [str(p) for p in job.inputs],
        "volumes_ml": [float(v) for v in volumes],
        "constants": [float(c) for c in constants] if constants is not None else None,
        "fit_kind": fit_kind,
        "metrics": {
            "surface_mean_mm": finite_or_none(model.get("surface_mean_mm")),
            "surface_rms_mm": finite_or_none(model.get("surface_rms_mm")),
            "surface_p95_mm": finite_or_none(model.get("surface_p95_mm")),
            "landmark_mean_mm": finite_or_none(model.get("landmark_mean_mm")),
            "objective_rms_mm": finite_or_none(headline.get("objective_rms_mm")),
        },
        "seconds": float(seconds),
        "input_digest": digest,
    }


def finite_or_none(v):
    """JSON-safe float: NaN and infinities become None (e.g. landmark errors without landmarks)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _json_default(o):
    from .atomic import jsonable

    if isinstance(o, Path):
        return str(o)
    return jsonable(o)


@contextmanager
def _partial_folder(final: Path):
    """A fresh hidden folder next to ``final``; removed if still there on exit (not published)."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.parent / f".{final.name}{_PARTIAL}{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    (tmp / _MARK).touch()
    try:
        yield tmp
    finally:
        _discard(tmp)


def _empty(folder: Path) -> None:
    """Remove whatever a failed fit left in its temporary folder (keep the marker)."""
    for p in folder.iterdir():
        if p.name == _MARK:
            continue
        shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()


def _discard(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def _publish(tmp: Path, final: Path) -> None:
    """Rename the complete folder ``tmp`` to ``final``; an existing ``final`` is moved aside first
    and removed after. ``final`` never exists half-written."""
    marker = tmp / _MARK
    if not marker.exists():  # the folder was cleaned away under us (a newer run): publish nothing
        raise FileNotFoundError(f"{tmp}: temporary folder vanished before it could be renamed into place")
    marker.unlink()
    for _ in range(5):
        try:
            os.rename(tmp, final)
            return
        except OSError:
            if not final.exists():
                raise
            old = final.parent / f".{final.name}{_OLD}{uuid.uuid4().hex[:12]}"
            try:
                os.rename(final, old)
            except FileNotFoundError:  # another writer moved it in the meantime: try again
                continue
            _discard(old)
    os.rename(tmp, final)


def clean_stale(out: Path) -> list[Path]:
    """Remove the temporary and moved-aside folders a killed run left under ``out/subjects`` and
    half-written ``cohort.json`` temporaries; return what was removed."""
    removed = []
    subjects = Path(out) / "subjects"
    if subjects.is_dir():
        for subject in subjects.iterdir():
            if not subject.is_dir():
                continue
            for p in subject.iterdir():
                if p.name.startswith(".") and (_PARTIAL in p.name or _OLD in p.name):
                    _discard(p)
                    removed.append(p)
    for p in Path(out).glob(".cohort.json.*"):
        p.unlink(missing_ok=True)
        removed.append(p)
    return removed


# --------------------------------------------------------------------------- the runner


def run_cohort(manifest, out, *, scheduler: str | None = None, workers: int | None = None,
               options: FitOptions = FitOptions(), skip_failed: bool = False, processes: bool = True,
               population: bool = True, connect_timeout_s: float = 30.0,
               progress: Callable[[dict], None] | None = None) -> CohortResult:
    """Fit every job of ``manifest`` (a path or a read :class:`~lungdeform.manifest.Manifest`)
    into ``out``; write ``out/cohort.json``; then population statistics
    (:func:`lungdeform.population.write_population`) when at least one fit succeeded.

    scheduler : address of a running Dask scheduler (``tcp://host:8786``); default: a local
        cluster of ``workers`` processes (default: CPU count, at most one per job to run), one
        thread each (``processes=False``: threads in this process, for debugging and tests).
    skip_failed : do not re-run jobs whose stored result failed.
    population : compute population statistics afterwards.

    On Ctrl-C (KeyboardInterrupt) the jobs in flight are cancelled, the cluster is closed,
    ``cohort.json`` records what finished (``"interrupted": true``) and the KeyboardInterrupt is
    raised again; re-running resumes.
    """
    from .manifest import Manifest

    t_start = time.perf_counter()
    started = _now()
    emit = progress or (lambda _e: None)
    if scheduler and workers is not None:
        raise InputError("--workers sets the size of the local cluster; with --scheduler the cluster's own "
                         "workers run the jobs (leave --workers out)")
    if workers is not None and int(workers) < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    m = manifest if isinstance(manifest, Manifest) else read_manifest(manifest)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    with _exclusive(out):
        clean_stale(out)
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
            return _summary(m, out, results, skipped, started, time.perf_counter() - t_start, address, n_workers,
                            processes, options, interrupted, pop)

        try:
            if to_run:
                address = _run_on_dask(to_run, out, options, scheduler, n_workers, processes, connect_timeout_s,
                                       results, emit)
        except KeyboardInterrupt:
            for job in to_run:  # jobs that finished on a worker while this process was interrupted
                stored = read_result(job_folder(out, job))
                if job.key not in results and stored and stored.get("input_digest") == input_digest(job, options):
                    results[job.key] = stored
            write_json(out / "cohort.json", summary(True))
            raise
        summary_path = write_json(out / "cohort.json", summary(False))
        ordered = tuple(results[j.key] for j in m.jobs)
        pop = None
        if population and any(r["status"] == "ok" for r in ordered):
            from .population import write_population

            emit({"event": "population", "ok": sum(r["status"] == "ok" for r in ordered)})
            pop = write_population(list(ordered), out, m.folder)
            write_json(out / "cohort.json", summary(False, pop), default=_json_default)
    return CohortResult(out, ordered, frozenset(skipped), time.perf_counter() - t_start, address, n_workers,
                        summary_path, pop, m.notes)


def _run_on_dask(jobs: list[Job], out: Path, options: FitOptions, scheduler, n_workers, processes,
                 connect_timeout_s, results: dict, emit) -> str:
    """Submit one task per job, relay stage events, record results as they finish; return the
    scheduler's address. Closes what it opened, also on Ctrl-C."""
    from .errors import require

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
                raise InputError(f"--scheduler {scheduler}: cannot connect ({_one_line(exc)})") from None
        else:
            # one thread per worker (the fit is CPU-bound and holds the GIL at times). Every HTTP
            # endpoint (the dashboard, if bokeh is installed) on a free port of 127.0.0.1: the
            # scheduler's default, port 8787 on all interfaces, collides with any other Dask on the
            # machine, and distributed then leaks the socket it failed to bind (a ResourceWarning).
            kw = {"host": "127.0.0.1"} if processes else {}
            with _sigint_ignored():  # inherited by the worker processes: Ctrl-C reaches this one only
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=processes,
                                       dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0",
                                       silence_logs=logging.ERROR, **kw)
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
    import signal
    import threading

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
    import signal
    import threading

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


def _summary(m, out, results, skipped, started, seconds, address, n_workers, processes, options,
             interrupted, population) -> dict:
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
        "started": started, "finished": _now(), "seconds": seconds, "interrupted": interrupted,
        "scheduler": address, "workers": n_workers, "processes": processes if address and n_workers else None,
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
            raise InputError(f"--out {out}: in use by another cohort run ({holder}); wait for it to finish") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since {_now()}".encode(), 0)
        yield
    finally:
        os.close(fd)
