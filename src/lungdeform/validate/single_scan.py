"""One scan to a breathing lung: the defaults scored on real lungs (``lungdeform validate single-scan``).

The experiment behind docs/DEFAULTS.md. For every two-volume subject in a data folder (the DIR-Lab
COPDgene layout, :func:`lungdeform.validate.copd.find_cases`, both lungs; or the ITK right lung pair,
:func:`lungdeform.validate.itk_pair.find_pair`), per lung:

1. the model mesh of the smaller-volume scan alone (:func:`lungdeform.evaluate.placement.model_mesh`, as
   ``lungdeform fit`` and the COPDgene experiment use; the larger-volume scan is not looked at);
2. a prediction at the larger volume, given only that volume (mL, the number a spirometer gives,
   anchored on the model mesh's own end-exhale volume), by each row:

   - ``default``: :func:`~lungdeform.model.lung.build_lung` with the population default
     (:mod:`lungdeform.model.population`): the shipped one, except for a subject the shipped default
     was learned from, which gets a default learned without it (leave one subject out, from the
     other subjects in the folder: :func:`lungdeform.cohort.default.learn_default`);
   - ``paper``: the same with Table I;
   - ``isotropic``: scaling about the solid's centroid to the volume;
   - ``dome``, ``dome_scaling``: given also the dome excursion measured from the two masks, the default
     split to move the dome that far, and the fair baseline scaling given the same number
     (:mod:`lungdeform.validate.dome_rows`);
   - ``fitted`` (``with_fitted``): the two-scan fit of that lung (c1…c9, a translation, the
     direction correction; uniform stiffness), a ceiling;

3. each prediction moved by the one translation that brings it closest to the real larger-volume
   surface (:func:`best_translation`; the same for every row: the phases of the COPDgene masks were
   re-centred and the ITK scans carry a table shift), the landmarks by the same translation;
4. scored: the symmetric mean surface distance (mm, crop faces left out) and the mean landmark
   error (mm), and per axis (LR, AP, SI) the mean |displacement| of the landmarks, predicted and
   observed (after the row's translation).

``metrics.json``: ``lungs.<subject>/<side>.<row>.{surface_mean_mm, landmark_mean_mm, translation_mm,
landmark_motion_mm: {predicted, observed}}``, ``summary.<row>.{surface_mean_mm, landmark_mean_mm}``
(medians over the lungs), ``summary.n_lungs``, ``defaults`` (which default scored which lung).
"""

from __future__ import annotations

import base64
import hashlib
import html
import io
import json
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_bytes, write_json, write_text
from lungdeform.cohort.default import DefaultSample, learn_default
from lungdeform.errors import ReadError
from lungdeform.evaluate.inputs import read_inputs
from lungdeform.evaluate.placement import place_targets
from lungdeform.fit.config import FitInputs
from lungdeform.fit.fitting import FitSettings, fit_lung, to_lung_model
from lungdeform.fit.objective import Target
from lungdeform.geometry.distance import SurfaceDistance, symmetric_distance
from lungdeform.geometry.mesh import Surface, face_normals, thinned
from lungdeform.geometry.moments import solid_moments
from lungdeform.model.lung import LungModel, build_lung
from lungdeform.model.population import PopulationDefault, paper_default, resolve_default
from lungdeform.plot.figure import png_bytes
from lungdeform.plot.statistics import grouped_bars
from lungdeform.progress import Progress, silent
from lungdeform.segment.split import SIDES, SplitCache

from . import copd, dome_rows, itk_pair

#: The rows, in report order (``dome``, ``dome_scaling``: :mod:`lungdeform.validate.dome_rows`).
ROWS = ("default", "dome", "dome_scaling", "paper", "isotropic", "fitted")
AXES = ("LR", "AP", "SI")
#: The two-scan fit of a training (and ``fitted``) lung: optimiser budget.
FIT_EVALUATIONS = 300


