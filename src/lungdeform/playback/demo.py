"""The main job on the embedded default lungs: build both, play one breath, write the results.

Steps: build the left and right lungs of the embedded default (Coronacases 001, CC BY 4.0) with the
population default (:mod:`lungdeform.model.population`; ``constants="paper"``: Table I), supine; play one breath of the ``normal`` preset of the PV breathing model
(:mod:`lungdeform.breathing.presets` → :func:`lungdeform.breathing.pv.simulate` → the volume above
end-exhale; 15/min, 500 mL; :func:`lungdeform.playback.schedule.preset_trace`) at the paper's
66.66 frames/s; write the model, a mesh time series, ``summary.json`` (volume per frame, per lung,
and its error) and a PNG snapshot.

The breathing curve drives each lung's share of the volume (in proportion to its end-exhale volume)
through the exact inverse of its volume cubic: frame k shows ``x = p + s_k·u`` with ``s_k`` the root
of ``V(p + s·u) = V_EE + share·ΔV(t_k)`` (:func:`lungdeform.playback.trajectory.lung_scales`, by
:func:`lungdeform.model.displacement.scale_for_volume`). The volume of every played frame is then
measured on the mesh (divergence theorem) and compared with the curve; ``summary.json`` also gives
how far the paper's linear reading ``s = share·ΔV/unit_ml`` would be from the curve.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lungdeform.atomic import atomic_dir, write_json
from lungdeform.breathing.presets import get_preset
from lungdeform.constants import STEPS_PER_S
from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.io.modelfile import save_model
from lungdeform.model.displacement import enclosed_volume_ml, volume_change_ml
from lungdeform.model.dome import DomeRequest
from lungdeform.model.lung import build_model
from lungdeform.model.population import PopulationDefault, resolve_default
from lungdeform.plot.figure import save_png
from lungdeform.plot.surface import snapshot
from lungdeform.progress import Progress, silent

from .export import export_pvd
from .schedule import lung_shares, preset_trace
from .trajectory import lung_scales

DEFAULT_PRESET = "normal"
#: Frames per second of the demo's ParaView series.
SERIES_FPS = 10.0


@dataclass(frozen=True)
class DemoResult:
    model: Path
    series: Path
    summary: Path
    snapshot: Path
    summary_data: dict


def _lung_summary(lung, delta_ml: np.ndarray, scales: np.ndarray) -> dict:
    """One lung's record of ``summary.json``: the volume (mL) measured on each played frame
    (``scales`` units) against the volume asked of it, ``V_EE + delta_ml`` (``delta_ml : (f,)`` mL,
    its share of the curve), and the error of the paper's linear reading ``s = delta_ml/unit_ml``."""
    target = lung.volume_ee_ml + delta_ml  # mL, what the curve asks of this lung
    pb = lung.playback(np.float64)
    measured = np.array([enclosed_volume_ml(pb.seek(sk), lung.surface.faces) for sk in scales])
    # the paper's linear reading s = ΔV/unit_ml, its volume from the exact cubic
    v_lin = lung.volume_ee_ml + volume_change_ml(lung.volume_poly, delta_ml / lung.unit_ml)
    err = measured - target
    return {
        "vertices": lung.n_vertices,
        "volume_ee_ml": lung.volume_ee_ml,
        "tidal_share_ml": lung.calibration_ml,
        "volume_ml": [round(float(x), 6) for x in measured],
        "target_volume_ml": [round(float(x), 6) for x in target],
        "volume_error_ml": [float(x) for x in err],
        "max_volume_error_percent": float(np.max(np.abs(err) / target) * 100),
        "linear_reading_max_error_percent": float(np.max(np.abs(v_lin - target) / target) * 100),
    }


def _summary(chosen, params, trace, tidal: float, orientation, per_lung: dict) -> dict:
    """``summary.json``: the breath played and each lung's measured volumes."""
    t, v_total = trace.t_s, trace.volume_ml
    duration = float(t[-1])
    summary = {
        "frames_per_second": (len(t) - 1) / duration,
        "duration_s": duration,
        "tidal_ml": tidal,
        "orientation": str(orientation),
        "breathing": {
            "preset": chosen.name, "description": chosen.description, "sources": list(chosen.sources),
            "period_s": params.period_s, "preset_tidal_volume_ml": chosen.tidal_volume_ml,
            "curve_tidal_ml": float(np.ptp(v_total)), "end_exhale_ml": trace.shifted_ml,
            "params": params.as_dict(),
            "meaning": "target_volume_above_ee_ml = V(t) - V_EE of the PV model; each lung takes its "
                       "share (in proportion to its end-exhale volume), met through the exact volume cubic",
        },
        "t_s": t.round(6).tolist(),
        "target_volume_above_ee_ml": v_total.round(6).tolist(),
        "lungs": per_lung,
    }
    summary["total_volume_ml"] = [round(sum(per_lung[n]["volume_ml"][i] for n in per_lung), 6)
                                  for i in range(len(t))]
    return summary


