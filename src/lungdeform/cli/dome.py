"""The dome options of ``build`` and ``demo``: ``--dome-mm`` and ``--breathing`` (:mod:`lungdeform.model.dome`)."""

from __future__ import annotations

from lungdeform.errors import InputError
from lungdeform.geometry.frame import SIDES
from lungdeform.model.dome import BREATHING, DomeRequest, check_excursion

DOME_MM_HELP = ("How far the diaphragm dome descends relative to the apex over the breath --tidal-ml describes "
                "(mm; ultrasound, fluoroscopy, a 4-D CT; docs/DEFAULTS.md 'Dome excursion'): one number for "
                "both domes, or 'left=MM,right=MM'. The breath is split so that each dome moves that far, the "
                "rest of the lung following the default's pattern. Default: the default's own.")
BREATHING_HELP = ("A breathing pattern for a scene without a measurement: "
                  + ", ".join(f"{k} (the dome sweeps {v:.0%} of each lung's breath)" for k, v in BREATHING.items())
                  + " (docs/DEFAULTS.md 'Dome excursion'). Not with --dome-mm.")


def dome_request(dome_mm: str | None, breathing: str | None) -> DomeRequest | None:
    """The :class:`DomeRequest` of ``--dome-mm`` / ``--breathing`` (None: neither), or :class:`InputError`
    naming the option: both given, a side other than left/right, or a value that is not a number of mm
    in [0, :data:`lungdeform.model.dome.MAX_DOME_MM`]."""
    if dome_mm is not None and breathing is not None:
        raise InputError("give --dome-mm or --breathing, not both")
    if breathing is not None:
        if breathing not in BREATHING:
            raise InputError(f"--breathing must be one of {', '.join(BREATHING)}, got {breathing!r}")
        return DomeRequest.breathing(breathing)
    if dome_mm is None:
        return None
    text = dome_mm.strip()
    if "=" not in text:
        return DomeRequest(mm={"both": check_excursion(text, "--dome-mm")}, source=f"--dome-mm {text}")
    mm = {}
    for part in text.split(","):
        side, _, value = part.partition("=")
        side = side.strip().lower()
        if side not in SIDES or side in mm:
            raise InputError(f"--dome-mm must be MM or 'left=MM,right=MM' (each side once), got {dome_mm!r}")
        mm[side] = check_excursion(value.strip(), f"--dome-mm {side}")
    return DomeRequest(mm=mm, source=f"--dome-mm {text}")


def dome_lines(record: dict | None, volumes_ml: dict) -> list[str]:
    """One line per lung of a model built with a dome request: the excursion asked and measured over its
    volume change ``volumes_ml[side]`` (mL); ``record``: the model's ``provenance["dome"]`` (None: no lines)."""
    if not record:
        return []
    return [f"{side}: dome excursion {record['measured_mm'][side]:.1f} mm relative to the apex over +{ml:.0f} mL "
            f"(asked {record['asked_mm'][side]:.1f} mm: {record['source']})" for side, ml in volumes_ml.items()]
