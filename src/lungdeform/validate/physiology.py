"""The physiology of a tidal breath, measured on a model (docs/DEFAULTS.md "Physiology").

:func:`tidal_motion` plays a model to ``+tidal_ml`` (both lungs together, each lung its share, exactly;
:func:`lungdeform.model.tidal.tidal_split`)
and measures, per lung:

- ``mean_abs_mm`` ``(LR, AP, SI)``: the mean |displacement| of its vertices along each LPS axis;
- ``base_mm`` ``(LR, AP, SI)``: the same over the lung base, the vertices of the lowest
  :data:`BASE_FRACTION` of its height whose outward normal points to the feet (n_z < −0.5): the
  diaphragmatic surface;
- ``diaphragm_cm_per_l``: the base's mean descent (−z, cm) per litre of volume change of both lungs.

Published ranges the tests check it against (:data:`DIAPHRAGM_CM_PER_L`): quiet breathing moves the
diaphragm 1.6–1.8 cm on average (lower limits 0.9–1.0 cm) for a tidal volume near 0.5 L (Boussuges A,
Gole Y, Blanc P. Diaphragmatic motion studied by M-mode ultrasonography: methods, reproducibility,
and normal values. Chest 2009;135:391–400), and the shared data's note gives about 1.7 cm per litre
inspired; so 1.5–4.0 cm per litre.
"""

from __future__ import annotations

import numpy as np

from lungdeform.errors import InputError
from lungdeform.model.lung import Model
from lungdeform.model.tidal import tidal_split

#: Lowest fraction of a lung's height searched for its base.
BASE_FRACTION = 0.2
#: Published range of diaphragm excursion per litre inspired (cm/L; module docstring).
DIAPHRAGM_CM_PER_L = (1.5, 4.0)
AXES = ("LR", "AP", "SI")


def tidal_motion(model: Model, tidal_ml: float = 500.0) -> dict:
    """Per lung, the motion at ``+tidal_ml`` mL (both lungs) above end-exhale (module docstring)."""
    if not (np.isfinite(tidal_ml) and tidal_ml > 0):
        raise InputError(f"tidal_ml must be > 0 mL, got {tidal_ml!r}")
    # each lung its part as a build splits it (a lone lung: its side's usual share)
    parts = tidal_split({name: lung.volume_ee_ml for name, lung in model.lungs.items()}, tidal_ml)
    out = {}
    for name, lung in model.lungs.items():
        share = parts[name]
        p = lung.surface.vertices
        u = lung.surface_at(lung.volume_ee_ml + share, exact=True).vertices - p
        z = p[:, 2]
        low = z <= z.min() + BASE_FRACTION * np.ptp(z)
        base = low & (lung.surface.vertex_normals[:, 2] < -0.5)
        if not base.any():
            raise InputError(f"{name}: no vertex of the lowest {BASE_FRACTION:.0%} faces the feet: not a lung base")
        out[name] = {"share_ml": float(share),
                     "mean_abs_mm": np.abs(u).mean(axis=0).tolist(),
                     "base_mm": np.abs(u[base]).mean(axis=0).tolist(),
                     "diaphragm_cm_per_l": float(-u[base, 2].mean() / 10.0 / (tidal_ml / 1000.0)),
                     "axes": list(AXES)}
    return out