@dataclass(frozen=True)
class Subject:
    """One subject's files: ``name``, the ``sides`` to score, ``scans`` (smaller volume, larger
    volume) and ``landmarks`` (one elastix point file per scan, rows corresponding)."""

    name: str
    sides: tuple[str, ...]
    scans: tuple[Path, Path]
    landmarks: tuple[Path, Path]

    @cached_property
    def digest(self) -> str:
        """SHA-256 (16 hex digits) of the smaller-volume scan's bytes: who the subject is."""
        return hashlib.sha256(Path(self.scans[0]).read_bytes()).hexdigest()[:16]


@dataclass(frozen=True, eq=False)
class LungPair:
    """One lung at two volumes, as the experiment sees it.

    Attributes
    ----------
    subject : str
    side : str
    rest : Surface
        Model mesh of the smaller-volume scan, mm LPS.
    keep : (n,) bool
        Its vertices away from crop faces (measured).
    target : Target
        The larger-volume surface in its own scan's frame, its crop faces not measured.
    volume_ml : float
        The larger volume, anchored on the model mesh (``rest.volume_ml`` + the measured change), mL.
    landmarks_rest, landmarks_target : (m, 3) float
        Landmarks of the lung in each scan, mm LPS (each in its scan's frame).
    """

    subject: str
    side: str
    rest: Surface
    keep: np.ndarray
    target: Target
    volume_ml: float
    landmarks_rest: np.ndarray
    landmarks_target: np.ndarray

    @cached_property
    def target_distance(self) -> SurfaceDistance:
        """Exact distances to the larger-volume surface, built once for every row of the lung."""
        return SurfaceDistance(self.target.surface.vertices, self.target.surface.faces)


def find_subjects(data: Path) -> list[Subject]:
    """The two-volume subjects in ``data``: COPDgene cases (both lungs) or the ITK right lung pair."""
    data = Path(data)
    if not data.is_dir():
        raise ReadError(f"{data}: not a folder")
    try:
        files = itk_pair.find_pair(data)
        return [Subject("itk", ("right",), (files[0], files[1]), (files[2], files[3]))]
    except ReadError:
        pass
    try:
        cases = copd.find_cases(data)
    except ReadError:
        raise ReadError(f"{data}: no two-volume subject (DIR-Lab COPDgene copdN_exp/insp masks and landmarks, "
                        "or the ITK right lung pair)") from None
    return [Subject(name, SIDES, (f[0], f[1]), (f[2], f[3])) for name, f in cases.items()]


def read_pair(subject: Subject, side: str, progress: Progress | None = None,
              splits: SplitCache | None = None) -> LungPair:
    """One lung of ``subject`` (:class:`LungPair`): both scans read, the landmarks of that lung;
    ``splits``: where a mask holding both lungs is split (one cache for both lungs of a subject)."""
    inputs = FitInputs(list(subject.scans), side, landmarks=list(subject.landmarks), splits=splits)
    read = read_inputs(inputs, True, progress)
    placed = place_targets(read, read.paths, list(subject.landmarks), "none", progress)
    volume = placed.rest.volume_ml + read.volumes_ml[1] - read.volumes_ml[0]
    return LungPair(subject.name, side, placed.rest, placed.keep, placed.targets[0], float(volume),
                    read.landmarks[0], read.landmarks[1])


