"""The breathing schedule a lung model plays: the volume of both lungs over time, and each lung's share.

A :class:`VolumeTrace` holds ``t_s : (k,) float`` (s, from 0, strictly increasing) and
``volume_ml : (k,) float`` (mL, both lungs together, above end-exhale). :func:`lung_shares` gives
each lung its share of that volume (its ``calibration_ml`` over the both-lung tidal volume the model
was built for: a lone lung plays its side's share, not the whole breath); each lung then plays
``V_EE + share · ΔV(t)`` exactly (:mod:`lungdeform.playback.export` for surfaces, :mod:`lungdeform.playback.trajectory`
for interior points).

Breathing curve: a CSV with columns ``t_s, volume_ml[, flow_ml_s, pressure_cmH2O]`` (as written by
``lungdeform breathe``); ``volume_ml`` is read as the volume of both lungs above end-exhale, unless
its minimum lies above its own peak-to-peak range (an absolute volume), when the minimum is
subtracted (reported in :attr:`VolumeTrace.shifted_ml`). Without a curve: :func:`plain_cycle`.
A simulated :class:`lungdeform.breathing.pv.BreathingCurve` (a preset, a fit) becomes a trace through
:meth:`VolumeTrace.from_breathing`; :func:`preset_trace` simulates a preset of
:mod:`lungdeform.breathing.presets` on an exact frame grid and does both (``export --preset``, ``demo``, the
viewer server's ``/presets.json``).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass

import numpy as np

from lungdeform.breathing.presets import get_preset
from lungdeform.breathing.pv import BreathingCurve, scaled_to_tidal_volume, simulate
from lungdeform.constants import STEPS_PER_S, TIDAL_VOLUME_ML
from lungdeform.errors import InputError, LungdeformError, ReadError, require_file
from lungdeform.model.lung import Model
from lungdeform.model.tidal import played_shares


@dataclass(frozen=True)
class VolumeTrace:
    """Volume of both lungs above end-exhale over time.

    t_s : (k,) float, s, strictly increasing; volume_ml : (k,) float, mL above end-exhale;
    source : str; shifted_ml : float, the minimum subtracted from an absolute-volume curve (0 if none);
    lines : (k,) int or None, the 1-based line of each sample in the curve file it was read from.
    """

    t_s: np.ndarray
    volume_ml: np.ndarray
    source: str = "plain cycle"
    shifted_ml: float = 0.0
    lines: np.ndarray | None = None

    def sample(self, t_s) -> np.ndarray:
        """Linear interpolation of the volume (mL) at times ``t_s`` (clamped to the ends)."""
        return np.interp(np.asarray(t_s, float), self.t_s, self.volume_ml)

    @classmethod
    def from_breathing(cls, curve, source: str | None = None) -> "VolumeTrace":
        """The trace of a :class:`lungdeform.breathing.pv.BreathingCurve` (absolute lung volume, mL).

        Times are shifted to start at 0 and the volume becomes ``V(t) − V_EE``, with ``V_EE`` the
        curve's minimum (:attr:`BreathingCurve.v_ee_ml`, kept in :attr:`shifted_ml`). Flow and
        pressure are dropped: playback needs the volume only. ``source`` defaults to the curve's
        ``meta["source"]`` or a generic name.
        """
        t = np.asarray(curve.t_s, float)
        v_ee = float(curve.v_ee_ml)
        if source is None:
            source = str(curve.meta.get("source", "breathing curve (lungdeform.breathing)"))
        return cls(t - t[0], np.asarray(curve.volume_ml, float) - v_ee, source, v_ee)


def plain_cycle(tidal_ml: float = TIDAL_VOLUME_ML, period_s: float = 4.0, rate_hz: float = 30.0) -> VolumeTrace:
    """One cosine breath: ``ΔV(t) = tidal/2 · (1 − cos 2πt/T)``, sampled at ``rate_hz`` over one period."""
    if not (tidal_ml > 0 and period_s > 0 and rate_hz > 0):
        raise InputError("tidal_ml, period_s and rate_hz must all be > 0")
    n = max(int(round(period_s * rate_hz)), 8)
    t = np.linspace(0.0, period_s, n + 1)
    v = 0.5 * tidal_ml * (1.0 - np.cos(2.0 * np.pi * t / period_s))
    return VolumeTrace(t, v, f"plain cycle: {tidal_ml:g} mL, {period_s:g} s, cosine")


def preset_trace(preset, cycles: int = 1, tidal_ml: float | None = None, rate_hz: float = STEPS_PER_S,
                 *, duration_s: float | None = None):
    """A breathing preset simulated by the PV model, on a frame grid that ends exactly at the end.

    preset : :class:`lungdeform.breathing.presets.Preset` or its name; cycles : whole breaths played (>= 1),
    duration ``D = cycles·T`` (T the preset's period, s); duration_s : s, any length > 0 instead of
    whole cycles (the simulation runs whole cycles and is cut after the last frame); tidal_ml : mL,
    both lungs (default: the preset's; otherwise its control parameters are rescaled with
    :func:`lungdeform.breathing.pv.scaled_to_tidal_volume`, the same shape); rate_hz : Hz, the least
    sample rate: ``n = ceil(D·rate_hz)`` intervals (at least 8), frames at ``t_k = k·D/n``, which the
    simulation (:func:`lungdeform.breathing.pv.simulate`, periodic steady state from the onset of
    inspiration at t = 0) outputs directly, no resampling.

    Returns ``(params, curve, trace)``: the :class:`~lungdeform.breathing.pv.BreathingParams` played,
    the :class:`~lungdeform.breathing.pv.BreathingCurve` (n + 1 frames, absolute volume, mL) and its
    :class:`VolumeTrace` (volume above the curve's minimum, end-exhale, mL; that minimum in
    ``shifted_ml``).
    """

    if isinstance(preset, str):
        preset = get_preset(preset)
    period = float(preset.params.period_s)
    if duration_s is None:
        try:
            whole = int(cycles) == cycles and int(cycles) >= 1
        except (TypeError, ValueError, OverflowError):
            whole = False
        if not whole:
            raise InputError(f"cycles must be a whole number >= 1, got {cycles!r}")
        duration, n_cycles = period * int(cycles), int(cycles)
    else:
        duration = float(duration_s)
        if not (np.isfinite(duration) and duration > 0):
            raise InputError(f"duration must be > 0 s, got {duration_s!r}")
        n_cycles = max(int(math.ceil(duration / period - 1e-9)), 1)
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise InputError(f"rate_hz must be > 0, got {rate_hz!r}")
    params = preset.params
    if tidal_ml is not None:
        if not (np.isfinite(tidal_ml) and tidal_ml > 0):
            raise InputError(f"tidal volume must be > 0 mL, got {tidal_ml!r}")
        params = scaled_to_tidal_volume(params, float(tidal_ml))
    n = max(int(math.ceil(duration * rate_hz - 1e-9)), 8)
    sim = simulate(params, n_cycles=n_cycles, fs_hz=n / duration)
    keep = sim.t_s <= duration * (1 + 1e-9)
    curve = BreathingCurve(sim.t_s[keep], sim.volume_ml[keep], sim.flow_ml_s[keep],
                           sim.pressure_cmH2O[keep], meta={**sim.meta, "source": f"preset {preset.name}"})
    if len(curve.t_s) != n + 1 or not math.isclose(curve.t_s[-1], duration, rel_tol=1e-9):
        # simulate() samples at k/fs_hz up to the end of its last cycle; guard that reading
        raise LungdeformError(f"breathing simulation gave {len(curve.t_s)} frames ending at "
                              f"{curve.t_s[-1]} s, expected {n + 1} ending at {duration} s")
    rescaled = "" if tidal_ml is None else f", rescaled to {float(tidal_ml):g} mL"
    trace = VolumeTrace.from_breathing(
        curve, f"lungdeform.presets:{preset.name} ({preset.description}{rescaled}), PV model simulated "
               f"over {duration:g} s")
    return params, curve, trace


def read_volume_csv(path) -> VolumeTrace:
    """Read a breathing curve CSV (header with ``t_s`` and ``volume_ml``); see the module docstring."""
    path = require_file(path, "curve", "give the curve.csv that breathe wrote")
    try:  # utf-8-sig: spreadsheet "CSV UTF-8" exports start with a byte-order mark
        with open(path, newline="", encoding="utf-8-sig") as fh:
            text = fh.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise ReadError(f"{path}: cannot read curve ({exc})") from exc
    first = next((ln for ln in text.splitlines() if ln.strip()), "")
    # a curve re-saved by a spreadsheet in a decimal-comma locale: ';' separated, decimal commas
    sep = ";" if ";" in first and "," not in first else ("\t" if "\t" in first and "," not in first else ",")
    rows = list(csv.reader(text.splitlines(), delimiter=sep))
    if not rows:
        raise ReadError(f"{path}: empty curve file")
    if sep != ",":
        rows = [rows[0]] + [[c.replace(",", ".") for c in r] for r in rows[1:]]
    header = [h.strip().strip('"') for h in rows[0]]
    for col in ("t_s", "volume_ml"):
        if col not in header:
            raise ReadError(f"{path}: curve needs a '{col}' column, header is {','.join(header)}")
    it, iv = header.index("t_s"), header.index("volume_ml")
    t, v, lines = [], [], []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            t.append(float(row[it]))
            v.append(float(row[iv]))
            lines.append(lineno)
        except (IndexError, ValueError) as exc:
            raise ReadError(f"{path}: line {lineno}: expected numbers in t_s and volume_ml") from exc
    t_arr, v_arr = np.array(t), np.array(v)
    if len(t_arr) < 2:
        raise ReadError(f"{path}: a curve needs at least 2 rows, got {len(t_arr)}")
    if not (np.all(np.isfinite(t_arr)) and np.all(np.isfinite(v_arr))):
        raise ReadError(f"{path}: t_s and volume_ml must be finite (no NaN or inf)")
    if np.any(np.diff(t_arr) <= 0):
        raise ReadError(f"{path}: t_s must be strictly increasing")
    shift = 0.0
    if v_arr.min() > np.ptp(v_arr):  # an absolute volume, far above 0: use the volume above its minimum
        shift = float(v_arr.min())
        v_arr = v_arr - shift
    return VolumeTrace(t_arr - t_arr[0], v_arr, str(path), shift, np.array(lines, dtype=np.int64))


#: The least volume a lung can breathe down to, as a fraction of its end-exhale volume: the residual
#: volume (left after a maximal exhalation) is about half the functional residual capacity at end of a
#: quiet exhalation (adult RV ≈ 1.2 L, FRC ≈ 2.4 L), so a curve below it is not one a lung can follow
#: (and the model's volume cubic need not have a root there, docs/METHOD_NOTES.md).
MIN_VOLUME_FRACTION = 0.5


#: The largest volume a lung can breathe up to, as a multiple of its end-exhale volume (total lung
#: capacity is about twice the functional residual capacity, adult TLC ≈ 6 L, FRC ≈ 2.4–3 L): a
#: state or a curve beyond it is refused as unreachable.
MAX_GROWTH = 3.0


def check_reachable(trace: VolumeTrace, model: Model) -> None:
    """Refuse a trace whose volume takes a lung below :data:`MIN_VOLUME_FRACTION` of its end-exhale
    volume, or above :data:`MAX_GROWTH` times it (each lung plays ``V_EE + share · ΔV``,
    :func:`lung_shares`), naming the first such sample: its line in the curve file when the trace
    was read from one. Raises :class:`InputError`."""
    shares = lung_shares(model)
    # each lung's own end-exhale volume: its scan's, less its share of the scan's height above end-exhale
    ee = {side: lung.volume_ee_ml - shares[side] * model.scan.above_ee_ml for side, lung in model.lungs.items()}
    # the ΔV (both lungs) that takes each lung to a bound; the least negative (lowest positive) is reached first
    low = {side: -(1.0 - MIN_VOLUME_FRACTION) * ee[side] / shares[side] for side in model.lungs}
    high = {side: (MAX_GROWTH - 1.0) * ee[side] / shares[side] for side in model.lungs}
    v = np.asarray(trace.volume_ml)
    for bounds, pick, outside, words in ((low, max, v < max(low.values()), f"below {MIN_VOLUME_FRACTION:.0%} of"),
                                         (high, min, v > min(high.values()), f"above {MAX_GROWTH:g} times")):
        worst = pick(bounds, key=bounds.get)
        rows = np.nonzero(outside)[0]
        if not len(rows):
            continue
        i = int(rows[0])
        where = f"line {int(trace.lines[i])}" if trace.lines is not None else f"sample {i + 1} (t {trace.t_s[i]:g} s)"
        dv = float(v[i])
        raise InputError(
            f"{trace.source} {where}: volume_ml {dv + trace.shifted_ml:g} mL (ΔV {dv:.0f} mL above end-exhale, "
            f"both lungs) takes the {worst} lung to {ee[worst] + shares[worst] * dv:.0f} mL, {words} "
            f"its end-exhale {ee[worst]:.0f} mL: no lung reaches that "
            f"({len(rows)} such rows; volume_ml is the volume of both lungs above end-exhale)"
        )


def lung_shares(model: Model) -> dict[str, float]:
    """Each lung's share of the total (both-lung) volume change: its ``calibration_ml`` over the
    both-lung tidal volume the model was built for (provenance ``tidal_ml``; a lone lung built for
    500 mL plays its 46–54 % of a 500 mL breath), else in proportion to ``calibration_ml`` (a fit)
    (:func:`lungdeform.model.tidal.played_shares`)."""
    cal = {k: lung.calibration_ml for k, lung in model.lungs.items()}
    return played_shares(cal, (model.provenance or {}).get("tidal_ml"))
