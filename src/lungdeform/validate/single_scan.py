"""One scan to a breathing lung: the defaults scored on real lungs (``lungdeform validate single-scan``).

The experiment behind docs/DEFAULTS.md. For every two-volume subject in the data folders
(:func:`lungdeform.validate.subjects.find_subjects`: any folder of ``NAME_exp_mask`` / ``NAME_insp_mask``
pairs, landmarks optional, such as the DIR-Lab COPDgene and Learn2Reg masks; or the ITK right lung
pair), per lung (:func:`lungdeform.validate.lung_pair.read_pair`; a lung cut by its field of view is
scored with the cut left out of the surface distance):

1. the model mesh of the smaller-volume scan alone (:func:`lungdeform.evaluate.placement.model_mesh`, as
   ``lungdeform fit`` and the COPDgene experiment use; the larger-volume scan is not looked at);
2. a prediction at the larger volume, given only that volume (mL, the number a spirometer gives,
   anchored on the model mesh's own end-exhale volume), by each row (:data:`ROW_PREDICTORS`; a row is a
   function of the lung and of what may be learned without its subject, :class:`Training`, so that
   further rows plug in through :attr:`SingleScanConfig.rows`):

   - ``default``: :func:`~lungdeform.model.lung.build_lung` with the population default
     (:mod:`lungdeform.model.population`): the shipped one (or a learned default file), except for a
     subject it was learned from, which gets a default learned without it (leave one subject out,
     from the default's other subjects among those read: :func:`lungdeform.cohort.default.learn_default`);
   - ``paper``: the same with Table I;
   - ``isotropic``: scaling about the solid's centroid to the volume;
   - ``dome``, ``dome_scaling``: given also the dome excursion measured from the two masks, the default
     split to move the dome that far, and the fair baseline scaling given the same number
     (:mod:`lungdeform.validate.dome_rows`);
   - ``fitted`` (``with_fitted``): the two-scan fit of that lung (c1…c9, a translation, the
     direction correction; uniform stiffness), a ceiling;

3. each prediction moved by the one translation that brings it closest to the real larger-volume
   surface (:func:`~lungdeform.validate.translation.best_translation`; the same for every row: the phases
   of the COPDgene masks were re-centred, the Learn2Reg scans cropped apart, the ITK scans carry a table
   shift), the landmarks by the same translation;
4. scored: the symmetric mean surface distance (mm, crop faces left out), per surface region (apex,
   base, costal, mediastinal: :mod:`lungdeform.geometry.regions`, the area-weighted mean distance of
   the prediction's vertices to the real surface), and, for a lung with landmarks, the mean landmark
   error (mm) and per axis (LR, AP, SI) the mean |displacement| of the landmarks, predicted and
   observed (after the row's translation).

``metrics.json``: ``lungs.<subject>/<side>.<row>.{surface_mean_mm, regions_mm, landmark_mean_mm (null
without landmarks), translation_mm, landmark_motion_mm: {predicted, observed}, seconds}``, per lung
``lung_info`` (``landmarks``, ``cut``, ``folder``); ``summary``: ``n_lungs`` (every lung scored),
``n_lungs_landmarks``, ``n_lungs_cut``, and per row ``surface_mean_mm`` (median over every lung),
``landmark_mean_mm`` (median over the lungs with landmarks), ``surface_mean_mm_landmark_lungs``, ratios
to isotropic scaling and ``regions_mm`` (medians per region); ``summary.subsets`` the same over the
lungs with landmarks, without, the whole (uncut) lungs and each data folder; ``defaults`` (which
default scored which subject), ``region_shares``. ``report.html``: the tables and figures
(:mod:`lungdeform.validate.single_scan_report`).

The two-scan fits (for the leave-one-subject-out defaults and the ``fitted`` row) and the lungs as read
are kept in a cache folder (``SingleScanConfig.cache``, default ``OUT``: ``fits/`` and ``pairs/``), under
digests of what they were made from (:mod:`lungdeform.validate.fitted_lung`), so that a rerun, another
output folder or ``learn-default`` reuses them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_json
from lungdeform.cohort.default import learn_default
from lungdeform.errors import ReadError
from lungdeform.geometry.distance import symmetric_distance
from lungdeform.geometry.mesh import Surface
from lungdeform.geometry.regions import REGIONS, region_means, region_shares, surface_regions
from lungdeform.model.lung import LungModel, build_lung
from lungdeform.model.population import NAMES, PopulationDefault, paper_default, resolve_default
from lungdeform.progress import Progress, silent
from lungdeform.segment.split import SplitCache

from .dome_rows import dome_row, dome_scaling_row
from .fitted_lung import FIT_EVALUATIONS, FittedLung, cached_fit, fit_pair, fitted_model, sample_of
from .lung_pair import LungPair, cached_pair, isotropic_vertices, lung_sides, read_pair
from .single_scan_report import row_names, write_report
from .subjects import Subject, find_subjects
from .translation import COARSE_POINTS, TOLERANCE_MM, best_translation

__all__ = ["AXES", "COARSE_POINTS", "FIT_EVALUATIONS", "ROWS", "ROW_PREDICTORS", "TOLERANCE_MM", "FittedLung",
           "LungPair", "SingleScanConfig", "Subject", "Training", "best_translation", "cached_fit", "find_subjects",
           "fit_pair", "fitted_model", "isotropic", "learn_from_folders", "modelled", "read_pair", "run_single_scan",
           "sample_of", "score", "summarise"]

AXES = ("LR", "AP", "SI")


def score(pair: LungPair, vertices, landmarks=None, regions=None) -> dict:
    """One row's figures for ``pair`` from its predicted ``vertices (n, 3)`` and ``landmarks (m, 3)``
    (mm LPS, the smaller-volume scan's frame; None for a lung without landmarks), after
    :func:`best_translation`; ``regions``: the labels of ``pair.rest``'s vertices
    (:func:`lungdeform.geometry.regions.surface_regions`), for the distance per region."""
    t = best_translation(vertices, pair.rest.faces, pair.keep, pair.target, target_distance=pair.target_distance)
    moved = Surface(np.asarray(vertices) + t, pair.rest.faces, pair.rest.name)
    sd = symmetric_distance(moved, pair.target.surface, keep_a=pair.keep, keep_b=pair.target.keep,
                            b_distance=pair.target_distance)
    out = {"surface_mean_mm": float(sd.stats.mean), "landmark_mean_mm": None, "translation_mm": t.tolist()}
    if regions is not None:
        out["regions_mm"] = region_means(regions, sd.a_to_b, sd.a_weights, sd.a_index)
    if pair.has_landmarks and landmarks is not None:
        err = np.linalg.norm(landmarks + t - pair.landmarks_target, axis=1)
        predicted = np.abs(landmarks - pair.landmarks_rest).mean(axis=0)
        observed = np.abs(pair.landmarks_target - t - pair.landmarks_rest).mean(axis=0)
        out["landmark_mean_mm"] = float(err.mean())
        out["landmark_motion_mm"] = {"axes": list(AXES), "predicted": predicted.tolist(), "observed": observed.tolist()}
    return out


def isotropic(pair: LungPair) -> tuple[np.ndarray, np.ndarray | None]:
    """``(vertices, landmarks)``: scaling about the solid's centroid to :attr:`LungPair.volume_ml`."""
    return isotropic_vertices(pair.rest, pair.volume_ml, pair.landmarks_rest)


def modelled(pair: LungPair, lung: LungModel) -> tuple[np.ndarray, np.ndarray | None]:
    """``(vertices, landmarks)`` of ``lung`` (built on ``pair.rest``) at the larger volume, exactly."""
    points = None if not pair.has_landmarks else lung.points_at(pair.landmarks_rest, pair.volume_ml, exact=True)
    return lung.surface_at(pair.volume_ml, exact=True).vertices, points


@dataclass(frozen=True, eq=False)
class Training:
    """What a row may use when it predicts one lung: ``default`` (the population default that scores
    the lung's subject: learned without it when it saw it), ``pairs`` and ``fits`` (``{(subject, side):
    LungPair / FittedLung}``) of the other subjects' lungs (the fits empty when none were made), and
    ``own_fit``, the lung's own two-scan fit, which only the ``fitted`` ceiling may use (None without
    ``with_fitted``)."""

    default: PopulationDefault
    pairs: Mapping = field(default_factory=dict)
    fits: Mapping = field(default_factory=dict)
    own_fit: FittedLung | None = None


#: A row: ``(vertices (n, 3), landmarks (m, 3) or None)`` mm of the lung at its larger volume, in the
#: smaller-volume scan's frame, from the lung and what it may learn from, optionally followed by a dict of
#: figures it was given (recorded in its row of ``metrics.json``); None when the row does not apply.
Predictor = Callable[[LungPair, Training], "tuple | None"]


def default_row(pair: LungPair, training: Training):
    """The population default (:attr:`Training.default`)."""
    return modelled(pair, build_lung(pair.rest, pair.side, default=training.default))


def paper_row(pair: LungPair, training: Training):
    """Table I (Santhanam et al. 2008), the paper's directions."""
    return modelled(pair, build_lung(pair.rest, pair.side, default=paper_default()))


def isotropic_row(pair: LungPair, training: Training):
    """Isotropic scaling to the volume."""
    return isotropic(pair)


def fitted_row(pair: LungPair, training: Training):
    """The lung's own two-scan fit (a ceiling: it saw the larger-volume scan)."""
    return None if training.own_fit is None else modelled(pair, fitted_model(pair, training.own_fit))


#: The rows, in report order (``dome``, ``dome_scaling``: :mod:`lungdeform.validate.dome_rows`).
ROW_PREDICTORS: dict[str, Predictor] = {"default": default_row, "dome": dome_row, "dome_scaling": dome_scaling_row,
                                        "paper": paper_row, "isotropic": isotropic_row, "fitted": fitted_row}
ROWS = tuple(ROW_PREDICTORS)


@dataclass(frozen=True)
class SingleScanConfig:
    """How :func:`run_single_scan` runs: ``default`` (None: the shipped default, leave one subject out
    for the subjects it was learned from; a learned default file: the same for the subjects it was
    learned from; ``"population"`` or ``"paper"``: that default for every lung, as it is),
    ``with_fitted`` (add the ``fitted`` row), ``train`` (folders of further subjects, not scored,
    that a leave-one-subject-out default also learns from when the default was learned from them),
    ``cache``
    (where the fits and the lungs as read are kept: ``fits/``, ``pairs/``; None: the output folder)
    and ``rows`` (further rows, ``(name, predictor)``, scored after :data:`ROW_PREDICTORS`; a row
    that needs the other subjects' fits sets ``needs_fits``)."""

    default: str | Path | None = None
    with_fitted: bool = False
    train: tuple = ()
    cache: Path | None = None
    rows: tuple = ()
    needs_fits: bool = False


def _defaults_for(subjects, base: PopulationDefault, learned_from: set[str], pairs, fits,
                  say) -> dict[str, tuple[PopulationDefault, str]]:
    """Per scored subject: ``(the default that scores it, how it was chosen)``: ``base`` as it is,
    except for a subject in ``learned_from`` (the subjects, of those read, that ``base`` was learned
    from), which gets a default learned anew from ``base``'s other subjects (leave one subject out)."""
    out = {}
    for s in subjects:
        if s.name not in learned_from:
            out[s.name] = (base, "as it is (it did not see this subject)")
            continue
        train = [sample_of(pairs[k], fits[k]) for k in pairs if k[0] != s.name and k[0] in learned_from]
        say(f"{s.name}: learning a default without it ({len(train)} lungs of {base.name!r}'s other subjects)")
        out[s.name] = (learn_default(train, name=f"{base.name} without {s.name}"),
                       f"leave one subject out: learned from {base.name!r}'s other {len(learned_from) - 1} subjects")
    return out


def _learned_from(subjects, base: PopulationDefault, loso: bool) -> set[str]:
    """The names of ``subjects`` that ``base`` was learned from (by the digest of their smaller-volume
    scan, :attr:`PopulationDefault.provenance` ``subject_digests``); none when not ``loso``."""
    if not loso:
        return set()
    digests = set(base.provenance.get("subject_digests", {}).values())
    return {s.name for s in subjects if s.digest in digests}


def read_folders(folders, cache: Path | None, say, what: str = "reading both scans"):
    """``({(subject, side): LungPair}, [Subject], {subject: folder})`` of every lung of every subject in
    ``folders`` (:func:`lungdeform.validate.lung_pair.cached_pair` through ``cache``); a subject name
    twice is refused."""
    pairs, subjects, where = {}, [], {}
    for folder in folders:
        for s in find_subjects(folder):
            if s.name in where:
                raise ReadError(f"{folder}: a second subject named {s.name!r} (the first is in {where[s.name]})")
            subjects.append(s)
            where[s.name] = str(folder)
            splits = SplitCache()  # each mask split once per subject, not once per lung
            for side in lung_sides(s, splits):
                say(f"{s.name} {side}: {what}")
                pair = cached_pair(s, side, cache, lambda m, n=s.name, sd=side: say(f"{n} {sd}: {m}"), splits)
                if pair.cut:
                    say(f"{s.name} {side}: cut by the field of view ({', '.join(pair.cut)}): scored with the cut "
                        "left out of the surface distance")
                pairs[(s.name, side)] = pair
    return pairs, subjects, where


def _check_leave_one_out(scored: set[str], learned_from: set[str]) -> None:
    """ReadError, before any fit, when a scored subject the default saw has fewer than two of the
    default's other subjects to learn from."""
    for name in sorted(scored):
        if len(learned_from - {name}) < 2:
            raise ReadError(f"{name}: the default was learned from this subject; leaving it out needs at least two "
                            "of its other subjects (add folders of them with --train, or give --default population)")


def run_single_scan(data, out: Path, config: SingleScanConfig = SingleScanConfig(), *,
                    progress: Progress | None = None) -> dict:
    """The experiment (module docstring) on every subject in ``data`` (a folder, or a list of folders);
    writes ``out/metrics.json`` and ``out/report.html``; returns the metrics."""
    say = progress or silent
    folders = [data] if isinstance(data, (str, Path)) else list(data)
    cache = Path(out) if config.cache is None else Path(config.cache)
    base = resolve_default(config.default)  # refused before any reading
    loso = config.default is None or config.default not in NAMES  # the shipped default, or a learned file
    pairs, subjects, where = read_folders(folders, cache, say)
    fits, extra, more = {}, {}, []
    if config.with_fitted or loso or config.needs_fits:
        extra, more, _ = read_folders(config.train, cache, say, "reading both scans (training only)")
        if set(where) & {s.name for s in more}:
            raise ReadError(f"subject {min(set(where) & {s.name for s in more})!r} is both scored and in --train")
    scored, learned_from = _learned_from(subjects, base, loso), _learned_from([*subjects, *more], base, loso)
    if config.with_fitted or scored or config.needs_fits:
        _check_leave_one_out(scored, learned_from)
        for key, pair in {**pairs, **extra}.items():
            if config.with_fitted or config.needs_fits or key[0] in learned_from:
                say(f"{key[0]} {key[1]}: two-scan fit (for leave-one-subject-out learning and the fitted row)")
                fits[key] = cached_fit(pair, cache / "fits")
    chosen = _defaults_for(subjects, base, learned_from, {**pairs, **extra}, fits, say)
    predictors = {**{k: v for k, v in ROW_PREDICTORS.items() if k != "fitted" or config.with_fitted},
                  **dict(config.rows)}
    lungs = {}
    for key, pair in pairs.items():
        say(f"{key[0]} {key[1]}: predicting the larger volume from the smaller scan alone")
        others = {k: v for k, v in {**pairs, **extra}.items() if k[0] != key[0]}
        training = Training(chosen[key[0]][0], others, {k: v for k, v in fits.items() if k[0] != key[0]},
                            fits.get(key) if config.with_fitted else None)
        lungs[pair.key] = score_lung(pair, training, predictors)
        lungs[pair.key]["lung_info"] = {"landmarks": pair.has_landmarks, "cut": list(pair.cut),
                                        "folder": Path(where[key[0]]).name}
    result = {"lungs": lungs, "summary": summarise(lungs),
              "defaults": {s.name: {"how": how, **d.record()} for s in subjects for d, how in [chosen[s.name]]},
              "build_seconds": {k: v["default"]["seconds"] for k, v in lungs.items() if "default" in v},
              "region_definition": "docs/DEFAULTS.md (lungdeform.geometry.regions)",
              "protocol": "each prediction moved by the one translation that best fits the real larger-volume "
                          "surface (the same for every row); landmarks moved by it too; a lung cut by the field of "
                          "view is scored with the cut left out of the surface distance"}
    write_json(Path(out) / "metrics.json", result, strict=True)
    write_report(Path(out) / "report.html", result)
    return result


def score_lung(pair: LungPair, training: Training, predictors: Mapping[str, Predictor]) -> dict:
    """One lung's rows (:func:`score` of each predictor that applies; ``seconds``: its prediction's
    time, s) and ``region_shares`` (each region's share of the smaller-volume surface's area)."""
    regions = surface_regions(pair.rest.vertices, pair.rest.faces, pair.side)
    rows: dict = {}
    for name, predict in predictors.items():
        t0 = time.perf_counter()
        got = predict(pair, training)
        seconds = time.perf_counter() - t0
        if got is not None:
            vertices, landmarks, *given = got  # a row may add what it was given (``dome_mm``)
            rows[name] = {**score(pair, vertices, landmarks, regions=regions), **(given[0] if given else {}),
                          "seconds": seconds}
    rows["region_shares"] = region_shares(pair.rest.vertices, pair.rest.faces, regions)
    return rows


def _median(values) -> float | None:
    v = [x for x in values if x is not None]
    return float(np.median(v)) if v else None


def _medians(lungs: dict) -> dict:
    """Per row: the medians of its figures (the landmark figure over the lungs with landmarks)."""
    out: dict = {}
    for row in row_names(lungs):
        got = [v[row] for v in lungs.values() if row in v]
        with_lm = [g for g in got if g.get("landmark_mean_mm") is not None]
        out[row] = {"surface_mean_mm": _median(g["surface_mean_mm"] for g in got),
                    "landmark_mean_mm": _median(g["landmark_mean_mm"] for g in with_lm),
                    "surface_mean_mm_landmark_lungs": _median(g["surface_mean_mm"] for g in with_lm),
                    "n_lungs": len(got), "n_lungs_landmarks": len(with_lm),
                    "regions_mm": {r: _median(g.get("regions_mm", {}).get(r) for g in got) for r in REGIONS}}
    iso = out.get("isotropic")
    for row in out.values():
        for k, name in (("surface_mean_mm", "surface_vs_isotropic"), ("landmark_mean_mm", "landmark_vs_isotropic")):
            ok = iso is not None and row[k] is not None and iso[k]
            row[name] = row[k] / iso[k] if ok else None
    return out


def summarise(lungs: dict) -> dict:
    """``n_lungs`` (every lung scored), ``n_lungs_landmarks``, ``n_lungs_cut``, per row the medians
    (:func:`_medians`) and ``subsets``: the same over the lungs with landmarks, without landmarks, the
    whole (uncut) lungs, and each data folder (``lung_info.folder``)."""
    info = {k: v.get("lung_info", {}) for k, v in lungs.items()}
    out: dict = {"n_lungs": len(lungs), "n_lungs_landmarks": sum(bool(i.get("landmarks", True)) for i in info.values()),
                 "n_lungs_cut": sum(bool(i.get("cut")) for i in info.values()),
                 "cut_lungs": sorted(k for k, i in info.items() if i.get("cut")), **_medians(lungs)}
    groups = {"landmarks": lambda i: i.get("landmarks", True), "no_landmarks": lambda i: not i.get("landmarks", True),
              "uncut": lambda i: not i.get("cut")}
    for folder in sorted({i.get("folder") for i in info.values() if i.get("folder")}):
        groups[f"folder {folder}"] = lambda i, f=folder: i.get("folder") == f
    out["subsets"] = {}
    for name, test in groups.items():
        sub = {k: v for k, v in lungs.items() if test(info[k])}
        if sub and len(sub) < len(lungs):
            out["subsets"][name] = {"n_lungs": len(sub), **_medians(sub)}
    return out


#: Where the shared subjects come from, by data folder name (recorded in a learned default's provenance;
#: NOTICE, docs/DEFAULTS.md).
CITATIONS = {
    "dirlab-copd-lung-masks": "DIR-Lab COPDgene: Castillo R. et al., Phys Med Biol 2013;58:2861 (research use with "
                              "citation); masks and landmarks converted by VoxelMorph++ (MIT)",
    "itk-right-lung-two-volumes": "ITKElastix example data, Apache-2.0",
    "learn2reg-lung-masks": "Learn2Reg 2020 task 2 lung CT (Radboud UMC): Hering A. et al., IEEE TMI 2023;42(3):697, "
                            "doi:10.5281/zenodo.3835682; masks from DeepReg (Apache-2.0)",
}


def learn_from_folders(folders, name: str = "population", *, cache: Path | None = None,
                       progress: Progress | None = None) -> PopulationDefault:
    """A population default learned from every two-volume subject in ``folders``
    (:func:`find_subjects`): each lung fitted on its own (:func:`~lungdeform.validate.fitted_lung.cached_fit`,
    kept in ``cache/fits`` when ``cache`` is given), then pooled
    (:func:`lungdeform.cohort.default.learn_default`). The provenance records the subjects, the
    digest of each one's smaller-volume scan (so that ``validate single-scan`` scores a subject it
    saw leave one subject out) and the data's citations (of the shared data folders, by name)."""
    say = progress or silent
    pairs, subjects, _ = read_folders(folders, cache, say, "reading both scans")
    samples = []
    for key, pair in pairs.items():
        say(f"{key[0]} {key[1]}: two-scan fit")
        samples.append(sample_of(pair, cached_fit(pair, None if cache is None else Path(cache) / "fits")))
    citations = [CITATIONS[Path(f).name] for f in folders if Path(f).name in CITATIONS]
    return learn_default(samples, name=name, provenance={
        "subject_digests": {s.name: s.digest for s in subjects}, "citation": "; ".join(citations),
        "source": f"{name}: learned by lungdeform learn-default"})
