"""The main job on the embedded default lungs: build both, play one breath, write the results.

Steps (issue 2 item 7): build the left and right lungs of the embedded default (Coronacases 001,
CC BY 4.0) with the Table I constants, supine; play one 5 s breath of 500 mL (both lungs together,
split in proportion to their end-exhale volumes) at the paper's 66.66 frames/s; write the model,
a mesh time series, ``summary.json`` (volume per frame, per lung) and a PNG snapshot.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .atomic import write_json
from .constants import STEPS_PER_S
from .mesh import signed_volume


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
    duration_s: float = 5.0,
    tidal_ml: float = 500.0,
    orientation="supine",
    series_fps: float = 10.0,
    progress: Callable[[str], None] | None = None,
) -> DemoResult:
    """Build the default lungs and play one breath into ``out`` (a folder)."""
    from .data import default_lungs
    from .model import build_model
    from .modelfile import save_model
    from .render import snapshot

    say = progress or (lambda _m: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    say("loading the embedded default lungs (Coronacases 001, CC BY 4.0)")
    lungs = default_lungs()
    model = build_model(lungs, tidal_ml=tidal_ml, gravity=orientation, progress=say,
                        provenance={"command": "demo", "source": "embedded Coronacases 001 lungs",
                                    "orientation": str(orientation)})
    model_path = save_model(out / "model.npz", model)
    say(f"playing one {duration_s:g} s, {tidal_ml:g} mL breath at {STEPS_PER_S:.2f} frames/s")
    from .export import plain_cycle

    breath = plain_cycle(tidal_ml, duration_s, STEPS_PER_S)  # one cosine breath at 66.66 frames/s
    t, v_total = breath.t_s, breath.volume_ml
    frames: dict[str, list[float]] = {}
    scales: dict[str, np.ndarray] = {}
    for name, lung in model.lungs.items():
        share = lung.calibration_ml / tidal_ml
        s = share * v_total / lung.unit_ml
        scales[name] = s
        pb = lung.playback(np.float64)
        vols = []
        for sk in s:
            x = pb.seek(sk)
            vols.append(signed_volume(x, lung.surface.faces) / 1000.0)
        frames[name] = vols
    summary = {
        "frames_per_second": (len(t) - 1) / duration_s,
        "duration_s": duration_s,
        "tidal_ml": tidal_ml,
        "orientation": str(orientation),
        "t_s": t.round(6).tolist(),
        "target_volume_above_ee_ml": v_total.round(6).tolist(),
        "lungs": {
            name: {
                "vertices": lung.n_vertices,
                "volume_ee_ml": lung.volume_ee_ml,
                "tidal_share_ml": lung.calibration_ml,
                "volume_ml": [round(x, 6) for x in frames[name]],
                "max_volume_error_percent": float(np.max(np.abs(
                    np.array(frames[name]) - (lung.volume_ee_ml + scales[name] * lung.unit_ml))
                    / (lung.volume_ee_ml + scales[name] * lung.unit_ml)) * 100),
            }
            for name, lung in model.lungs.items()
        },
    }
    summary["total_volume_ml"] = [round(sum(frames[n][i] for n in frames), 6) for i in range(len(t))]
    summary_path = write_json(out / "summary.json", summary)
    series_path = _write_series(out, model, breath, series_fps, say)
    peak = int(np.argmax(v_total))
    layers = []
    for name, lung in model.lungs.items():
        layers.append((lung.surface, "#4a7ab5", 1.0))
    for name, lung in model.lungs.items():
        layers.append((lung.surface_at(scale=scales[name][peak]), "#d9534f", 0.35))
    png = snapshot(out / "snapshot.png", layers, views=("anterior", "lateral-right"),
                   title=f"end-exhale (blue) and end-inhale +{v_total[peak]:.0f} mL (red), {orientation}")
    return DemoResult(model_path, series_path, summary_path, png, summary)


def _write_series(out: Path, model, breath, fps, say) -> Path:
    """Mesh time series for ParaView (``series.pvd`` + one ``.vtp`` per lung and frame)."""
    from .export import export_pvd

    say(f"writing the mesh time series at {fps:g} frames/s")
    return export_pvd(model, out / "series.pvd", breath, fps=fps, progress=say)
