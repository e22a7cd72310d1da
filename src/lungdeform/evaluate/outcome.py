"""What one run of the fit pipeline gave, typed (:func:`lungdeform.evaluate.pipeline.run_fit`).

Each step's result is a frozen dataclass built once: :class:`Fits` (the fits of c1…c9 run),
:class:`Scores` (every method measured on every target), :class:`AlignmentChoice` and, gathering
them with the inputs read and the held-out landmark step, :class:`FitRun`. ``metrics.json`` is
built once from a :class:`FitRun` (:func:`lungdeform.evaluate.pipeline.fit_metrics`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from lungdeform.fit.config import FitConfig, FitInputs
    from lungdeform.fit.fitting import FitOutcome
    from lungdeform.interior.motion_prior import MotionPrior

    from .heldout import HeldOut
    from .inputs import ReadInputs
    from .placement import Placement


@dataclass(frozen=True, eq=False)
class Fits:
    """The fits of c1…c9 in one run (:func:`lungdeform.fit.fitting.fit_lung` each).

    Attributes
    ----------
    optimizer : FitOutcome
        The headline surface fit (``config.mode``), after the surface refinement.
    grid : FitOutcome or None
        The paper's grid search (with ``config.grid``).
    landmarks : FitOutcome or None
        The landmark-informed fit on all landmarks (with ``landmark_comparisons``).
    """

    optimizer: FitOutcome
    grid: FitOutcome | None = None
    landmarks: FitOutcome | None = None

    def named(self) -> dict[str, FitOutcome]:
        """The fits run, by name (``"optimizer"``, ``"grid"``, ``"landmarks"``, in that order):
        the keys of ``metrics["fit"]``."""
        named = {"optimizer": self.optimizer, "grid": self.grid, "landmarks": self.landmarks}
        return {name: fit for name, fit in named.items() if fit is not None}


@dataclass(frozen=True, eq=False)
class Scores:
    """Every method measured on every target (:func:`lungdeform.evaluate.scoring.score_targets`).

    Attributes
    ----------
    per_target : dict[str, dict[str, dict]]
        Target name → method name → metrics dict (``metrics["targets"]``).
    predictions : dict[(str, str), tuple]
        (target name, method name) → (vertices (n, 3) mm, per-vertex error (n,) mm, landmark
        errors (m,) mm or None): what the report draws.
    skipped : dict[str, str]
        Baselines not computed, name → reason.
    baseline_seconds : float
        Seconds spent on the baselines and landmark-informed references: computing their
        predictions and measuring them (surface distances, landmark errors).
    baseline_cpu_seconds : float
        The same, CPU seconds of the process (every thread; robust to the machine's load).
    """

    per_target: dict
    predictions: dict
    skipped: dict
    baseline_seconds: float
    baseline_cpu_seconds: float = 0.0


@dataclass(frozen=True)
class AlignmentChoice:
    """The alignment asked (``config.align``), the one used (``"auto"`` resolved by
    :func:`lungdeform.fit.cycle.choose_alignment`) and why."""

    asked: str
    used: str
    why: str

    def as_dict(self) -> dict:
        return {"asked": self.asked, "used": self.used, "why": self.why}


@dataclass(frozen=True, eq=False)
class FitRun:
    """What one run of :func:`lungdeform.evaluate.pipeline.run_fit` gave, before it is written.

    Attributes
    ----------
    inputs : FitInputs
        What the run was given.
    config : FitConfig
        The configuration as run (``align`` resolved, :attr:`alignment`).
    read : ReadInputs
        The inputs read and checked (:func:`lungdeform.evaluate.inputs.read_inputs`).
    placed : Placement
        The model mesh and the targets in its frame (after a joint alignment, moved by it).
    fits : Fits
        The fits of c1…c9.
    held : HeldOut
        What landmarks give, held out (:func:`lungdeform.evaluate.heldout.held_out_landmarks`).
    scores : Scores
        Every method measured on every target.
    alignment : AlignmentChoice
        The alignment asked, used and why.
    warnings : tuple[str, ...]
        Every warning of the run: reading, placing, fitting.
    seconds : float
        The run's time up to writing its files (s).
    surface_field : SurfaceMapField or None
        The surface-map interior field (None: the sliding field).
    prior : MotionPrior or None
        The population motion prior added to ``surface_field``, tapered to zero at the surface.
    """

    inputs: FitInputs
    config: FitConfig
    read: ReadInputs
    placed: Placement
    fits: Fits
    held: HeldOut
    scores: Scores
    alignment: AlignmentChoice
    warnings: tuple
    seconds: float
    surface_field: object = None
    prior: MotionPrior | None = None

    @property
    def landmarks(self):
        """The end-exhale landmarks ``(m, 3)`` mm, or None."""
        return self.read.landmarks[0] if self.read.landmarks is not None else None

    @property
    def model_seconds(self) -> float:
        """:attr:`seconds` less the baselines' and landmark-informed references' (s): the model's own."""
        return self.seconds - self.scores.baseline_seconds