def best_translation(vertices, faces, keep, target: Target, iterations: int = 50, *,
                     target_distance: SurfaceDistance | None = None) -> np.ndarray:
    """``t : (3,) float`` mm: the translation of the surface ``(vertices (n, 3) mm, faces)`` that
    minimises its symmetric closest-point distance to ``target`` (kept vertices on both sides): the
    fixed point of iterated closest points, where the mean residual of both directions (pooled) is
    zero, to within :data:`TOLERANCE_MM` (its last step; or after ``iterations`` exact steps).
    ``target_distance``: a prepared :class:`SurfaceDistance` of ``target.surface`` (reused).

    Plain iterated closest points creeps along the directions the surfaces slide in (on the COPDgene
    lungs it had stopped at 50 steps, up to 0.8 mm short of it), so each step here is a Gauss-
    Newton step on the mean squared closest-point distance (point-to-plane: :func:`_evaluate`; same
    fixed point), coarse to fine: first on a seeded subsample (:data:`COARSE_POINTS` per side, each
    side weighted as all its points), then on all points (:func:`_descend`)."""
    tgt = target.surface
    kt = np.ones(tgt.n_vertices, bool) if target.keep is None else np.asarray(target.keep, bool)
    vertices = np.asarray(vertices, float)
    to_target = target_distance or SurfaceDistance(tgt.vertices, tgt.faces)
    own = SurfaceDistance(vertices, faces)
    pts, tpts = vertices[np.asarray(keep, bool)], tgt.vertices[kt]
    share = len(pts) / (len(pts) + len(tpts))
    full = [_Side(to_target, pts, 1.0, share, face_normals(to_target.vertices, to_target.faces)),
            _Side(own, tpts, -1.0, 1.0 - share, face_normals(own.vertices, own.faces))]
    coarse = [_Side(s.distance, s.points[thinned(len(s.points), COARSE_POINTS, seed=k)], s.sign, s.weight, s.normals)
              for k, s in enumerate(full)]
    t = _descend(coarse, np.zeros(3), 10 * TOLERANCE_MM, 4 * iterations)
    return _descend(full, t, TOLERANCE_MM, iterations)


#: :func:`best_translation`: points per side in its coarse stage (a seeded subsample).
COARSE_POINTS = 4000
#: :func:`best_translation`: it stops where its Newton step (the distance to the fixed point it
#: estimates) is below this, mm. Exact closest points switch faces as the surface moves, so on a lung
#: the mean residual stays noisy at ~1e-4 mm (steps of ~5e-4 mm) however long one iterates.
TOLERANCE_MM = 1e-3


@dataclass(frozen=True, eq=False)
class _Side:
    """One direction of the symmetric closest-point distance: ``points (k, 3)`` mm moved by
    ``sign · t`` to the surface of ``distance`` (``normals (m, 3)``, unit, per face), their mean
    residual counting ``weight`` (this direction's share of all the points)."""

    distance: SurfaceDistance
    points: np.ndarray
    sign: float
    weight: float
    normals: np.ndarray


def _evaluate(sides, t) -> tuple[np.ndarray, float, np.ndarray]:
    """At translation ``t``: ``(step (3,) mm, energy mm², curvature (3, 3))``: the pooled mean
    closest-point residual (the plain iterated-closest-points step; minus half the gradient of the
    energy), the pooled mean squared distance, and the point-to-plane curvature (mean n nᵀ of the
    closest faces' normals: the Gauss-Newton Hessian of half the energy)."""
    step, energy, curvature = np.zeros(3), 0.0, np.zeros((3, 3))
    for s in sides:
        moved = s.points + s.sign * t
        _, closest, face = s.distance.query(moved)
        r = s.sign * (closest - moved)
        n = s.normals[face]
        step += s.weight * r.mean(axis=0)
        energy += s.weight * float(np.mean(np.einsum("ij,ij->i", r, r)))
        curvature += s.weight * (n.T @ n) / len(n)
    return step, energy, curvature


def _descend(sides, t, tol: float, iterations: int) -> np.ndarray:
    """Gauss-Newton steps ``t ← t + H⁻¹ step`` (:func:`_evaluate` at ``t``) from ``t`` until one is
    shorter than ``tol`` mm (the point after it is returned; after ``iterations`` evaluations, the last
    point kept). A step that raised the energy is taken back and replaced by the plain step from the
    point before (iterated closest points, which does not raise it)."""
    best, plain = None, False  # best: (t, energy, step) of the last point kept
    for _ in range(iterations):
        step, energy, gauss = _evaluate(sides, t)
        if best is not None and energy > best[1] and not plain:
            t, plain = best[0] + best[2], True
            continue
        best, plain = (t, energy, step), False
        move = np.linalg.lstsq(gauss, step, rcond=None)[0]
        if np.linalg.norm(move) < np.linalg.norm(step):  # the curvature (trace 1) lacks a direction: plain step
            move = step
        t = t + move
        if np.linalg.norm(move) < tol:
            return t
    return best[0] if best is not None else t


