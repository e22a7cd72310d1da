"""The default a lung model breathes with when it was not fitted: Table I, or a population default.

A model built from one scan (``lungdeform build``, ``demo``, ``segment`` → ``build`` → ``warp
--phases``) has no breathing of its own to fit; it takes its constants from a default:

- ``"paper"``: Santhanam et al. (2008) Table I, c1…c9 per side, the paper's directions (15)–(17);
- ``"population"`` (the shipped default, :func:`shipped_default`): learned from real subjects at two
  lung volumes by ``lungdeform learn-default`` (:mod:`lungdeform.cohort.default`): c1…c9 and a smooth
  direction correction (:func:`lungdeform.model.direction.polynomial_basis`), both in the lung frame
  (Sec. IV-B.1: X lateral from the heart, Y anterior, Z apex → base), so one set serves both sides
  (a left lung is the mirror image of a right one in that frame). docs/DEFAULTS.md gives the
  subjects, the leave-one-subject-out scores and when to use which.

Inside the lung a built model's interior is its surface displacement carried inside
(:func:`lungdeform.interior.surface_map.surface_extension`), plus, with a learned default, an affine
interior prior (:mod:`lungdeform.interior.prior`, mm per mL in the lung-normalised frame): the motion of
real interior landmarks that the surface does not show, learned on the training subjects' landmarks.

The direction correction rotates the paper's directions, ``d = normalise(d⁰ + Φ(x̂)·C)``
(:mod:`lungdeform.fit.direction_correction` fits the same form to one patient). It was learned
supine, so it applies to supine models only; another posture takes the paper's directions with the
default's c1…c9 (:meth:`PopulationDefault.correction_for`).

The file is JSON (``schema`` :data:`SCHEMA`): ``name``, ``constants`` (``{"left": [9], "right": [9]}``),
``direction_degree``, ``direction_correction`` (``(K, 3)`` lung-frame rows, or null),
``interior_prior`` (``(4, 3)`` mm per mL, or null), ``provenance``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lungdeform.atomic import read_schema_json, write_json
from lungdeform.constants import TABLE_I, gravity_vector
from lungdeform.errors import InputError, ReadError
from lungdeform.geometry.frame import SIDES, frame_axes

from .direction import MAX_DEGREE, polynomial_basis

SCHEMA = "lungdeform.population_default"
SCHEMA_VERSION = 1
#: The shipped population default (learned on the shared real subjects; docs/DEFAULTS.md).
SHIPPED = Path(__file__).with_name("population_default.json")
#: Names accepted where a default is chosen (``--constants``): a file path is accepted too.
NAMES = ("population", "paper")
#: Posture the direction correction was learned in (gravity, LPS).
LEARNED_POSTURE = "supine"


@dataclass(frozen=True, eq=False)
class PopulationDefault:
    """c1…c9 per side and an optional direction correction in the lung frame.

    Attributes
    ----------
    name : str
        ``"paper"``, ``"population"`` or the name recorded in a learned file.
    constants : dict side → (9,) float
        c1…c9 (c7…c9 scaled so that the largest |c| is 1 for a learned default).
    direction_degree : int
        Degree of the correction's polynomial (0: none).
    direction_correction : (K, 3) float or None
        ``C`` with output components in the lung frame (X, Y, Z), ``K = C(degree + 3, 3)``.
    interior_prior : (4, 3) float or None
        Affine interior prior, mm per mL of volume change, lung-normalised (:mod:`lungdeform.interior.prior`).
    provenance : dict
        What it was learned from, how, and its scores (JSON-safe).
    """

    name: str
    constants: dict
    direction_degree: int = 0
    direction_correction: np.ndarray | None = None
    interior_prior: np.ndarray | None = None
    provenance: dict = field(default_factory=dict)

    def __post_init__(self):
        consts = {}
        for side in SIDES:
            c = np.asarray(self.constants.get(side) if isinstance(self.constants, dict) else None, float)
            if c.shape != (9,) or not np.all(np.isfinite(c)):
                raise InputError(f"default {self.name!r}: constants[{side!r}] must be 9 finite values c1…c9, "
                                 f"got shape {c.shape}")
            consts[side] = c
        object.__setattr__(self, "constants", consts)
        deg = self.direction_degree
        if not (isinstance(deg, (int, np.integer)) and 0 <= int(deg) <= MAX_DEGREE):
            raise InputError(f"default {self.name!r}: direction_degree must be 0…{MAX_DEGREE}, got {deg!r}")
        object.__setattr__(self, "direction_degree", int(deg))
        if self.direction_correction is not None:
            c = np.asarray(self.direction_correction, float)
            k = polynomial_basis(np.zeros((1, 3)), int(deg)).shape[1]
            if c.shape != (k, 3) or not np.all(np.isfinite(c)):
                raise InputError(f"default {self.name!r}: direction_correction must be a finite ({k}, 3) array for "
                                 f"degree {deg}, got shape {c.shape}")
            object.__setattr__(self, "direction_correction", c)
        if self.interior_prior is not None:
            ip = np.asarray(self.interior_prior, float)
            if ip.shape != (4, 3) or not np.all(np.isfinite(ip)):
                raise InputError(f"default {self.name!r}: interior_prior must be a finite (4, 3) array, got shape "
                                 f"{ip.shape}")
            object.__setattr__(self, "interior_prior", ip)

    def constants_for(self, side: str) -> np.ndarray:
        """``c : (9,) float``, c1…c9 of ``side``."""
        if side not in SIDES:
            raise InputError(f"side must be 'left' or 'right', got {side!r}")
        return self.constants[side].copy()

    def correction_for(self, side: str, gravity=LEARNED_POSTURE) -> np.ndarray | None:
        """``C : (K, 3) float`` in LPS for ``side`` (the lung-frame rows mapped with the side's axes),
        or None: no correction, or ``gravity`` is not the posture it was learned in."""
        if self.direction_correction is None:
            return None
        if not np.allclose(gravity_vector(gravity), gravity_vector(LEARNED_POSTURE)):
            return None
        return np.ascontiguousarray(self.direction_correction @ frame_axes(side))

    def prior_for(self, gravity=LEARNED_POSTURE) -> np.ndarray | None:
        """The interior prior ``(4, 3)`` mm per mL, or None: none, or ``gravity`` is not the posture it
        was learned in."""
        if self.interior_prior is None or not np.allclose(gravity_vector(gravity), gravity_vector(LEARNED_POSTURE)):
            return None
        return self.interior_prior.copy()

    @property
    def digest(self) -> str:
        """SHA-256 (16 hex digits) of the numbers: equal digests, equal defaults."""
        h = hashlib.sha256(json.dumps(self.numbers(), sort_keys=True).encode())
        return h.hexdigest()[:16]

    def numbers(self) -> dict:
        """The default's numbers as plain lists (what a model's provenance and the file record)."""
        corr = None if self.direction_correction is None else self.direction_correction.tolist()
        prior = None if self.interior_prior is None else self.interior_prior.tolist()
        return {"constants": {s: self.constants[s].tolist() for s in SIDES},
                "direction_degree": self.direction_degree, "direction_correction": corr, "interior_prior": prior}

    def record(self) -> dict:
        """What a model file's provenance records of the default it was built with."""
        return {"name": self.name, "digest": self.digest, "source": self.provenance.get("source", self.name)}

    def as_dict(self) -> dict:
        return {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "name": self.name, **self.numbers(),
                "provenance": self.provenance}


