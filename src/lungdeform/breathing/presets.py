"""Breathing presets: normal, deep / vital-capacity, obstructive, restrictive, dyspnoea, pneumothorax.

Each preset fixes the mechanics (E, R, I), the timing (period, inspiratory fraction ρ = T_i/T_tot of the
muscle drive, PIIA decay κ), the relative muscle-pressure pattern over the five basis functions of
:mod:`lungdeform.breathing.pv`, and a target tidal volume; the absolute control parameters a_k (cmH2O)
are then scaled once so the periodic solution has exactly that tidal volume (the equation is linear).
The values are *representative* choices inside published ranges, not measurements of one subject:

- Normal quiet breathing. Respiratory-system compliance ≈ 0.1 L/cmH2O (E_rs ≈ 10 cmH2O/L; lung and
  chest wall ≈ 0.2 L/cmH2O each) and airway resistance ≈ 1–3 cmH2O·s/L (West, *Respiratory
  Physiology: The Essentials*, ch. 7); inertance ≈ 0.01 cmH2O·s²/L (Mead, Physiol Rev 1961;41:281);
  rate ≈ 15/min, T_i/T_tot ≈ 0.42 (Tobin et al., Chest 1983;84:202 "Breathing patterns 1: normal
  subjects"); tidal volume 500 mL (project convention, the paper's Sec. V). FRC ≈ 2.4 L.
- Deep breathing / slow vital-capacity manoeuvre: from residual volume to total lung capacity,
  VC ≈ 4.5 L in an adult man (Quanjer et al., Eur Respir J 1993;6 Suppl 16:5; slow VC manoeuvre as in
  Miller et al., ATS/ERS standardisation, Eur Respir J 2005;26:319), ≈ 12 s per manoeuvre, with active
  expiration (a_4 < 0) taking the volume below FRC (expiratory reserve). Linear elastance: the
  flattening of the PV curve near TLC is not modelled.
- Obstructive (COPD): raised resistance R_rs ≈ 10–20 cmH2O·s/L and a long time constant
  (Lucangelo et al., Respir Care 2005;50:55 "Respiratory mechanics derived from signals in the
  ventilator circuit"), lower elastance in emphysema, T_i/T_tot ≈ 0.33 (I:E ≈ 1:2; Tobin et al.,
  Chest 1983;84:286 "Breathing patterns 2: diseased subjects"). With τ = R/E = 1.5 s and T_e ≈ 2.1 s
  < 3τ, expiration is incomplete: end-expiratory volume rises above the relaxation volume
  (dynamic hyperinflation, air trapping, intrinsic PEEP).
  Simulate with ``start="rest"`` to watch it build up. FRC ≈ 3.5 L (hyperinflated).
- Restrictive (interstitial fibrosis): stiff lungs, E_rs ≈ 25 cmH2O/L, normal R, small tidal
  volume and fast rate (≈ 23/min; Javaheri & Sicilian, Thorax 1992;47:93). FRC ≈ 1.7 L.
- Dyspnoea (rapid shallow breathing): ≈ 32/min, V_T ≈ 280 mL, f/V_T ≈ 114 breaths/min/L, above the
  105 threshold of Yang & Tobin (N Engl J Med 1991;324:1445). Normal mechanics.
- One-sided pneumothorax, the collapsed side: air in the pleural space uncouples that lung from the
  chest wall; the lung recoils to a small volume and barely ventilates. Its PV relation: a very
  high effective elastance (≈ 60 cmH2O/L for that lung) and a small relaxation volume (≈ 0.4 L),
  tidal volume ≈ 60 mL, driven at a tachypnoeic 25/min (Noppen & De Keukeleire, Respiration
  2008;76:121). Use it for the collapsed lung only, with ``normal`` or ``dyspnoea`` for the other.
"""

from __future__ import annotations

from dataclasses import dataclass

from lungdeform.errors import InputError

from .pv import BreathingParams, Mechanics, scaled_to_tidal_volume