def score(pair: LungPair, vertices, landmarks) -> dict:
    """One row's figures for ``pair`` from its predicted ``vertices (n, 3)`` and ``landmarks (m, 3)``
    (mm LPS, the smaller-volume scan's frame), after :func:`best_translation`."""
    t = best_translation(vertices, pair.rest.faces, pair.keep, pair.target, target_distance=pair.target_distance)
    moved = Surface(np.asarray(vertices) + t, pair.rest.faces, pair.rest.name)
    sd = symmetric_distance(moved, pair.target.surface, keep_a=pair.keep, keep_b=pair.target.keep,
                            b_distance=pair.target_distance)
    err = np.linalg.norm(landmarks + t - pair.landmarks_target, axis=1)
    predicted = np.abs(landmarks - pair.landmarks_rest).mean(axis=0)
    observed = np.abs(pair.landmarks_target - t - pair.landmarks_rest).mean(axis=0)
    return {"surface_mean_mm": float(sd.stats.mean), "landmark_mean_mm": float(err.mean()),
            "translation_mm": t.tolist(),
            "landmark_motion_mm": {"axes": list(AXES), "predicted": predicted.tolist(), "observed": observed.tolist()}}


def isotropic(pair: LungPair) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, landmarks)``: scaling about the solid's centroid to :attr:`LungPair.volume_ml`."""
    _, mu, _ = solid_moments(pair.rest.vertices, pair.rest.faces)
    s = (pair.volume_ml / pair.rest.volume_ml) ** (1.0 / 3.0)
    return mu + (pair.rest.vertices - mu) * s, mu + (pair.landmarks_rest - mu) * s


