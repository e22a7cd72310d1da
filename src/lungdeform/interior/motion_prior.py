"""A population prior of interior motion: what other subjects' landmarks say the surfaces miss.

From the surfaces alone a new patient's interior motion is the correspondence field
(:mod:`lungdeform.interior.surface_map`). On the DIR-Lab COPDgene masks its landmark residuals are
mostly affine and shared across subjects (the predictions sit 2–8 mm too far posterior; docs/FITTING.md,
"Interior from the surfaces alone"). The prior is that shared part: a least-squares affine map of
residual displacement (mm, at each training subject's largest volume) over the lung-normalised
position ``q̂ = (q − μ) / σ`` (``μ`` the solid's centroid, ``σ (3,)`` the standard deviations of its
solid along x, y, z; the x axis mirrored for a left lung, so lateral means the same on both sides),

    r(q) = β₀ + B q̂,        β = argmin Σ_lungs (1/m_l) Σ_j |r_j − β₀ − B q̂_j|² + λ |B|²,

each training lung weighted equally whatever its landmark count. Applied to a new lung it is an
affine displacement in world mm (:meth:`MotionPrior.affine`), so it folds into the correspondence
field's affine part and playback costs nothing more. Scored only leave-one-subject-out
(``lungdeform validate copd``): a prior never scores the subject it was learned from.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lungdeform.atomic import read_schema_json, write_json
from lungdeform.errors import InputError, ReadError
from lungdeform.geometry.mesh import as_vertices
from lungdeform.interior.prior import lung_normaliser, mirror, normalised, prior_affine, prior_displacement

SCHEMA = "lungdeform.motion_prior"
SCHEMA_VERSION = 1
#: Ridge weight ``λ`` on the linear part (chosen leave-one-subject-out on the shared cases).
RIDGE = 1.0
__all__ = ["MotionPrior", "PriorSample", "learn_motion_prior", "load_prior", "lung_normaliser", "save_prior"]


@dataclass(frozen=True)
class PriorSample:
    """One training lung: ``points (m, 3)`` mm (end-exhale landmarks), ``residual (m, 3)`` mm (observed
    position at the largest volume minus the correspondence field's), its ``side``, ``centroid (3,)``
    and ``scale (3,)`` mm (:func:`lung_normaliser`) and the ``subject`` it belongs to."""

    subject: str
    side: str
    centroid: np.ndarray
    scale: np.ndarray
    points: np.ndarray
    residual: np.ndarray


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

    def as_dict(self) -> dict:
        return {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "coefficients_mm": self.coefficients.tolist(),
                "subjects": list(self.subjects), "ridge": self.ridge,
                "frame": "lung-normalised position (x mirrored for a left lung) -> residual displacement, mm"}


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
        if len(r) != len(q) or len(q) == 0:
            raise InputError(f"{smp.subject} {smp.side}: need one residual per point ({len(q)}), got {len(r)}")
        xs.append(np.c_[np.ones(len(q)), q])
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
    data = read_schema_json(p, SCHEMA, SCHEMA_VERSION, "motion prior")
    try:
        return MotionPrior(np.asarray(data["coefficients_mm"], float), tuple(data.get("subjects", ())),
                           float(data.get("ridge", RIDGE)))
    except (KeyError, TypeError, ValueError, InputError) as exc:
        raise ReadError(f"{p}: malformed motion prior ({exc})") from exc
