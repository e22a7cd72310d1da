"""The main job on the embedded default lungs: build both, play one breath, write the results.

Steps (issue 2 item 7): build the left and right lungs of the embedded default (Coronacases 001,
CC BY 4.0) with the Table I constants, supine; play one breath of the ``normal`` preset of the PV
breathing model (:mod:`lungdeform.presets` → :func:`lungdeform.breathing.pv.simulate` → the volume above
end-exhale; 15/min, 500 mL; :func:`lungdeform.playback.schedule.preset_trace`) at the paper's 66.66 frames/s; write the model, a mesh time series,
``summary.json`` (volume per frame, per lung, and its error) and a PNG snapshot.

The breathing curve drives each lung's share of the volume (in proportion to its end-exhale volume)
through the exact inverse of its volume cubic: frame k shows ``x = p + s_k·u`` with ``s_k`` the root
of ``V(p + s·u) = V_EE + share·ΔV(t_k)`` (:func:`lungdeform.model.displacement.scale_for_volume`). The
volume of every played frame is then measured on the mesh (divergence theorem) and compared with the
curve; ``summary.json`` also gives how far the paper's linear reading ``s = share·ΔV/unit_ml`` would
be from the curve.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from lungdeform.atomic import write_json
from lungdeform.breathing.presets import get_preset
from lungdeform.constants import STEPS_PER_S
from lungdeform.data import default_lungs
from lungdeform.geometry.mesh import signed_volume
from lungdeform.io.modelfile import save_model
from lungdeform.model.displacement import scale_for_volume
from lungdeform.model.lung import build_model
from lungdeform.plot import save_png, snapshot

from .export import export_pvd
from .schedule import lung_shares, preset_trace

DEFAULT_PRESET = "normal"


@dataclass(frozen=True)
class DemoResult:
    model: Path
    series: Path
    summary: Path
    snapshot: Path
    summary_data: dict


def run_demo(
    out: Path,
    *,
    preset: str = DEFAULT_PRESET,
    duration_s: float | None = None,
    tidal_ml: float | None = None,
    orientation="supine",
    series_fps: float = 10.0,
    progress: Callable[[str], None] | None = None,
) -> DemoResult:
    """Build the default lungs and play ``preset`` (one period unless ``duration_s``) into ``out``."""

    say = progress or (lambda _m: None)
    chosen = get_preset(preset)
    params, _curve, trace = preset_trace(chosen, 1, tidal_ml, STEPS_PER_S, duration_s=duration_s)
    tidal = float(chosen.tidal_volume_ml if tidal_ml is None else tidal_ml)
    duration = float(trace.t_s[-1])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    say("loading the embedded default lungs (Coronacases 001, CC BY 4.0)")
    lungs = default_lungs()
    model = build_model(lungs, tidal_ml=tidal, gravity=orientation, progress=say,
                        provenance={"command": "demo", "source": "embedded Coronacases 001 lungs",
                                    "orientation": str(orientation), "breathing": f"preset {chosen.name}"})
    model_path = save_model(out / "model.npz", model)
    t, v_total = trace.t_s, trace.volume_ml
    fps = (len(t) - 1) / duration
    say(f"playing the '{chosen.name}' preset ({tidal:g} mL, {params.period_s:g} s per breath) for "
        f"{duration:g} s at {fps:.2f} frames/s")
    shares = lung_shares(model)
    per_lung: dict[str, dict] = {}
    scales: dict[str, np.ndarray] = {}
    for name, lung in model.lungs.items():
        target = lung.volume_ee_ml + shares[name] * v_total  # mL, what the curve asks of this lung
        s = np.array([scale_for_volume(lung.volume_poly, float(dv)) for dv in shares[name] * v_total])
        scales[name] = s
        pb = lung.playback(np.float64)
        measured = np.array([signed_volume(pb.seek(sk), lung.surface.faces) / 1000.0 for sk in s])
        # the paper's linear reading s = ΔV/unit_ml, its volume from the exact cubic (mm³ → mL)
        s_lin = shares[name] * v_total / lung.unit_ml
        c = lung.volume_poly
        v_lin = lung.volume_ee_ml + (c[1] * s_lin + c[2] * s_lin ** 2 + c[3] * s_lin ** 3) / 1000.0
        err = measured - target
        per_lung[name] = {
            "vertices": lung.n_vertices,
            "volume_ee_ml": lung.volume_ee_ml,
            "tidal_share_ml": lung.calibration_ml,
            "volume_ml": [round(float(x), 6) for x in measured],
            "target_volume_ml": [round(float(x), 6) for x in target],
            "volume_error_ml": [float(x) for x in err],
            "max_volume_error_percent": float(np.max(np.abs(err) / target) * 100),
            "linear_reading_max_error_percent": float(np.max(np.abs(v_lin - target) / target) * 100),
        }
    summary = {
        "frames_per_second": fps,
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
    summary_path = write_json(out / "summary.json", summary)
    series_path = _write_series(out, model, trace, series_fps, say)
    peak = int(np.argmax(v_total))
    # end-inhale first, end-exhale over it: the red rim is how far the surface moved out
    inhale = [(lung.surface_at(scale=scales[name][peak]).vertices, lung.surface.faces)
              for name, lung in model.lungs.items()]
    exhale = [(lung.surface.vertices, lung.surface.faces) for lung in model.lungs.values()]
    layers = [(inhale, "#d9534f", 1.0), (exhale, "#4a7ab5", 1.0)]
    png = save_png(snapshot(layers, views=("anterior", "lateral-right"),
                            title=f"end-exhale (blue) inside end-inhale +{v_total[peak]:.0f} mL (red rim), "
                                  f"preset {chosen.name}, {orientation}"), out / "snapshot.png")
    return DemoResult(model_path, series_path, summary_path, png, summary)


def _write_series(out: Path, model, breath, fps, say) -> Path:
    """Mesh time series for ParaView (``series.pvd`` + one ``.vtp`` per lung and frame)."""

    say(f"writing the mesh time series at {fps:g} frames/s")
    return export_pvd(model, out / "series.pvd", breath, fps=fps, progress=say)