def modelled(pair: LungPair, lung: LungModel) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices, landmarks)`` of ``lung`` (built on ``pair.rest``) at the larger volume, exactly."""
    return (lung.surface_at(pair.volume_ml, exact=True).vertices,
            lung.points_at(pair.landmarks_rest, pair.volume_ml, exact=True))


@dataclass(frozen=True, eq=False)
class FittedLung:
    """What the experiment keeps of a lung's two-scan fit (:func:`fit_pair`): ``constants (9,)``,
    ``stiffness (n,)``, ``directions (n, 3)``, ``displacement (n, 3)`` (mm per ``unit_ml``),
    ``force (n,)``, ``translation (3,)`` mm (of the larger-volume scan), ``unit_ml``, ``calibration_ml``."""

    constants: np.ndarray
    stiffness: np.ndarray
    directions: np.ndarray
    displacement: np.ndarray
    force: np.ndarray
    translation: np.ndarray
    unit_ml: float
    calibration_ml: float


def fit_pair(pair: LungPair) -> FittedLung:
    """The two-scan fit of ``pair`` (c1…c9, a translation, the direction correction; uniform stiffness)."""
    fit = fit_lung(pair.rest, pair.side, [pair.target],
                   FitSettings(translate=True, direction_degree=3, max_evaluations=FIT_EVALUATIONS), keep=pair.keep)
    return FittedLung(fit.constants, fit.stiffness, fit.directions, fit.displacement, fit.force,
                      np.asarray(fit.translations[0], float), float(fit.unit_ml), float(fit.calibration_ml))


def cached_fit(pair: LungPair, subject: Subject, folder: Path) -> FittedLung:
    """:func:`fit_pair`, kept in ``folder/<subject>_<side>.npz`` under a digest of both scans, the side
    and the fit settings, and read back from there when the digest matches (a rerun resumes)."""
    h = hashlib.sha256(f"{subject.digest}/{Path(subject.scans[1]).stat().st_size}/{pair.side}/"
                       f"{FIT_EVALUATIONS}/{pair.rest.n_vertices}".encode()).hexdigest()[:16]
    path = Path(folder) / f"{subject.name}_{pair.side}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                if str(z["digest"]) == h:
                    return FittedLung(*(z[k] for k in ("constants", "stiffness", "directions", "displacement", "force",
                                                         "translation")), float(z["unit_ml"]), float(z["calibration_ml"]))
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is fitted again
    fit = fit_pair(pair)
    buf = io.BytesIO()
    np.savez(buf, digest=np.array(h), **{k: np.asarray(getattr(fit, k)) for k in FittedLung.__dataclass_fields__})
    write_bytes(path, buf.getvalue())
    return fit


def fitted_model(pair: LungPair, fit: FittedLung) -> LungModel:
    """The two-scan fit as a :class:`LungModel` on ``pair.rest`` (the ``fitted`` row)."""
    return to_lung_model(pair.rest, pair.side, fit)


def sample_of(pair: LungPair, fit: FittedLung) -> DefaultSample:
    """What :func:`lungdeform.cohort.default.learn_default` takes from one fitted lung."""
    return DefaultSample(pair.subject, pair.side, pair.rest, fit.constants, fit.directions, fit.force,
                         pair.landmarks_rest, pair.landmarks_target + fit.translation,
                         pair.volume_ml - pair.rest.volume_ml)


@dataclass(frozen=True)
class SingleScanConfig:
    """How :func:`run_single_scan` runs: ``default`` (None: the shipped default, leave one subject out
    for the subjects it was learned from; else a name or file for every lung, as it is),
    ``with_fitted`` (add the ``fitted`` row) and ``train`` (folders of further subjects, not scored,
    that a leave-one-subject-out default also learns from: the ITK pair is one subject)."""

    default: str | Path | None = None
    with_fitted: bool = False
    train: tuple = ()


def _defaults_for(subjects, given: PopulationDefault | None, seen: set[str], pairs, fits,
                  say) -> dict[str, tuple[PopulationDefault, str]]:
    """Per subject: ``(the default that scores it, how it was chosen)``: ``given`` for all, else the
    shipped default, learned anew without each subject in ``seen`` (those it was learned from)."""
    if given is not None:
        return {s.name: (given, f"given: {given.name}") for s in subjects}
    shipped = resolve_default(None)
    out = {}
    for s in subjects:
        if s.name not in seen:
            out[s.name] = (shipped, "shipped")
            continue
        train = [sample_of(pairs[k], fits[k]) for k in pairs if k[0] != s.name]
        say(f"{s.name}: learning a default without it ({len(train)} lungs of the other subjects)")
        out[s.name] = (learn_default(train, name=f"population without {s.name}"),
                       "leave one subject out (the shipped default saw this subject)")
    return out


def _seen_by_shipped(subjects, given: PopulationDefault | None) -> set[str]:
    """The subjects the shipped default was learned from (none when a default is given)."""
    if given is not None:
        return set()
    digests = set(resolve_default(None).provenance.get("subject_digests", {}).values())
    return {s.name for s in subjects if s.digest in digests}


def _training_pairs(folders, scored: set[str], say) -> tuple[dict[tuple[str, str], LungPair], list[Subject]]:
    """Every lung of the subjects in ``folders`` (not scored; only learned from), and those subjects."""
    out, subjects = {}, []
    for folder in folders:
        for s in find_subjects(folder):
            subjects.append(s)
            if s.name in scored:
                raise ReadError(f"{folder}: subject {s.name!r} is also in the data folder")
            splits = SplitCache()  # each mask split once per subject, not once per lung
            for side in s.sides:
                say(f"{s.name} {side}: reading both scans (training only)")
                out[(s.name, side)] = read_pair(s, side, splits=splits)
    return out, subjects


def _check_leave_one_out(seen: set[str], names: set[str]) -> None:
    """ReadError, before any fit, when a subject the shipped default saw has fewer than two others to learn from."""
    for name in sorted(seen):
        if len(names - {name}) < 2:
            raise ReadError(f"{name}: the shipped default was learned from this subject; leaving it out needs "
                            "at least two other subjects (add folders of them with --train, or give --default)")


def run_single_scan(data: Path, out: Path, config: SingleScanConfig = SingleScanConfig(), *,
                    progress: Progress | None = None) -> dict:
    """The experiment (module docstring) on every subject in ``data``; writes ``out/metrics.json`` and
    ``out/report.html``; returns the metrics."""
    say = progress or silent
    subjects = find_subjects(data)
    given = None if config.default is None else resolve_default(config.default)  # refused before any reading
    pairs: dict[tuple[str, str], LungPair] = {}
    for s in subjects:
        splits = SplitCache()  # each mask split once per subject, not once per lung
        for side in s.sides:
            say(f"{s.name} {side}: reading both scans")
            pairs[(s.name, side)] = read_pair(s, side, lambda m, n=s.name, sd=side: say(f"{n} {sd}: {m}"), splits)
    seen = _seen_by_shipped(subjects, given)
    fits, extra = {}, {}
    if config.with_fitted or seen:
        extra, more = _training_pairs(config.train, {s.name for s in subjects}, say)
        by_name = {s.name: s for s in [*subjects, *more]}
        _check_leave_one_out(seen, {k[0] for k in {**pairs, **extra}})
        for key, pair in {**pairs, **extra}.items():
            say(f"{key[0]} {key[1]}: two-scan fit (for leave-one-subject-out learning and the fitted row)")
            fits[key] = cached_fit(pair, by_name[key[0]], Path(out) / "fits")
    chosen = _defaults_for(subjects, given, seen, {**pairs, **extra}, fits, say)
    lungs, build_seconds = {}, {}
    for key, pair in pairs.items():
        say(f"{key[0]} {key[1]}: predicting the larger volume from the smaller scan alone")
        lungs[f"{key[0]}/{key[1]}"], build_seconds[f"{key[0]}/{key[1]}"] = _score_lung(
            pair, chosen[key[0]][0], fits.get(key) if config.with_fitted else None)
    result = {"lungs": lungs, "summary": summarise(lungs),
              "defaults": {s.name: {"how": how, **d.record()} for s in subjects for d, how in [chosen[s.name]]},
              "build_seconds": build_seconds,
              "protocol": "each prediction moved by the one translation that best fits the real larger-volume "
                          "surface (the same for every row); landmarks moved by it too"}
    write_json(Path(out) / "metrics.json", result, strict=True)
    write_report(Path(out) / "report.html", result)
    return result


def _score_lung(pair: LungPair, default: PopulationDefault, fit: FittedLung | None) -> tuple[dict, float]:
    """One lung's rows, and the time of building its default model (s)."""
    t0 = time.perf_counter()
    lung = build_lung(pair.rest, pair.side, default=default)
    seconds = time.perf_counter() - t0
    rows = {"default": score(pair, *modelled(pair, lung)),
            "paper": score(pair, *modelled(pair, build_lung(pair.rest, pair.side, default=paper_default()))),
            "isotropic": score(pair, *isotropic(pair)), **dome_rows.scored_rows(pair, default, score)}
    if fit is not None:
        rows["fitted"] = score(pair, *modelled(pair, fitted_model(pair, fit)))
    return rows, seconds


