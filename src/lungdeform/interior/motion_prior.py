"""A population prior of interior motion: what other subjects' landmarks say the surfaces miss.

From the surfaces alone a new patient's interior motion is the correspondence field
(:mod:`lungdeform.interior.surface_map`). On the DIR-Lab COPDgene masks its landmark residuals are
mostly affine and shared across subjects (the predictions sit 2–8 mm too far posterior; docs/FITTING.md,
"Interior from the surfaces alone"). The prior is that shared part: a least-squares affine map of
residual displacement (mm, at each training subject's largest volume) over the lung-normalised
position ``q̂ = (q − μ) / σ`` (``μ`` the solid's centroid, ``σ (3,)`` the standard deviations of its
solid along x, y, z; the x axis mirrored for a left lung, so lateral means the same on both sides),
tapered to zero at the lung's surface as it is played (:class:`lungdeform.interior.prior.TaperedPrior`),

    r(q) = w(δ(q)) (β₀ + B q̂),   β = argmin Σ_lungs (1/m_l) Σ_j |r_j − w_j (β₀ + B q̂_j)|² + λ |B|²,

``w_j`` the taper at landmark ``j``'s depth below the lung's end-exhale surface (:func:`taper_at`,
reaching 1 at :data:`TAPER_MM` deep), each training lung weighted equally whatever its landmark count. Applied to a new lung it is a tapered affine displacement in world mm
(:meth:`MotionPrior.tapered`): zero on the surface, so the fitted lung keeps the correspondence
field's surface, shape and volume change (an untapered affine moved the surface off its target;
schema version 1 priors were learned untapered and are refused). Scored only leave-one-subject-out
(``lungdeform validate copd``): a prior never scores the subject it was learned from.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lungdeform.atomic import read_schema_json, write_json
from lungdeform.errors import InputError, ReadError
from lungdeform.geometry.mesh import Surface, as_vertices
from lungdeform.interior.prior import (TaperedPrior, lung_normaliser, mirror, normalised, prior_affine,
                                       prior_displacement, taper_weights)

SCHEMA = "lungdeform.motion_prior"
#: 2: learned and played tapered to zero at the surface (module docstring); 1 (untapered) is refused.
SCHEMA_VERSION = 2
#: Depth (mm) at which the prior reaches its full value. On the DIR-Lab COPDgene lungs the prior is
#: 8 mm (median; 17–19 mm at most) at the surface at full inspiration, and the taper's slope (up to
#: 1.5 / width) turns it into a compression there: at 10 or 20 mm the field's Jacobian could fold
#: (its bound 1 − 1.5 (r·n) / width reaches −1.4 and −0.2); at 30 mm it stays ≥ 0.2 on every lung
#: (leave-one-subject-out landmark medians 6.79 / 7.06 / 7.37 mm; docs/FITTING.md: chosen on the
#: scored lungs).
TAPER_MM = 30.0
#: Ridge weight ``λ`` on the linear part (chosen leave-one-subject-out on the shared cases).
RIDGE = 1.0
__all__ = ["MotionPrior", "PriorSample", "learn_motion_prior", "load_prior", "lung_normaliser", "save_prior", "taper_at"]


@dataclass(frozen=True)
class PriorSample:
    """One training lung: ``points (m, 3)`` mm (end-exhale landmarks), ``residual (m, 3)`` mm (observed
    position at the largest volume minus the correspondence field's), ``taper (m,)`` the prior's weight
    at each point's depth (:func:`taper_at` the end-exhale surface),
    its ``side``, ``centroid (3,)`` and ``scale (3,)`` mm (:func:`lung_normaliser`) and the ``subject``
    it belongs to."""

    subject: str
    side: str
    centroid: np.ndarray
    scale: np.ndarray
    points: np.ndarray
    residual: np.ndarray
    taper: np.ndarray


@dataclass(frozen=True, eq=False)
class MotionPrior:
    """The learned prior (module docstring): ``coefficients (4, 3)`` mm (rows β₀, then B's rows for
    x̂, ŷ, ẑ; mirrored frame), the ``subjects`` it was learned from and its ``ridge``."""

    coefficients: np.ndarray
    subjects: tuple[str, ...]
    ridge: float = RIDGE

    def __post_init__(self):
        c = np.asarray(self.coefficients, float)
        if c.shape != (4, 3) or not np.all(np.isfinite(c)):
            raise InputError(f"coefficients must be a finite (4, 3) array, got shape {c.shape}")
        object.__setattr__(self, "coefficients", c)
        object.__setattr__(self, "subjects", tuple(str(s) for s in self.subjects))

    def displacement(self, points, centroid, scale, side: str) -> np.ndarray:
        """``(m, 3)`` mm: the prior's residual displacement at ``points : (m, 3)`` mm of a lung."""
        return prior_displacement(self.coefficients, points, centroid, scale, side)

    def affine(self, centroid, scale, side: str) -> np.ndarray:
        """``(3, 4)``: the same displacement as ``[M | b]`` in world mm, ``M q + b``."""
        return prior_affine(self.coefficients, centroid, scale, side)

    def tapered(self, surface: Surface, side: str, per_unit: float = 1.0) -> TaperedPrior:
        """The prior on the lung of end-exhale ``surface`` (mm LPS) as it is played: tapered to zero at
        that surface (:class:`~lungdeform.interior.prior.TaperedPrior`), mm times ``per_unit``."""
        affine = self.affine(*lung_normaliser(surface), side) * float(per_unit)
        return TaperedPrior(affine, surface.vertices, surface.faces, TAPER_MM)

    def as_dict(self) -> dict:
        return {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "coefficients_mm": self.coefficients.tolist(),
                "subjects": list(self.subjects), "ridge": self.ridge,
                "frame": "lung-normalised position (x mirrored for a left lung) -> residual displacement, mm"}


def taper_at(points, surface: Surface) -> np.ndarray:
    """``w : (m,) float``: the prior's taper at ``points : (m, 3)`` mm LPS inside the lung of end-exhale
    ``surface``, as :meth:`MotionPrior.tapered` plays it (what a :class:`PriorSample` learns with)."""
    return taper_weights(points, surface, TAPER_MM)


def learn_motion_prior(samples, ridge: float = RIDGE) -> MotionPrior:
    """:class:`MotionPrior` from ``samples`` (:class:`PriorSample`, one per training lung)."""
    samples = list(samples)
    if len(samples) < 2:
        raise InputError(f"a motion prior needs at least 2 training lungs, got {len(samples)}")
    if not (np.isfinite(ridge) and ridge >= 0):
        raise InputError(f"ridge must be >= 0, got {ridge!r}")
    xs, ys, ws = [], [], []
    for smp in samples:
        q = normalised(smp.points, smp.centroid, smp.scale, smp.side)
        r = as_vertices(smp.residual, "residual")
        t = np.asarray(smp.taper, float).reshape(-1)
        if len(r) != len(q) or len(t) != len(q) or len(q) == 0:
            raise InputError(f"{smp.subject} {smp.side}: need one residual and one taper weight per point ({len(q)}), "
                             f"got {len(r)} and {len(t)}")
        if not np.all((t >= 0) & (t <= 1)):
            raise InputError(f"{smp.subject} {smp.side}: taper weights must lie in [0, 1]")
        xs.append(np.c_[np.ones(len(q)), q] * t[:, None])  # the prior as it is played: w (β₀ + B q̂)
        ys.append(r * mirror(smp.side))
        ws.append(np.full(len(q), 1.0 / len(q)))
    x, y, w = np.vstack(xs), np.vstack(ys), np.concatenate(ws)
    reg = float(ridge) * np.diag([0.0, 1.0, 1.0, 1.0]) * w.sum() / len(samples)
    beta = np.linalg.solve((x * w[:, None]).T @ x + reg, (x * w[:, None]).T @ y)
    return MotionPrior(beta, tuple(sorted({s.subject for s in samples})), float(ridge))


def save_prior(path, prior: MotionPrior) -> Path:
    """Write ``prior`` as JSON to ``path``, atomically."""
    return write_json(Path(path), prior.as_dict(), strict=True)


def load_prior(path) -> MotionPrior:
    """Read a prior written by :func:`save_prior`; :class:`ReadError` naming the file otherwise."""
    p = Path(path)
    try:
        data = read_schema_json(p, SCHEMA, SCHEMA_VERSION, "motion prior")
    except ReadError as exc:  # an older prior is named as such (read again only then)
        if _version(p) != 1:
            raise
        raise ReadError(f"{p}: a motion prior of schema version 1, learned without the surface taper that "
                        f"version {SCHEMA_VERSION} plays; learn it again (lungdeform validate copd writes "
                        f"motion_prior.json)") from exc
    try:
        return MotionPrior(np.asarray(data["coefficients_mm"], float), tuple(data.get("subjects", ())),
                           float(data.get("ridge", RIDGE)))
    except (KeyError, TypeError, ValueError, InputError) as exc:
        raise ReadError(f"{p}: malformed motion prior ({exc})") from exc


def _version(path: Path):
    """The ``schema_version`` of a motion prior file, or None when it cannot be read as one."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return data.get("schema_version") if isinstance(data, dict) and data.get("schema") == SCHEMA else None
