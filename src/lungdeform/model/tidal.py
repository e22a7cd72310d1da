"""How a tidal volume given for both lungs together is split between the lungs of a model.

- :func:`tidal_split` (building): two lungs share it in proportion to their end-exhale volumes;
  a lone lung takes its side's usual share of both lungs, :data:`ONE_LUNG_SHARE` (right 53.6 %,
  left 46.4 %: CT lung volumes of 32 asymptomatic volunteers, supine, deep inspiration, Yamada et
  al., Respiration 2020;99(7):598–605, doi:10.1159/000507265, Table 3; standing 53.3/46.7 %). The
  same rule as for two lungs (share by volume), with the population's volumes standing in for the
  missing partner. The shipped data agree: the Coronacases lobe maps' left lungs are 44.9–46.9 % of
  both (docs/DEFAULTS.md, "Tidal volume of one lung").
- :func:`played_shares` (playing): the share of a both-lung volume change ΔV each lung of a model
  plays, ``calibration_ml / tidal_ml`` where the model records the both-lung tidal volume it was
  built for (provenance ``tidal_ml``); a model without one (a fit: each lung calibrated at its own
  measured volume change) shares ΔV in proportion to ``calibration_ml``.

Volumes in mL; shares are fractions of both lungs' volume change.
"""

from __future__ import annotations

import math

from lungdeform.errors import InputError

#: A lone lung's share of a both-lung tidal volume: its side's share of both lungs' volume
#: (Yamada et al. 2020, Table 3, supine CT; module docstring).
ONE_LUNG_SHARE = {"right": 0.536, "left": 0.464}
#: Where :data:`ONE_LUNG_SHARE` comes from, in words (printed by ``lungdeform build``).
ONE_LUNG_SOURCE = "Yamada et al., Respiration 2020;99:598, supine CT volumes"


def tidal_split(volumes_ml: dict[str, float], tidal_ml: float) -> dict[str, float]:
    """Each lung's part (mL) of ``tidal_ml`` (mL, both lungs together) from ``{side: end-exhale
    volume mL}``: two lungs in proportion to their volumes, one lung ``ONE_LUNG_SHARE[side]``."""
    if not (math.isfinite(tidal_ml) and tidal_ml > 0):
        raise InputError(f"tidal_ml must be > 0 mL, got {tidal_ml!r}")
    if not volumes_ml or not all(math.isfinite(v) and v > 0 for v in volumes_ml.values()):
        raise InputError(f"volumes_ml must be one or two lung volumes > 0 mL, got {volumes_ml!r}")
    if len(volumes_ml) == 1:
        (side,) = volumes_ml
        if side not in ONE_LUNG_SHARE:
            raise InputError(f"the side of a lone lung must be 'left' or 'right' (its share of the tidal "
                             f"volume depends on it), got {side!r}")
        return {side: tidal_ml * ONE_LUNG_SHARE[side]}
    total = sum(volumes_ml.values())
    return {side: tidal_ml * v / total for side, v in volumes_ml.items()}


def split_rule(sides: list[str]) -> str:
    """How :func:`tidal_split` shares the tidal volume between ``sides``, in words (recorded in a
    built model's provenance as ``tidal_split``)."""
    if len(sides) == 1 and sides[0] in ONE_LUNG_SHARE:
        return (f"one lung: the {sides[0]} lung's usual share of both lungs, "
                f"{ONE_LUNG_SHARE[sides[0]]:.1%} ({ONE_LUNG_SOURCE})")
    return "in proportion to the lungs' end-exhale volumes"


def played_shares(calibration_ml: dict[str, float], tidal_ml=None) -> dict[str, float]:
    """``{lung: share}`` of a both-lung volume change that each lung plays (module docstring):
    ``calibration_ml / tidal_ml`` when ``tidal_ml`` (the model's recorded both-lung tidal volume,
    mL) is given, else in proportion to ``calibration_ml``. Raises :class:`InputError` when the
    recorded volume is not a number > 0 or is less than the lungs' calibration volumes together."""
    total = sum(calibration_ml.values())
    if tidal_ml is None:
        return {k: c / total for k, c in calibration_ml.items()}
    if isinstance(tidal_ml, bool) or not isinstance(tidal_ml, (int, float)) or not (
            math.isfinite(tidal_ml) and tidal_ml > 0):
        raise InputError(f"the model's provenance entry tidal_ml must be a volume > 0 mL, got {tidal_ml!r}")
    if total > tidal_ml * (1 + 1e-9):
        raise InputError(f"the model's provenance entry tidal_ml ({tidal_ml:g} mL, both lungs) is less than "
                         f"its lungs' calibration volumes together ({total:g} mL)")
    # the lungs calibrated at all of it (every two-lung build): the same number, normalised exactly
    denom = total if abs(total - tidal_ml) <= 1e-9 * tidal_ml else float(tidal_ml)
    return {k: c / denom for k, c in calibration_ml.items()}
