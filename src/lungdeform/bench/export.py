"""Size and time of the OpenUSD exports against the glb of the same model and curve, in the same run.

For each model (the embedded lungs as ``lungdeform demo`` builds them; models of about N vertices from
:func:`lungdeform.bench.viewer.model_with_vertices`, the embedded lungs subdivided) and one curve (by
default :func:`lungdeform.playback.schedule.plain_cycle`: one 4 s breath, 121 frames), each format of
:data:`FORMATS` is written ``repeats`` times to a temporary folder, the formats interleaved within
each repeat so that a busy machine slows them alike. The yardstick is the glb
(:func:`lungdeform.playback.export.export_glb`, what engines load today): each format's bytes and
median seconds are reported with their ratio to the glb's. Targets (docs/VIEWER.md, "OpenUSD and
USDZ"): the blend-shape USDZ at most 1.5 × the glb's bytes, and its export time for 1,000,000
vertices within 2 × the glb's.

Record per model: ``model``, ``vertices`` (both lungs), ``frames``, ``curve``, and ``formats``: per
format ``bytes``, ``seconds`` (median), ``seconds_all``, ``bytes_ratio_to_glb``, ``seconds_ratio_to_glb``.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from lungdeform.errors import InputError
from lungdeform.model.lung import Model
from lungdeform.playback.export import export_glb
from lungdeform.playback.schedule import VolumeTrace, plain_cycle
from lungdeform.playback.usd import export_usd, require_usd, usd_frames

#: (name, file suffix, baked): the glb yardstick, the blend-shape crate and USDZ, the baked USDZ.
FORMATS = (("glb", ".glb", False), ("usdc", ".usdc", False), ("usdz", ".usdz", False),
           ("usdz --baked", ".usdz", True))


def _write(model: Model, path: Path, trace: VolumeTrace, baked: bool) -> None:
    if path.suffix == ".glb":
        export_glb(model, path, trace)
    else:
        export_usd(model, path, trace, baked=baked)


def export_record(model: Model, label: str, trace: VolumeTrace | None = None, *, repeats: int = 3,
                  baked_max_vertices: int = 100_000) -> dict:
    """One model's record (see the module docstring); the baked USDZ only up to ``baked_max_vertices``
    vertices (both lungs: it holds every vertex at every distinct frame)."""
    if repeats < 1:
        raise InputError(f"repeats must be >= 1, got {repeats}")
    require_usd()
    trace = trace or plain_cycle()
    total = sum(lung.n_vertices for lung in model.lungs.values())
    chosen = [f for f in FORMATS if not f[2] or total <= baked_max_vertices]
    seconds = {name: [] for name, _, _ in chosen}
    sizes = {}
    with tempfile.TemporaryDirectory(prefix="lungdeform-bench-export-") as tmp:
        for _ in range(repeats):
            for name, suffix, baked in chosen:
                path = Path(tmp) / f"{name.replace(' --', '_')}{suffix}"
                t0 = time.perf_counter()
                _write(model, path, trace, baked)
                seconds[name].append(time.perf_counter() - t0)
                sizes[name] = path.stat().st_size
                path.unlink()
    glb_bytes, glb_s = sizes["glb"], float(np.median(seconds["glb"]))
    formats = {name: {"bytes": sizes[name], "seconds": float(np.median(s)), "seconds_all": s,
                      "bytes_ratio_to_glb": sizes[name] / glb_bytes,
                      "seconds_ratio_to_glb": float(np.median(s)) / glb_s} for name, s in seconds.items()}
    return {"model": label, "vertices": total, "frames": len(usd_frames(trace).t_s), "curve": trace.source,
            "formats": formats}
