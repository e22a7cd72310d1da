"""Learning a population default from two-volume subjects (``lungdeform learn-default``; docs/DEFAULTS.md).

Each training lung is first fitted on its own (:func:`lungdeform.fit.fitting.fit_lung`: c1…c9, a
translation, the direction correction; uniform stiffness), giving a :class:`DefaultSample`. What
generalises across lungs is then pooled in the lung frame of Sec. IV-B.1, where a left lung is the
mirror image of a right one (:mod:`lungdeform.model.population`):

1. c1…c9: the median over the training lungs of each constant (c7…c9 first scaled so that the
   largest |c| is 1, as the fit reports them);
2. optionally (``degree > 0``) the direction correction ``C (K, 3)`` (lung frame): with the pooled
   c1…c6 giving the paper's directions ``d⁰`` on each training lung, the weighted least-squares fit
   of ``Φ(x̂)·C ≈ d − d⁰`` over every training vertex, ``d`` that lung's fitted directions, each
   vertex weighted by its share of the lung's motion (``|F|·area``, normalised per lung, so every
   lung counts once), with a ridge of :data:`RIDGE` × the mean diagonal. Scored leave one subject
   out it did not generalise (docs/DEFAULTS.md), so :data:`DEGREE` is 0;
3. the interior prior (:mod:`lungdeform.interior.prior`), mm per mL, from the training lungs with
   landmarks (none without any): each such lung built with
   1.–2. (:func:`lungdeform.model.lung.build_lung`) and its landmarks moved to the larger volume; the
   residuals (observed, in the frame of that lung's own two-scan fit, minus predicted), in mm, fitted
   by ``ΔV·w(q)·(β₀ + B q̂)``, ``w`` the taper a built lung plays the prior with (zero at the surface:
   :class:`lungdeform.interior.prior.TaperedPrior`), in weighted least squares (every lung weighted once, whatever its landmark
   count; ``ΔV`` its volume change, mL), with a ridge on ``B`` of :data:`PRIOR_RIDGE` × the mean
   diagonal. Fitting in mm, not in mm per mL, keeps a lung with a small volume change from
   dominating the fit with its noise (scored leave one subject out: docs/DEFAULTS.md).

Every choice here was scored leave one subject out (``lungdeform validate single-scan``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from lungdeform.errors import InputError
from lungdeform.geometry.distance import vertex_areas
from lungdeform.geometry.frame import frame_axes, lung_frame
from lungdeform.geometry.mesh import Surface
from lungdeform.interior.prior import lung_normaliser, mirror, normalised, taper_weights
from lungdeform.model.direction import directions as paper_directions
from lungdeform.model.direction import polynomial_basis
from lungdeform.model.lung import BuildSettings, build_lung
from lungdeform.model.population import PopulationDefault

#: Degree of the learned direction correction (0: none; docs/DEFAULTS.md).
DEGREE = 0
#: Ridge of the pooled correction, relative to the mean diagonal of its normal matrix.
RIDGE = 1e-3
#: Ridge of the interior prior's linear part, relative to the mean diagonal (docs/DEFAULTS.md).
PRIOR_RIDGE = 0.01


@dataclass(frozen=True, eq=False)
class DefaultSample:
    """One training lung's own fit.

    Attributes
    ----------
    subject : str
    side : 'left' | 'right'
    surface : Surface
        End-exhale model mesh, mm LPS.
    constants : (9,) float
        Its fitted c1…c9.
    directions : (n, 3) float
        Its fitted unit directions (direction correction included), LPS.
    force : (n,) float
        Its fitted elastostatic force ``F`` (relative units), for the weights.
    landmarks : (m, 3) float or None
        End-exhale landmarks, mm LPS (None: a lung without landmarks, which the interior prior does not see).
    landmarks_target : (m, 3) float or None
        The same landmarks at the larger volume, mm, moved into the end-exhale frame by the fit's translation.
    delta_ml : float
        The volume change between the two scans, mL.
    """

    subject: str
    side: str
    surface: Surface
    constants: np.ndarray
    directions: np.ndarray
    force: np.ndarray
    landmarks: np.ndarray | None
    landmarks_target: np.ndarray | None
    delta_ml: float

    @property
    def has_landmarks(self) -> bool:
        return self.landmarks is not None and len(self.landmarks) > 0


def pooled_constants(samples: Sequence[DefaultSample]) -> np.ndarray:
    """``(9,) float``: the median of each constant over ``samples`` (c7…c9 scaled to max |c| = 1)."""
    rows = []
    for smp in samples:
        c = np.asarray(smp.constants, float).copy()
        top = np.max(np.abs(c[6:]))
        if not top > 0:
            raise InputError(f"{smp.subject} {smp.side}: c7…c9 are all zero")
        c[6:] /= top
        rows.append(c)
    return np.median(np.asarray(rows), axis=0)


def pooled_correction(samples: Sequence[DefaultSample], constants, degree: int = DEGREE,
                      ridge: float = RIDGE) -> np.ndarray:
    """``C : (K, 3) float`` in the lung frame (module docstring, step 2)."""
    k = polynomial_basis(np.zeros((1, 3)), degree).shape[1]
    normal, rhs = np.zeros((k, k)), np.zeros((k, 3))
    for smp in samples:
        p = smp.surface.vertices
        frame = lung_frame(p, smp.side)
        axes = frame_axes(smp.side)
        phi = polynomial_basis(frame.normalized(p), degree)
        d0 = paper_directions(frame, p, constants) @ axes.T  # lung frame
        d = np.asarray(smp.directions, float) @ axes.T
        w = np.abs(np.asarray(smp.force, float)) * vertex_areas(p, smp.surface.faces)
        w = w / max(float(w.sum()), 1e-300)
        normal += (phi * w[:, None]).T @ phi
        rhs += (phi * w[:, None]).T @ (d - d0)
    lam = ridge * np.trace(normal) / k
    return np.linalg.solve(normal + lam * np.eye(k), rhs)


def learn_default(samples: Sequence[DefaultSample], name: str = "population", provenance: dict | None = None,
                  degree: int = DEGREE) -> PopulationDefault:
    """A :class:`~lungdeform.model.population.PopulationDefault` from the training lungs ``samples``."""
    samples = list(samples)
    if len(samples) < 2:
        raise InputError(f"a population default needs at least 2 training lungs, got {len(samples)}")
    c = pooled_constants(samples)
    corr = pooled_correction(samples, c, degree) if degree > 0 else None
    partial = PopulationDefault(name, {"left": c, "right": c}, degree if corr is not None else 0, corr)
    prior = pooled_prior(samples, partial) if any(s.has_landmarks for s in samples) else None
    prov = {"lungs": [f"{s.subject}/{s.side}" for s in samples],
            "subjects": sorted({s.subject for s in samples}), "method": "lungdeform.cohort.default", **(provenance or {})}
    return replace(partial, interior_prior=prior, provenance=prov)


def pooled_prior(samples: Sequence[DefaultSample], default: PopulationDefault,
                 ridge: float = PRIOR_RIDGE) -> np.ndarray:
    """``(4, 3)`` mm per mL: the interior prior of ``default`` (module docstring, step 3), from the
    samples with landmarks."""
    xs, ys, ws = [], [], []
    for smp in (s for s in samples if s.has_landmarks):
        lung = build_lung(smp.surface, smp.side, default=default, settings=BuildSettings(smp.delta_ml))
        moved = lung.points_at(smp.landmarks, lung.volume_ee_ml + smp.delta_ml, exact=True)
        q = normalised(smp.landmarks, *lung_normaliser(smp.surface), smp.side)
        fade = taper_weights(smp.landmarks, smp.surface)[:, None]  # as a built lung plays the prior
        xs.append(smp.delta_ml * fade * np.c_[np.ones(len(q)), q])  # the prior per mL, times this lung's change
        ys.append((np.asarray(smp.landmarks_target, float) - moved) * mirror(smp.side))
        ws.append(np.full(len(q), 1.0 / len(q)))  # every lung counts once
    x, y, w = np.vstack(xs), np.vstack(ys), np.concatenate(ws)
    normal = (x * w[:, None]).T @ x
    reg = ridge * np.trace(normal) / 4.0 * np.diag([0.0, 1.0, 1.0, 1.0])
    return np.linalg.solve(normal + reg, (x * w[:, None]).T @ y)
