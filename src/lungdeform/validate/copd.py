"""DIR-Lab COPDgene lung masks (cases 1–5): the model fitted per lung, expiration → inspiration.

The experiment behind ``lungdeform validate copd`` (docs/FITTING.md "DIR-Lab COPDgene, five subjects").

Data: a folder holding, per case N, ``copdN_exp_mask.nii.gz``, ``copdN_insp_mask.nii.gz`` (both lungs
in one label) and ``copdN_exp_landmarks.txt``, ``copdN_insp_landmarks.txt`` (elastix point files,
world mm, row i ↔ row i). Each phase was re-centred on its lungs, so the fit estimates a translation
(``align="joint"``). For every case and lung (the split of :mod:`lungdeform.segment.split`, that
lung's landmarks) :func:`run_lung` runs :func:`lungdeform.evaluate.pipeline.run_fit` into
``OUT/copdN/<side>/`` (model.npz, metrics.json, report.html) and adds the calibrated mask-only
baselines (:func:`mask_baselines`, once per case: :class:`CaseBaselines`); :func:`run_copd` collects
``OUT/metrics.json`` (:func:`lung_row` per lung, :func:`summarise`: medians over the lungs) and
``OUT/report.html``. Each mask is split once per case (a :class:`lungdeform.segment.split.SplitCache`).
Times: per lung ``seconds`` (the whole fit pipeline, the outputs written included),
``baseline_seconds`` (the pipeline's baselines and landmark-informed references) and the pipeline's
``model_seconds`` (its fit less those, before the outputs are written); per case ``fit_seconds`` and
``model_fit_seconds`` (its two lungs' ``seconds``, and the same less ``baseline_seconds``: the
writing of model.npz, metrics.json and report.html included) and ``mask_baselines_seconds`` (the
mask-only baselines, timed apart; :func:`case_seconds`).

:func:`write_cohort_manifest` writes the same cases as a manifest for ``lungdeform cohort`` (population
statistics of c1…c9 against Table I; :data:`COHORT_OPTIONS` are the cohort options that match
:func:`copd_config`): ``lungdeform validate copd --data DIR --out OUT --manifest-only``.

A lung whose ``metrics.json`` records the same settings digest (:func:`settings_digest`: the input
files' contents, the fit settings, the CPD baseline's settings, the calibrated baselines' constants) is
not fitted again.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import re
import time
from contextlib import nullcontext
from dataclasses import asdict
from pathlib import Path

import numpy as np

from lungdeform.atomic import atomic_dir, made_folder, write_json, write_text
from lungdeform.errors import InputError, ReadError
from lungdeform.evaluate import baselines as B
from lungdeform.evaluate.pipeline import run_fit
from lungdeform.evaluate.workers import LungWorkers
from lungdeform.fit import registration
from lungdeform.fit.config import FitConfig, FitInputs
from lungdeform.interior.motion_prior import RIDGE, PriorSample, learn_motion_prior, save_prior, taper_at
from lungdeform.io.image import read_image
from lungdeform.io.landmarks import read_elastix_points
from lungdeform.io.modelfile import load_model
from lungdeform.plot.figure import png_bytes
from lungdeform.plot.statistics import grouped_bars
from lungdeform.progress import Progress, silent
from lungdeform.segment.split import SIDES, SplitCache, landmarks_of_side, require_split

from . import subjects

COMMAND = "validate copd"
FILES = ("copd{n}_exp_mask.nii.gz", "copd{n}_insp_mask.nii.gz", "copd{n}_exp_landmarks.txt",
         "copd{n}_insp_landmarks.txt")
#: Rows of the pipeline's metrics collected per lung, and their figures.
ROWS = {"model": ("surface_mean_mm", "landmark_mean_mm"), "model_unrefined": ("surface_mean_mm",),
        "model_surface_only": ("landmark_mean_mm",),
        "model_surface_sliding": ("landmark_mean_mm",),
        "no_motion": ("surface_mean_mm", "landmark_mean_mm"), "affine": ("surface_mean_mm", "landmark_mean_mm"),
        "cpd": ("surface_mean_mm", "landmark_mean_mm"), "landmarks_tps": ("landmark_mean_mm",)}
#: The calibrated mask-only baselines (landmark error only; docs/FITTING.md), with the calibration (mm).
MASK_ROWS = {"no_motion_centroids": 16.2, "affine_moments": 11.9, "cpd_moments": 8.5}
#: Every row of the tables, in order: the fit's rows, the correspondence field without the prior
#: (:func:`apply_loso_priors`), the calibrated mask-only rows.
TABLE_ROWS = (*ROWS, "model_surface_noprior", *MASK_ROWS)


def find_cases(data: Path, cases=None) -> dict[str, tuple[Path, ...]]:
    """``{"copdN": (exp mask, insp mask, exp landmarks, insp landmarks)}`` for every case in ``data``
    with all four files (or the cases numbered in ``cases``, which must all be there)."""
    data = Path(data)
    if not data.is_dir():
        raise ReadError(f"{data}: not a folder")
    names = (re.fullmatch(r"copd(\d+)_exp_mask\.nii\.gz", p.name) for p in data.iterdir())
    found = sorted(int(m.group(1)) for m in names if m)
    wanted = found if cases is None else [int(c) for c in cases]
    out = {}
    for n in wanted:
        files = tuple(data / f.format(n=n) for f in FILES)
        missing = [p.name for p in files if not p.is_file()]
        if missing and cases is not None:
            raise ReadError(f"{data}: case {n} is missing {', '.join(missing)}")
        if not missing:
            out[f"copd{n}"] = files
    if not out:
        raise ReadError(f"{data}: no DIR-Lab COPDgene case (copdN_exp_mask.nii.gz with its insp mask and landmarks)")
    return out


def incomplete_cases(data: Path, cases=None) -> dict[str, list[str]]:
    """``{"copdN": [names of its missing files]}`` for every case with some but not all of its four
    files in ``data`` (only those numbered in ``cases``, when given): :func:`find_cases` leaves them
    out; the caller says so."""
    data = Path(data)
    if not data.is_dir():
        return {}
    names = (re.fullmatch(r"copd(\d+)_(exp|insp)_(mask\.nii\.gz|landmarks\.txt)", p.name) for p in data.iterdir())
    seen = sorted({int(m.group(1)) for m in names if m})
    out = {}
    for n in seen if cases is None else [n for n in seen if n in {int(c) for c in cases}]:
        missing = [f.format(n=n) for f in FILES if not (data / f.format(n=n)).is_file()]
        if missing:
            out[f"copd{n}"] = missing
    return out


def copd_config(max_evaluations: int = 300) -> FitConfig:
    """The experiment's fit: a translation fitted with c1…c9 (``align="joint"``), the stiffness field,
    the interior landmark correction scored held out (5-fold), the baselines."""
    return FitConfig(stiffness=True, max_evaluations=max_evaluations, align="joint", landmark_fit=True,
                     command=COMMAND)


#: ``lungdeform cohort`` options giving the fit of :func:`copd_config` (the landmark fit is on by default).
COHORT_OPTIONS = ("--align", "joint", "--stiffness")


def cohort_manifest(found: dict[str, tuple[Path, ...]]) -> str:
    """The text of a cohort manifest (:func:`lungdeform.validate.subjects.cohort_manifest`) for the cases
    ``found`` (:func:`find_cases`): per case two rows, expiration then inspiration, side ``both``."""
    return subjects.cohort_manifest(as_subjects(found))


def as_subjects(found: dict[str, tuple[Path, ...]]) -> list[subjects.Subject]:
    """The cases ``found`` (:func:`find_cases`) as :class:`lungdeform.validate.subjects.Subject`."""
    return [subjects.Subject(name, None, (f[0], f[1]), (f[2], f[3])) for name, f in found.items()]


def write_cohort_manifest(found: dict[str, tuple[Path, ...]], path: Path) -> Path:
    """Write (atomically) :func:`cohort_manifest` of the cases ``found`` (:func:`find_cases`) to
    ``path``; return it."""
    return write_text(Path(path), cohort_manifest(found))


def settings_digest(files, side: str, config: FitConfig) -> str:
    """SHA-256 (hex, 16 digits) of the input files' bytes, the side, the fit settings, the CPD
    baseline's settings and the calibrated baselines' constants: equal digests mean an equal fit."""
    h = hashlib.sha256()
    for p in files:
        h.update(Path(p).read_bytes())
    mask = [B.MASK_CPD_POINTS, B.MASK_CPD_SIGMA, B.MASK_CPD_ALPHA, B.MASK_CPD_BETA_MM, B.MASK_CPD_SAMPLING,
            registration.SAMPLING]
    settings = {"side": side, "config": asdict(config), "cpd": asdict(B.CpdSettings()), "mask_baselines": mask}
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()[:16]


def mask_baselines(files, cache: SplitCache | None = None) -> dict[str, dict[str, dict[str, float]]]:
    """``{side: {row: {"landmark_mean_mm": …}}}``: the calibrated mask-only baselines of a case
    (:data:`MASK_ROWS`; :func:`lungdeform.evaluate.baselines.centroid_map`, ``moment_affine_map``,
    ``mask_cpd_map``), each lung's expiration points mapped to inspiration, on that lung's landmarks."""
    exp_mask, insp_mask, exp_lm, insp_lm = files
    images = [read_image(exp_mask), read_image(insp_mask)]
    splits = [require_split(im, cache=cache) for im in images]
    points = [read_elastix_points(exp_lm), read_elastix_points(insp_lm)]
    out = {}
    for k, side in enumerate(SIDES, start=1):
        rows, _ = landmarks_of_side(points, splits, side, [str(exp_lm), str(insp_lm)])
        a, b = points[0][rows], points[1][rows]
        masks = [sp.labels == k for sp in splits]
        voxels = [im.index_to_world(np.argwhere(m)[:, ::-1]) for im, m in zip(images, masks)]
        moment = B.moment_affine_map(*voxels)
        surfaces = [B.mask_surface_points(im, m) for im, m in zip(images, masks)]
        maps = {"no_motion_centroids": _affine_fn(B.centroid_map(*voxels)), "affine_moments": _affine_fn(moment),
                "cpd_moments": B.mask_cpd_map(moment, *surfaces)}
        out[side] = {name: {"landmark_mean_mm": float(np.linalg.norm(f(a) - b, axis=1).mean())}
                     for name, f in maps.items()}
    return out


class CaseBaselines:
    """One case's :func:`mask_baselines` (``files`` from :func:`find_cases`), computed on the first
    call and kept: ``(rows of side, seconds)``, ``seconds`` the time of computing both lungs' once."""

    def __init__(self, files, splits: SplitCache | None = None):
        self.files, self.splits, self.rows, self.seconds = files, splits, None, None

    def computed(self) -> "CaseBaselines":
        """Itself with both lungs' rows computed now and its splits let go (what a worker process needs
        is the rows; the splits travel to it once, apart)."""
        self(SIDES[0])
        self.splits = None
        return self

    def __call__(self, side: str) -> tuple[dict, float]:
        if self.rows is None:
            t0 = time.perf_counter()
            self.rows = mask_baselines(self.files, self.splits)
            self.seconds = time.perf_counter() - t0
        return self.rows[side], self.seconds


