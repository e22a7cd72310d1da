"""One job of a cohort: fitting one lung (a subject's side) and its ``result.json`` record.

A job (:class:`lungdeform.cohort.manifest.Job`) runs :func:`lungdeform.evaluate.pipeline.run_fit` into a hidden
temporary folder next to its final one (``.<side>.partial-<hex>``) and renames it into place when
complete, so a folder under ``subjects/`` is always whole; one that existed before is moved aside
(``.<side>.old-<hex>``) and removed. Both kinds of leftover (after a kill) are removed at the start
of the next run (:func:`clean_partial`). Every job ends with a ``result.json``
(:data:`RESULT_SCHEMA`), ``status`` ``ok`` or ``failed``: an exception in one job is recorded there
and never stops the others.

Resume digest: :func:`input_digest` hashes what a result depends on (inputs' paths, sizes and
modification times, volumes, landmarks, fit options and the lungdeform version); the runner
(:func:`lungdeform.cohort.runner.run_cohort`) skips a job whose folder holds an ``ok`` result with the
same digest.

Fit options (:class:`FitOptions`, part of the digest): the budget, baselines, grid and stiffness,
``align`` (``apex`` for scans with a table shift; ``none`` or ``joint`` for inputs already in one
frame, e.g. a synthetic cohort from ``lungdeform synth-cohort``, whose truth the apex alignment
would shift), ``landmark_fit`` / ``folds`` (with landmarks, the interior landmark correction with its
k-fold cross-validation) and
``direction_degree``. ``result.json``'s ``constants`` are those of the fit ``model.npz`` holds
(``fit_kind``: the key of that fit in ``metrics.json``'s ``fit``, ``optimizer``).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import time
import traceback
import uuid
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable

from lungdeform import __version__
from lungdeform.atomic import jsonable, write_json
from lungdeform.evaluate.pipeline import run_fit
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.progress import silent

from .manifest import Job

RESULT_SCHEMA = "lungdeform.cohort.result"
RESULT_VERSION = 1
#: Stages a job goes through, in order (one progress bar each in the CLI).
STAGES = ("read", "align", "fit", "write")
_PARTIAL, _OLD, _MARK = ".partial-", ".old-", ".lungdeform-partial"


@dataclass(frozen=True)
class FitOptions:
    """Fit settings shared by every job (part of the input digest); validated as the
    :class:`lungdeform.fit.config.FitConfig` they become (:meth:`config`), whose errors name the field."""

    max_evaluations: int = 300
    baselines: bool = True
    grid: bool = False
    stiffness: bool = False
    #: how targets reach the end-exhale frame: "apex", "joint" or "none" (lungdeform.fit.config.ALIGN_MODES);
    #: synthetic cohorts (already in one frame) want "none" or "joint"
    align: str = "apex"
    #: with landmarks: the interior landmark correction, cross-validated over ``folds`` folds
    landmark_fit: bool = True
    folds: int = 5
    #: degree of the smooth correction of the paper's directions (lungdeform.fit.direction_correction; 0: none)
    direction_degree: int = 3
    #: refuse a lung whose shape clearly says the other side (lungdeform.geometry.frame.check_side)
    side_check: bool = True

    def __post_init__(self):
        config = self.config()  # validates every field (errors name it)
        for f in fields(self):  # plain Python numbers and booleans: the digest is JSON
            object.__setattr__(self, f.name, getattr(config, f.name))

    def config(self, command: str = "cohort") -> FitConfig:
        """These options as the :class:`lungdeform.fit.config.FitConfig` of a job's fit."""
        return FitConfig(command=command, **{f.name: getattr(self, f.name) for f in fields(self)})


def job_folder(out: Path, job: Job) -> Path:
    return Path(out) / "subjects" / job.subject / job.side


def input_digest(job: Job, options: FitOptions) -> str:
    """SHA-256 of what a job's result depends on: each input's and landmark file's absolute path,
    size and modification time (a DICOM folder: every file in it), the volumes, the order, the
    fit options and the lungdeform version (an upgrade re-fits: results from another version are
    not reused)."""

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

    out_dir = Path(out_dir)
    emit = progress or silent
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
            inputs = FitInputs(job.inputs, job.side, job.volumes_ml, job.landmarks)
            metrics = run_fit(inputs, tmp, options.config(), progress=say)
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


def clean_partial(out: Path) -> list[Path]:
    """Remove the temporary and moved-aside job folders (:func:`_partial_folder`, :func:`_publish`)
    a killed run left under ``out/subjects``; return what was removed."""
    removed = []
    subjects = Path(out) / "subjects"
    for subject in subjects.iterdir() if subjects.is_dir() else ():
        for p in subject.iterdir() if subject.is_dir() else ():
            if p.name.startswith(".") and (_PARTIAL in p.name or _OLD in p.name):
                _discard(p)
                removed.append(p)
    return removed


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