@dataclass(frozen=True)
class Preset:
    """name; description; params : :class:`BreathingParams` (a_k already scaled);
    tidal_volume_ml : target V_T, mL; sources : citations for the values."""

    name: str
    description: str
    params: BreathingParams
    tidal_volume_ml: float
    sources: tuple

    def as_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "tidal_volume_ml": self.tidal_volume_ml,
                "params": self.params.as_dict(), "sources": list(self.sources)}


def _make(name, description, params: BreathingParams, vt, sources) -> Preset:
    """The preset with ``params`` (a_k relative) scaled once to the tidal volume ``vt`` mL."""
    return Preset(name, description, scaled_to_tidal_volume(params, vt), vt, tuple(sources))


def _params(mech, pattern, period, rho, decay, relax) -> BreathingParams:
    return BreathingParams(mech, pattern, period_s=period, insp_fraction=rho, decay=decay, relaxation_ml=relax)


_WEST = "West JB, Respiratory Physiology: The Essentials (compliance, airway resistance)"
_MEAD = "Mead J, Physiol Rev 1961;41:281 (inertance)"


def _build() -> dict[str, Preset]:
    presets = [
        _make("normal", "normal quiet breathing, 15/min, 500 mL",
              _params(Mechanics(10.0, 2.5, 0.01), (0.0, 1.0, 0.5, 0.0, 0.0), 4.0, 0.42, 0.15, 2400.0), 500.0,
              [_WEST, _MEAD, "Tobin MJ et al., Chest 1983;84:202 (normal breathing pattern)"]),
        _make("deep", "deep breathing / slow vital-capacity manoeuvre, 5/min, 4.5 L with active expiration",
              _params(Mechanics(10.0, 2.5, 0.01), (0.0, 1.0, 0.3, -0.6, 0.0), 12.0, 0.45, 0.1, 2400.0), 4500.0,
              ["Quanjer PH et al., Eur Respir J 1993;6 Suppl 16:5 (vital capacity)",
               "Miller MR et al., Eur Respir J 2005;26:319 (slow VC manoeuvre)", _WEST]),
        _make("copd", "obstructive (COPD): high resistance, long expiration, air trapping",
              _params(Mechanics(8.0, 12.0, 0.01), (0.0, 1.0, 0.3, 0.0, 0.0), 3.2, 0.33, 0.1, 3500.0), 500.0,
              ["Lucangelo U et al., Respir Care 2005;50:55 (R_rs, E_rs in COPD)",
               "Tobin MJ et al., Chest 1983;84:286 (breathing pattern in COPD)"]),
        _make("restrictive", "restrictive (fibrosis): stiff lungs, small fast breaths",
              _params(Mechanics(25.0, 3.0, 0.01), (0.0, 1.0, 0.5, 0.0, 0.0), 2.6, 0.42, 0.15, 1700.0), 350.0,
              ["Javaheri S, Sicilian L, Thorax 1992;47:93 (breathing pattern in interstitial lung disease)",
               _WEST]),
        _make("dyspnoea", "dyspnoea: rapid shallow breathing, 32/min, 280 mL",
              _params(Mechanics(10.0, 2.5, 0.01), (0.0, 1.0, 0.2, 0.0, 0.3), 1.875, 0.45, 0.15, 2400.0), 280.0,
              ["Yang KL, Tobin MJ, N Engl J Med 1991;324:1445 (rapid shallow breathing index)", _WEST]),
        _make("pneumothorax", "one-sided pneumothorax: PV relation of the collapsed lung (use the other "
              "preset for the healthy side)",
              _params(Mechanics(60.0, 4.0, 0.01), (0.0, 1.0, 0.5, 0.0, 0.0), 2.4, 0.42, 0.15, 400.0), 60.0,
              ["Noppen M, De Keukeleire T, Respiration 2008;76:121 (pneumothorax)", _WEST]),
    ]
    return {p.name: p for p in presets}


PRESETS: dict[str, Preset] = _build()
PRESET_NAMES = tuple(PRESETS)


def get_preset(name: str) -> Preset:
    """The preset called ``name`` (case-insensitive), or InputError listing the names."""
    key = str(name).strip().lower()
    if key not in PRESETS:
        raise InputError(f"unknown breathing preset {name!r}; choose one of: {', '.join(PRESET_NAMES)}")
    return PRESETS[key]