def summarise(lungs: dict) -> dict:
    """Medians over the lungs of each row's surface and landmark means, and ``n_lungs``."""
    out: dict = {"n_lungs": len(lungs)}
    for row in ROWS:
        got = [v[row] for v in lungs.values() if row in v]
        if got:
            out[row] = {k: float(np.median([g[k] for g in got])) for k in ("surface_mean_mm", "landmark_mean_mm")}
    iso = out.get("isotropic")
    for row in ROWS:
        if iso and row in out:
            out[row]["surface_vs_isotropic"] = out[row]["surface_mean_mm"] / iso["surface_mean_mm"]
            out[row]["landmark_vs_isotropic"] = out[row]["landmark_mean_mm"] / iso["landmark_mean_mm"]
    return out


def _figure(values: dict, title: str) -> str:
    fig = grouped_bars(values, title=title, ylabel="mm")
    return f'<img alt="{html.escape(title)}" src="data:image/png;base64,{base64.b64encode(png_bytes(fig)).decode()}">'


def write_report(path: Path, result: dict) -> Path:
    """``report.html``: the medians, per lung the rows' errors as bars and the landmark motion per axis."""
    rows = [r for r in ROWS if r in result["summary"]]
    head = "".join(f"<th>{r}</th>" for r in rows)
    med = "".join(f"<td>{result['summary'][r]['surface_mean_mm']:.2f} / {result['summary'][r]['landmark_mean_mm']:.2f}"
                  f"</td>" for r in rows)
    per = "".join(f"<tr><td>{html.escape(k)}</td>" + "".join(
        f"<td>{v[r]['surface_mean_mm']:.2f} / {v[r]['landmark_mean_mm']:.2f}</td>" if r in v else "<td>–</td>"
        for r in rows) + "</tr>" for k, v in result["lungs"].items())
    axes = {}
    for k, v in result["lungs"].items():
        axes[f"{k} observed"] = dict(zip(AXES, v["default"]["landmark_motion_mm"]["observed"]))
        for r in ("default", "paper"):
            axes[f"{k} {r}"] = dict(zip(AXES, v[r]["landmark_motion_mm"]["predicted"]))
    parts = ["<html><head><meta charset='utf-8'><title>Single scan</title></head><body>",
             "<h1>One scan to the larger volume: surface / landmark mean error (mm)</h1>",
             f"<p>{html.escape(result['protocol'])}. Defaults: "
             f"{html.escape(json.dumps(result['defaults']))}</p>",
             f"<h2>Medians over {result['summary']['n_lungs']} lungs</h2>",
             f"<table border=1 cellspacing=0 cellpadding=3><tr><th></th>{head}</tr><tr><td>median</td>{med}</tr>"
             f"{per}</table>",
             _figure({k: {r: v[r]["surface_mean_mm"] for r in rows if r in v} for k, v in result["lungs"].items()},
                     "surface mean distance per lung"),
             _figure({k: {r: v[r]["landmark_mean_mm"] for r in rows if r in v} for k, v in result["lungs"].items()},
                     "landmark mean error per lung"),
             "<h2>Mean |landmark displacement| per axis (mm): observed and predicted</h2>",
             _figure(axes, "landmark motion per axis"), "</body></html>"]
    return write_text(path, "\n".join(parts))