def _affine_fn(affine):
    mat, t = affine
    return lambda x: np.asarray(x, float) @ mat.T + t


def _done(folder: Path, digest: str) -> dict | None:
    path = folder / "metrics.json"
    if not path.is_file():
        return None
    try:
        metrics = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return metrics if metrics.get("settings_digest") == digest and "mask_baselines" in metrics else None


def run_lung(files, side: str, out: Path, config: FitConfig, mask_rows=None, *,
             progress: Progress | None = None, splits: SplitCache | None = None) -> tuple[dict, bool]:
    """``(metrics, fitted)``: one lung of a case (``files`` from :func:`find_cases`) fitted into the
    folder ``out`` with ``config``, unless its ``metrics.json`` already records the same
    :func:`settings_digest` (then read back, ``fitted`` False). ``mask_rows``: that lung's
    :func:`mask_baselines` (a dict), or a :class:`CaseBaselines` of the case (called after the fit),
    or None (computed). ``metrics["seconds"]`` is the fit's time, ``metrics["mask_baselines_seconds"]`` the
    mask-only baselines' (both lungs of the case, computed once; absent when given as a dict).
    ``splits``: where the case's masks are split (one :class:`SplitCache` for both lungs)."""
    out = Path(out)
    digest = settings_digest(files, side, config)
    done = _done(out, digest)
    if done is not None:
        return done, False
    t0 = time.perf_counter()
    exp_mask, insp_mask, exp_lm, insp_lm = files
    with atomic_dir(out) as tmp:  # the lung's folder is complete, with its digest, or absent
        inputs = FitInputs([exp_mask, insp_mask], side, landmarks=[exp_lm, insp_lm], splits=splits)
        fitted = run_fit(inputs, tmp, config, progress=progress)
        seconds = time.perf_counter() - t0
        if isinstance(mask_rows, dict):
            masks = {"mask_baselines": mask_rows}
        else:  # computed after the fit (which split the masks first, into the same cache), timed apart
            rows, rows_seconds = (mask_rows if mask_rows is not None else CaseBaselines(files, splits))(side)
            masks = {"mask_baselines": rows, "mask_baselines_seconds": rows_seconds}
        # the fit's metrics with the whole lung's time, its mask-only baselines and the digest
        metrics = {**fitted, "seconds": seconds, **masks, "settings_digest": digest}
        write_json(tmp / "metrics.json", metrics, strict=True, default=str)
    return metrics, True


