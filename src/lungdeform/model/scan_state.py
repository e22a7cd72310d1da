"""Where in the breath the scan a model was built from lies (docs/RADIOTHERAPY.md, "The scan's breathing state").

A model's rest surface is the scan it was built from, whatever the breathing state of that scan. A
planning CT may be an end-exhale scan, an end-inhale one (POPI's phase 00, a DIR-Lab T00), a
mid-ventilation or time-averaged CT. :class:`ScanState` records where it lies: ``above_ee_ml``, mL of
both lungs above the breath's end-exhale (0 for an end-exhale scan; the tidal volume for an
end-inhale one). Every breathing state lungdeform plays is a volume ``ΔV`` of both lungs above
end-exhale (a curve, a preset, a phase; ``--volume-ml`` less the end-exhale volume); each lung moves
from the scan by its share of ``ΔV − above_ee_ml`` (:func:`lungdeform.playback.trajectory.lung_scales`),
so it breathes out below the scan as well as in above it. A model that records no state (files
before schema 5, a fit, whose rest is its smallest scan) is an end-exhale scan: ``above_ee_ml = 0``.

The anchor is end-exhale (the functional residual capacity, the most reproducible point of quiet
breathing): an end-inhale scan of a 500 mL breath lies 500 mL above end-exhale, and a deeper breath
(a 700 mL curve) passes 200 mL beyond it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from lungdeform.errors import InputError

#: How a scan's state can be said, by name, and the fraction of the tidal volume each means.
NAMED_FRACTIONS = {"end-exhale": 0.0, "mid": 0.5, "end-inhale": 1.0}
#: Every value of :attr:`ScanState.name`: a named state, a fraction of the tidal volume, or a volume.
KINDS = (*NAMED_FRACTIONS, "fraction", "volume")
#: The largest volume above end-exhale a scan may be said to lie at, mL (beyond any vital capacity).
MAX_ABOVE_ML = 10000.0
#: Help of ``build --scan-state``.
HELP = ("The scan's breathing state: end-exhale (default), end-inhale, mid (mid-ventilation, half the tidal volume), "
        "a FRACTION of the tidal volume (0 = end-exhale, 1 = end-inhale), or its volume above end-exhale in mL of "
        "both lungs (e.g. 300mL; a breath-hold scan may lie beyond the tidal volume). The model breathes both "
        "ways from it (docs/RADIOTHERAPY.md, \"The scan's breathing state\").")


@dataclass(frozen=True)
class ScanState:
    """The scan's place in the breath: ``above_ee_ml`` mL of both lungs above end-exhale (>= 0), and
    ``name`` how it was said (:data:`KINDS`: ``end-exhale``, ``end-inhale``, ``mid``, ``fraction``,
    ``volume``)."""

    name: str = "end-exhale"
    above_ee_ml: float = 0.0

    def __post_init__(self):
        if self.name not in KINDS:
            raise InputError(f"scan state must be one of {', '.join(KINDS)}, got {self.name!r}")
        v = float(self.above_ee_ml)
        if not (math.isfinite(v) and 0.0 <= v <= MAX_ABOVE_ML):
            raise InputError(f"the scan's volume above end-exhale must be 0 to {MAX_ABOVE_ML:g} mL, got {v!r}")
        if self.name == "end-exhale" and v != 0.0:
            raise InputError(f"an end-exhale scan lies 0 mL above end-exhale, got {v:g} mL")

    @property
    def is_end_exhale(self) -> bool:
        return self.above_ee_ml == 0.0

    def describe(self) -> str:
        """The state in words: ``end-exhale``, ``end-inhale, 500 mL above end-exhale``, ``150 mL above end-exhale`` …"""
        if self.is_end_exhale:
            return "end-exhale"
        if self.name in ("fraction", "volume"):
            return f"{self.above_ee_ml:g} mL above end-exhale"
        label = "mid-ventilation" if self.name == "mid" else self.name
        return f"{label}, {self.above_ee_ml:g} mL above end-exhale"

    def record(self) -> dict:
        """What the model file and the outputs record: ``state`` and ``above_end_exhale_ml``."""
        return {"state": self.name, "above_end_exhale_ml": float(self.above_ee_ml), "in_words": self.describe()}


def parse_scan_state(text: str, tidal_ml: float, option: str = "--scan-state") -> ScanState:
    """The :class:`ScanState` of ``text``: a name of :data:`NAMED_FRACTIONS`, a fraction 0 to 1 of
    ``tidal_ml`` (mL, both lungs), or a volume above end-exhale ``300mL`` (0 to
    :data:`MAX_ABOVE_ML`). :class:`InputError` naming ``option`` otherwise."""
    given = str(text).strip().lower()
    if given in NAMED_FRACTIONS:
        return ScanState(given, NAMED_FRACTIONS[given] * float(tidal_ml))
    usage = (f"{option} must be end-exhale, end-inhale, mid, a fraction of the tidal volume from 0 to 1, or a "
             f"volume above end-exhale such as 300mL, got {text!r}")
    volume = re.fullmatch(r"([-+0-9.eE]+)\s*ml", given)
    try:
        value = float(volume.group(1) if volume else given)
    except ValueError:
        raise InputError(usage) from None
    if volume:
        if not (math.isfinite(value) and 0.0 <= value <= MAX_ABOVE_ML):
            raise InputError(f"{option}: a volume above end-exhale must be 0 to {MAX_ABOVE_ML:g} mL, got {text!r}")
        return ScanState("volume" if value > 0 else "end-exhale", value)
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise InputError(usage)
    return ScanState("fraction" if value > 0 else "end-exhale", value * float(tidal_ml))