def paper_default() -> PopulationDefault:
    """Table I (Santhanam et al. 2008), the paper's directions."""
    return PopulationDefault("paper", {s: TABLE_I[s] for s in SIDES},
                             provenance={"source": "Santhanam et al. 2008, Table I"})


def save_default(path, default: PopulationDefault) -> Path:
    """Write ``default`` as JSON to ``path``, atomically."""
    return write_json(Path(path), default.as_dict(), strict=True)


def read_default(path) -> PopulationDefault:
    """A default written by :func:`save_default`; :class:`ReadError` naming the file otherwise."""
    p = Path(path)
    data = read_schema_json(p, SCHEMA, SCHEMA_VERSION, "population default")
    try:
        corr, prior = data.get("direction_correction"), data.get("interior_prior")
        return PopulationDefault(str(data["name"]), dict(data["constants"]), int(data.get("direction_degree", 0)),
                                 None if corr is None else np.asarray(corr, float),
                                 None if prior is None else np.asarray(prior, float), dict(data.get("provenance", {})))
    except (KeyError, TypeError, ValueError, InputError) as exc:
        raise ReadError(f"{p}: malformed population default ({exc})") from exc


def shipped_default() -> PopulationDefault:
    """The population default shipped with the package (:data:`SHIPPED`)."""
    return read_default(SHIPPED)


def resolve_default(choice=None) -> PopulationDefault:
    """A :class:`PopulationDefault` from ``choice``: None or ``"population"`` (the shipped one),
    ``"paper"`` (Table I), a path to a default file, or a :class:`PopulationDefault` (as it is)."""
    if isinstance(choice, PopulationDefault):
        return choice
    if choice is None or choice == "population":
        return shipped_default()
    if choice == "paper":
        return paper_default()
    p = Path(choice)
    if not p.is_file():
        raise InputError(f"constants must be one of {', '.join(NAMES)} or a population default file, got {choice!r}")
    return read_default(p)