def lung_row(metrics: dict) -> dict:
    """One lung's figures (:data:`ROWS` from the fit's metrics, :data:`MASK_ROWS` from its
    ``mask_baselines``), ``seconds`` (the fit) and ``mask_baselines_seconds`` (the case's mask-only
    baselines, both lungs; None when not recorded)."""
    row = {name: {k: metrics[name][k] for k in keys} for name, keys in ROWS.items() if name in metrics}
    row.update({name: dict(metrics["mask_baselines"][name]) for name in MASK_ROWS})
    row["seconds"] = metrics["seconds"]
    row["model_seconds"] = metrics.get("model_seconds")
    row["baseline_seconds"] = metrics.get("baseline_seconds")
    row["mask_baselines_seconds"] = metrics.get("mask_baselines_seconds")
    return row


def case_seconds(case: dict, split_seconds: float | None = None) -> dict:
    """A case's times (s): ``fit_seconds``, the sum of its lungs' fits (the whole pipeline, from
    reading the inputs to writing model.npz, metrics.json and report.html: :func:`run_lung`'s
    ``seconds``), ``model_fit_seconds``, the same less the pipeline's baselines and landmark-informed
    references (``baseline_seconds``, timed apart; so the writing of the outputs is included), and
    ``mask_baselines_seconds``, its mask-only baselines (both lungs, once); None when not recorded.
    With ``split_seconds`` (the lungs fitted at once after the masks were split, :func:`fit_case_lungs`)
    the sums include the split, and ``model_fit_wall_seconds`` is the wall time of the model's fit of
    the case: the split, then the slower lung (less its baselines)."""
    masks = [r.get("mask_baselines_seconds") for r in case.values() if r.get("mask_baselines_seconds") is not None]
    model = [None if r.get("baseline_seconds") is None else r["seconds"] - r["baseline_seconds"] for r in case.values()]
    split = split_seconds or 0.0
    out = {"fit_seconds": float(sum(r["seconds"] for r in case.values())) + split,
           "model_fit_seconds": float(sum(model)) + split if model and None not in model else None,
           "mask_baselines_seconds": float(max(masks)) if masks else None}
    if split_seconds is not None:
        out["model_fit_wall_seconds"] = split + max(model) if model and None not in model else None
    return out


