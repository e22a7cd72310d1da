"""A lung's two-scan fit, as ``validate single-scan`` and ``learn-default`` keep it (:class:`FittedLung`).

The fit (:func:`fit_pair`: :func:`lungdeform.fit.fitting.fit_lung` with c1…c9, a translation and the
direction correction, uniform stiffness) is the expensive step of both commands: a few minutes a lung.
:func:`cached_fit` keeps it in a folder (``--fits DIR``), under a digest of exactly what the fit is given
(the model mesh, the target surface, which vertices of each are measured, the volume, the side and the
fit's settings: :func:`fit_digest`), so that any later run, of either command, on any machine, reads it
back instead of fitting again, and a changed input or setting is fitted anew.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_bytes
from lungdeform.cohort.default import DefaultSample
from lungdeform.fit.fitting import FitSettings, fit_lung, to_lung_model
from lungdeform.model.lung import LungModel

from .lung_pair import LungPair

#: The two-scan fit of a training (and ``fitted``) lung: optimiser budget.
FIT_EVALUATIONS = 300
#: Bumped whenever :func:`fit_pair` fits differently (a cached fit of another version is fitted again).
FIT_VERSION = 1


@dataclass(frozen=True, eq=False)
class FittedLung:
    """What is kept of a lung's two-scan fit (:func:`fit_pair`): ``constants (9,)``,
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


def fit_digest(pair: LungPair) -> str:
    """SHA-256 (16 hex digits) of what :func:`fit_pair` is given, and of its settings."""
    h = hashlib.sha256(f"{pair.side}/{FIT_EVALUATIONS}/{FIT_VERSION}/{pair.volume_ml!r}/{pair.target.volume_ml!r}".encode())
    tk = pair.target.keep
    for a in (pair.rest.vertices, pair.rest.faces, pair.keep, pair.target.surface.vertices, pair.target.surface.faces,
              np.ones(pair.target.surface.n_vertices, bool) if tk is None else tk):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def cached_fit(pair: LungPair, folder: Path | None) -> FittedLung:
    """:func:`fit_pair`, kept in ``folder/<subject>_<side>_<digest>.npz`` (:func:`fit_digest`) and read
    back from there when present (a rerun resumes; None: no cache)."""
    if folder is None:
        return fit_pair(pair)
    path = Path(folder) / f"{pair.subject}_{pair.side}_{fit_digest(pair)}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                return FittedLung(*(z[k] for k in ("constants", "stiffness", "directions", "displacement", "force",
                                                     "translation")), float(z["unit_ml"]), float(z["calibration_ml"]))
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is fitted again
    fit = fit_pair(pair)
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(getattr(fit, k)) for k in FittedLung.__dataclass_fields__})
    write_bytes(path, buf.getvalue())
    return fit


def fitted_model(pair: LungPair, fit: FittedLung) -> LungModel:
    """The two-scan fit as a :class:`LungModel` on ``pair.rest`` (the ``fitted`` row)."""
    return to_lung_model(pair.rest, pair.side, fit)


def sample_of(pair: LungPair, fit: FittedLung) -> DefaultSample:
    """What :func:`lungdeform.cohort.default.learn_default` takes from one fitted lung (landmarks, when
    the lung has them, moved into the smaller-volume frame by the fit's translation)."""
    target = None if pair.landmarks_target is None else pair.landmarks_target + fit.translation
    return DefaultSample(pair.subject, pair.side, pair.rest, fit.constants, fit.directions, fit.force,
                         pair.landmarks_rest, target, pair.volume_ml - pair.rest.volume_ml)
