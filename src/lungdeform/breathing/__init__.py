"""Breathing over time: the pressure–volume model (Sec. III-A/B), measured traces and their cycles.

Owns: :mod:`~lungdeform.breathing.pv` (the single-compartment PV model and its simulation),
:mod:`~lungdeform.breathing.inversion` (its fit to a measured trace), :mod:`~lungdeform.breathing.presets`
(named breathing patterns with their sources), :mod:`~lungdeform.breathing.trace` (trace readers),
:mod:`~lungdeform.breathing.cycles` (cycle detection), :mod:`~lungdeform.breathing.holdout` (held-out
scoring), :mod:`~lungdeform.breathing.stream` (causal streaming), :mod:`~lungdeform.breathing.predict`
(causal prediction), :mod:`~lungdeform.breathing.predict_interval` (its online conformal intervals),
:mod:`~lungdeform.breathing.gating` (the gating window and the beam decision),
:mod:`~lungdeform.breathing.curve_models` (Lujan and Fourier curves to compare against) and
:mod:`~lungdeform.breathing.run` (a preset run or a trace fit with its curve, metrics and plots).

May import: the core modules only (errors, atomic, constants, and :mod:`lungdeform.plot` for figures).
Volumes are mL, time s, pressures cmH2O; nothing here knows a mesh.
"""

from .pv import (
    N_CONTROL,
    N_PHASE,
    BreathingCurve,
    BreathingParams,
    Mechanics,
    basis,
    interp_periodic,
    muscle_pressure,
    periodic_response,
    scale_from_volume,
    scaled_to_tidal_volume,
    simulate,
    simulate_pressure,
    transfer,
)

__all__ = [
    "BreathingCurve",
    "BreathingParams",
    "Mechanics",
    "N_CONTROL",
    "N_PHASE",
    "basis",
    "interp_periodic",
    "muscle_pressure",
    "periodic_response",
    "scale_from_volume",
    "scaled_to_tidal_volume",
    "simulate",
    "simulate_pressure",
    "transfer",
]