def summarise(cases: dict, timing: dict | None = None) -> dict:
    """Medians over the lungs of every figure of :func:`lung_row`, and ``n_lungs``; over the cases,
    of their times (``timing``: per case :func:`case_seconds`, default computed from ``cases``)."""
    lungs = [row for case in cases.values() for row in case.values()]
    out: dict = {"n_lungs": len(lungs)}
    for row in lungs:
        for name, figs in row.items():
            if isinstance(figs, dict):
                out.setdefault(name, {k: None for k in figs})
    for name, figs in list(out.items()):
        if name == "n_lungs":
            continue
        for k in figs:
            vals = [r[name][k] for r in lungs if name in r and r[name].get(k) is not None]
            figs[k] = float(np.median(vals)) if vals else None
    out["seconds"] = float(np.median([r["seconds"] for r in lungs])) if lungs else None
    per_case = list(timing.values()) if timing is not None else [case_seconds(c) for c in cases.values() if c]
    for key in ("fit_seconds", "model_fit_seconds", "model_fit_wall_seconds", "mask_baselines_seconds"):
        vals = [t[key] for t in per_case if t.get(key) is not None]
        out[key] = float(np.median(vals)) if vals else None
    return out


def run_copd(data: Path, out: Path, config: FitConfig | None = None, cases=None, *,
             progress: Progress | None = None, workers: int = 1) -> dict:
    """Every case in ``data`` (:func:`find_cases`, ``cases`` a subset by number), both lungs, fitted
    (:func:`run_lung`) into ``out/copdN/<side>``; writes ``out/metrics.json`` (``cases``, ``summary``,
    ``refitted``: the lungs fitted this run, ``timing``: per case :func:`case_seconds`) and
    ``out/report.html``; returns the metrics. ``workers`` ≥ 2: each case's two lungs are fitted at once
    in two worker processes (:func:`fit_case_lungs`; more would idle)."""
    say = progress or silent
    config = copd_config() if config is None else config
    out = Path(out)
    found = find_cases(data, cases)
    result: dict = {"cases": {}, "refitted": [], "timing": {}, "settings": asdict(config)}
    with LungWorkers(min(workers, len(SIDES))) if workers > 1 else nullcontext() as pool:
        for name, files in found.items():
            if pool is None:
                lungs, split_seconds = _fit_case_serial(name, files, out, config, say), None
            else:
                lungs, split_seconds = fit_case_lungs(name, files, out, config, pool, say)
            for side, (metrics, fitted) in lungs.items():
                result["cases"].setdefault(name, {})[side] = lung_row(metrics)
                if fitted:
                    result["refitted"].append(f"{name}/{side}")
            result["timing"][name] = case_seconds(result["cases"][name], split_seconds)
    result["prior"] = apply_loso_priors(out, result["cases"])
    result["summary"] = summarise(result["cases"], result["timing"])
    result["calibration_mm"] = dict(MASK_ROWS)
    write_json(out / "metrics.json", result, strict=True, default=str)
    write_report(out / "report.html", result)
    return result