def learn_from_folders(folders, name: str = "population", *,
                       progress: Progress | None = None) -> PopulationDefault:
    """A population default learned from every two-volume subject in ``folders``
    (:func:`find_subjects`): each lung fitted on its own (:func:`fit_pair`), then pooled
    (:func:`lungdeform.cohort.default.learn_default`). The provenance records the subjects, the
    digest of each one's smaller-volume scan (so that ``validate single-scan`` scores a subject it
    saw leave one subject out) and the data's citations."""
    say = progress or silent
    samples, digests = [], {}
    for folder in folders:
        for s in find_subjects(folder):
            if s.name in digests:
                raise ReadError(f"{folder}: a second subject named {s.name!r}")
            digests[s.name] = s.digest
            splits = SplitCache()  # each mask split once per subject, not once per lung
            for side in s.sides:
                say(f"{s.name} {side}: reading and fitting both scans")
                pair = read_pair(s, side, lambda m, n=s.name, sd=side: say(f"{n} {sd}: {m}"), splits)
                samples.append(sample_of(pair, fit_pair(pair)))
    return learn_default(samples, name=name, provenance={"subject_digests": digests, "citation": CITATIONS,
                                                         "source": f"{name}: learned by lungdeform learn-default"})


#: Where the shared subjects come from (recorded in a learned default's provenance; NOTICE, docs/DEFAULTS.md).
CITATIONS = ("DIR-Lab COPDgene: Castillo R. et al., Phys Med Biol 2013;58:2861 (research use with citation); "
             "ITKElastix example data, Apache-2.0")