def _snapshot(out: Path, model, scales: dict, v_total: np.ndarray, chosen, orientation) -> Path:
    """End-inhale drawn first, end-exhale over it, from the front and the right: the red rim is how
    far the surface moved out at the peak of the breath."""
    peak = int(np.argmax(v_total))
    inhale = [(lung.surface_at(scale=scales[name][peak]).vertices, lung.surface.faces)
              for name, lung in model.lungs.items()]
    exhale = [(lung.surface.vertices, lung.surface.faces) for lung in model.lungs.values()]
    layers = [(inhale, "#d9534f", 1.0), (exhale, "#4a7ab5", 1.0)]
    dome = model.provenance.get("dome")
    told = (f"\n{dome['source']}: dome excursion " + ", ".join(f"{k} {v:.1f} mm" for k, v in dome["asked_mm"].items())
            if dome else "")
    return Path(save_png(snapshot(layers, views=("anterior", "lateral-right"),
                                  title=f"end-exhale (blue) inside end-inhale +{v_total[peak]:.0f} mL (red rim), "
                                        f"preset {chosen.name}, {orientation}{told}"), out / "snapshot.png"))


def run_demo(
    out: Path,
    *,
    preset: str = DEFAULT_PRESET,
    duration_s: float | None = None,
    tidal_ml: float | None = None,
    orientation="supine",
    constants=None,
    dome: DomeRequest | None = None,
    progress: Progress | None = None,
) -> DemoResult:
    """Build the default lungs and play ``preset`` (one period unless ``duration_s``) into ``out``.

    The set is written atomically (:func:`lungdeform.atomic.atomic_dir`): into a hidden temporary
    folder beside ``out``, renamed to ``out`` at the end, so that ``out`` holds the whole set or does
    not exist; a previous demo there is replaced only at the end. An ``out`` holding anything but
    a demo's files (:data:`DEMO_FILES`) is refused (:class:`InputError`) rather than replaced.
    ``constants``: the default the lungs are built with (:func:`lungdeform.model.population.resolve_default`:
    None or ``"population"``, ``"paper"``, a file). ``dome``: how far each dome descends over the breath
    (:class:`lungdeform.model.dome.DomeRequest`, ``--dome-mm`` / ``--breathing``); None: the default's own.
    """

    say = progress or silent
    chosen = get_preset(preset)
    posture = Posture(orientation, resolve_default(constants), dome)
    params, _curve, trace = preset_trace(chosen, 1, tidal_ml, STEPS_PER_S, duration_s=duration_s)
    out = Path(out)
    check_replaceable(out)
    with atomic_dir(out) as tmp:
        result = _run_into(tmp, chosen, params, trace, tidal_ml, posture, SERIES_FPS, say)
    final = {k: out / getattr(result, k).relative_to(tmp) for k in ("model", "series", "summary", "snapshot")}
    return dataclasses.replace(result, **final)


#: What a demo folder holds (and all that :func:`run_demo` replaces).
DEMO_FILES = ("model.npz", "summary.json", "series.pvd", "series_frames", "snapshot.png")


def check_replaceable(out: Path) -> None:
    """:class:`InputError` unless ``out`` is absent, an empty folder or a previous demo's folder."""
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_symlink() or (out.exists() and out.resolve() == Path.cwd().resolve()):
        raise InputError(f"{out}: the demo replaces its output folder as a whole; name a new folder")
    other = sorted(p.name for p in out.iterdir() if p.name not in DEMO_FILES) if out.is_dir() else []
    if other:
        raise InputError(f"{out}: holds other files ({', '.join(other[:3])}{', …' if len(other) > 3 else ''}); "
                         "the demo replaces its output folder as a whole: name a new or empty folder")


@dataclass(frozen=True)
class Posture:
    """How the demo's lungs are built: the ``orientation`` (gravity), the ``default`` (c1…c9, directions) and
    the ``dome`` request (None: the default's own)."""

    orientation: object
    default: PopulationDefault
    dome: DomeRequest | None = None


def _run_into(out: Path, chosen, params, trace, tidal_ml, posture: Posture, series_fps, say) -> DemoResult:
    """The demo's steps, writing into the (temporary) folder ``out``."""
    tidal = float(chosen.tidal_volume_ml if tidal_ml is None else tidal_ml)
    duration = float(trace.t_s[-1])
    say("loading the embedded default lungs (Coronacases 001, CC BY 4.0)")
    orientation = posture.orientation
    model = build_model(default_lungs(), tidal_ml=tidal, gravity=orientation, default=posture.default, progress=say,
                        dome=posture.dome, provenance={"command": "demo", "source": "embedded Coronacases 001 lungs",
                                    "orientation": str(orientation), "breathing": f"preset {chosen.name}"})
    model_path = save_model(out / "model.npz", model)
    say(f"playing the '{chosen.name}' preset ({tidal:g} mL, {params.period_s:g} s per breath) for "
        f"{duration:g} s at {(len(trace.t_s) - 1) / duration:.2f} frames/s")
    shares = lung_shares(model)
    scales = lung_scales(model, trace.volume_ml)
    per_lung = {name: _lung_summary(lung, shares[name] * trace.volume_ml, scales[name])
                for name, lung in model.lungs.items()}
    summary = _summary(chosen, params, trace, tidal, orientation, per_lung)
    if "dome" in model.provenance:  # the dome excursion asked and measured (--dome-mm, --breathing)
        summary["dome"] = model.provenance["dome"]
    summary_path = write_json(out / "summary.json", summary)
    series_path = _write_series(out, model, trace, series_fps, say)
    png = _snapshot(out, model, scales, trace.volume_ml, chosen, orientation)
    return DemoResult(model_path, series_path, summary_path, png, summary)


def _write_series(out: Path, model, breath, fps, say) -> Path:
    """Mesh time series for ParaView (``series.pvd`` + one ``.vtp`` per lung and frame)."""

    say(f"writing the mesh time series at {fps:g} frames/s")
    return export_pvd(model, out / "series.pvd", breath, fps=fps, progress=say)