def _fit_case_serial(name: str, files, out: Path, config: FitConfig, say) -> dict[str, tuple[dict, bool]]:
    """``{side: (metrics, fitted)}``: the two lungs of a case one after the other (:func:`run_lung`)."""
    splits = SplitCache()  # each mask split once per case (by the first fit), not once per use
    masks = CaseBaselines(files, splits)  # both lungs' mask-only baselines, once, after the first fit
    lungs = {}
    for side in SIDES:
        say(f"{name} {side}: fitting (or reading the finished fit)")
        lungs[side] = run_lung(files, side, out / name / side, config, masks,
                               progress=lambda m, n=name, s=side: say(f"{n} {s}: {m}"), splits=splits)
    return lungs


def fit_case_lungs(name: str, files, out: Path, config: FitConfig, workers: LungWorkers,
                   say=silent) -> tuple[dict[str, tuple[dict, bool]], float]:
    """``({side: (metrics, fitted)}, split seconds)``: the two lungs of a case fitted at once by
    ``workers`` (:class:`lungdeform.evaluate.workers.LungWorkers`), each as :func:`run_lung` fits it.
    The parent first splits both masks (the seconds returned: the time a serial run counts in its
    first lung's fit) and computes the mask-only baselines (timed apart, as in a serial run); the
    workers get the splits, so neither splits again. A lung already finished with the same settings
    is read back, not sent."""
    folders = {side: out / name / side for side in SIDES}
    done = {side: _done(folders[side], settings_digest(files, side, config)) for side in SIDES}
    lungs = {side: (m, False) for side, m in done.items() if m is not None}
    todo = [side for side in SIDES if done[side] is None]
    if not todo:
        return lungs, 0.0
    say(f"{name}: splitting the masks")
    t0 = time.perf_counter()
    splits = SplitCache()
    splits.split_files(files[:2])
    split_seconds = time.perf_counter() - t0
    rows = CaseBaselines(files, splits).computed()  # both lungs' rows, once here; the workers get the splits apart
    say(f"{name}: fitting the {' and '.join(todo)} lung{'s' if len(todo) > 1 else ''} in "
        f"{min(len(todo), workers.count)} worker process{'es' if min(len(todo), workers.count) > 1 else ''}")
    with made_folder(out / name):  # made here, not by the first worker: an interrupted case leaves none
        finished = workers.map(_lung_task, [(files, side, folders[side], config, rows, splits) for side in todo])
    for side, task in zip(todo, finished):
        lungs[side] = task.value
        say(f"{name} {side}: done in {task.seconds:.1f} s")
    return {side: lungs[side] for side in SIDES}, split_seconds


def _lung_task(files, side: str, folder: Path, config: FitConfig, rows: "CaseBaselines",
               splits: SplitCache) -> tuple[dict, bool]:
    """:func:`run_lung` in a worker process (module-level, so that it pickles)."""
    return run_lung(files, side, folder, config, rows, splits=splits)


def prior_sample(folder: Path, subject: str, side: str) -> PriorSample | None:
    """A lung's :class:`~lungdeform.interior.motion_prior.PriorSample` from its fit's ``landmarks.npz``
    (the largest-volume target), with the taper at each landmark's depth below the fitted model's
    surface (``model.npz``: the surface the prior is played over), or None when the fit wrote none (a
    sliding interior)."""
    path = folder / "landmarks.npz"
    if not path.is_file():
        return None
    surface = load_model(folder / "model.npz").lungs[side].surface
    with np.load(path) as z:
        i = int(np.argmax(z["volumes_ml"]))
        points = z["landmarks"]
        return PriorSample(subject, side, z["centroid"], z["scale"], points, z["observed"][i] - z["surface_only"][i],
                           taper_at(points, surface))


def apply_loso_priors(out: Path, cases: dict) -> dict:
    """The population motion prior scored leave-one-subject-out: for each case, a prior learned on
    the other cases' lungs (:func:`lungdeform.interior.motion_prior.learn_motion_prior`) added to its
    correspondence field; in each lung's row ``model_surface_only`` becomes that (the field alone
    moves to ``model_surface_noprior``). Writes ``out/priors/<case>.json`` (what scored each case) and
    ``out/motion_prior.json`` (learned on every case, for new subjects). Returns what was done."""
    samples = {(name, side): prior_sample(out / name / side, name, side) for name in cases for side in cases[name]}
    if len({k[0] for k, v in samples.items() if v is not None}) < 2:
        return {"applied": False, "reason": "a leave-one-subject-out prior needs landmark fits of at least 2 cases"}
    for name, case in cases.items():
        train = [v for (n, _), v in samples.items() if n != name and v is not None]
        prior = learn_motion_prior(train)
        save_prior(out / "priors" / f"{name}.json", prior)
        for side, row in case.items():
            smp = samples[(name, side)]
            if smp is None:
                continue
            moved = smp.residual - smp.taper[:, None] * prior.displacement(smp.points, smp.centroid, smp.scale, side)
            row["model_surface_noprior"] = row.pop("model_surface_only")
            row["model_surface_only"] = {"landmark_mean_mm": float(np.linalg.norm(moved, axis=1).mean())}
    save_prior(out / "motion_prior.json", learn_motion_prior([v for v in samples.values() if v is not None]))
    return {"applied": True, "ridge": RIDGE, "scored": "leave one subject out", "all_cases": "motion_prior.json"}


def _cell(v) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.2f}"


def _table(rows: dict) -> str:
    """HTML table: one line per lung (or the summary), surface and landmark mean per method."""
    names = list(TABLE_ROWS)
    head = "".join(f"<th>{html.escape(n)}<br>surface / landmark</th>" for n in names)
    lines = [f"<tr><th>lung</th>{head}<th>s</th></tr>"]
    for lung, row in rows.items():
        cells = "".join(f"<td>{_cell(row.get(n, {}).get('surface_mean_mm'))} / "
                        f"{_cell(row.get(n, {}).get('landmark_mean_mm'))}</td>" for n in names)
        lines.append(f"<tr><td>{html.escape(lung)}</td>{cells}<td>{_cell(row.get('seconds'))}</td></tr>")
    return "<table border=1 cellspacing=0 cellpadding=3>" + "".join(lines) + "</table>"


def _timing_table(timing: dict) -> str:
    """HTML table: per case, the model's own fit and the whole fit pipeline (both lungs), and the
    mask-only baselines, seconds; with the lungs fitted at once (``--workers``), the model's fit in wall time too."""
    wall = any(t.get("model_fit_wall_seconds") is not None for t in timing.values())
    extra = "<th>model's fit, both lungs at once, wall (s)</th>" if wall else ""
    lines = ["<tr><th>case</th><th>model's fit, both lungs (s)</th><th>fit pipeline with its baselines, "
             f"both lungs (s)</th><th>mask-only baselines (s)</th>{extra}</tr>"]
    for name, t in timing.items():
        cell = f"<td>{_cell(t.get('model_fit_wall_seconds'))}</td>" if wall else ""
        lines.append(f"<tr><td>{html.escape(name)}</td><td>{_cell(t.get('model_fit_seconds'))}</td>"
                     f"<td>{_cell(t.get('fit_seconds'))}</td><td>{_cell(t.get('mask_baselines_seconds'))}</td>{cell}</tr>")
    return "<h2>Time per case</h2><table border=1 cellspacing=0 cellpadding=3>" + "".join(lines) + "</table>"


def write_report(path: Path, result: dict) -> Path:
    """``report.html``: the summary table, and per case its table and a bar plot of the mean
    landmark error per method and lung (:func:`lungdeform.plot.statistics.grouped_bars`)."""
    parts = ["<html><head><meta charset='utf-8'><title>DIR-Lab COPDgene</title></head><body>",
             "<h1>DIR-Lab COPDgene: expiration → inspiration, per lung (mm)</h1>",
             "<p>Landmark errors are held out from what they score; cpd, affine and the calibrated rows "
             f"use the masks only (calibration, medians over 10 lungs: {html.escape(str(MASK_ROWS))}).</p>",
             "<h2>Medians over the lungs</h2>",
             _table({f"median of {result['summary']['n_lungs']}": result["summary"]}),
             _timing_table(result.get("timing", {}))]
    for name, case in result["cases"].items():
        values = {side: {m: row[m]["landmark_mean_mm"] for m in row if isinstance(row[m], dict)
                         and "landmark_mean_mm" in row[m]} for side, row in case.items()}
        fig = grouped_bars(values, title=f"{name}: mean landmark error", ylabel="mm")
        b64 = base64.b64encode(png_bytes(fig)).decode("ascii")
        parts += [f"<h2>{html.escape(name)}</h2>", _table(case), f'<img alt="{html.escape(name)}" '
                  f'src="data:image/png;base64,{b64}">']
    parts.append("</body></html>")
    return write_text(path, "\n".join(parts))


def parse_cases(text: str | None) -> list[int] | None:
    """``"1,3"`` → ``[1, 3]``; None or empty → None (every case)."""
    if not text:
        return None
    try:
        nums = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise InputError(f"cases must be case numbers separated by commas, e.g. 1,3; got {text!r}") from None
    if not nums or any(n < 1 for n in nums):
        raise InputError(f"cases must be case numbers ≥ 1 separated by commas, got {text!r}")
    return sorted(set(nums))
