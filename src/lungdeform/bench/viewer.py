"""Frame time of the browser viewer at N vertices, beside lungdeform's own CPU playback step.

The model (:func:`model_with_vertices`) is the embedded pair of real lungs, built once on a
decimated surface, then midpoint-subdivided (:func:`upsampled`: surface and per-vertex model data
interpolated alike) to reach N vertices together. :func:`viewer_record` exports it as a glb, times
the CPU playback step on the same vertices against a memory copy (:func:`lungdeform.bench.kernels.bench_playback`,
same run) and hands the glb to a browser run (:func:`run_browser_bench`: node, Playwright and
Chromium on ``viewer/scripts/bench-viewer.mjs``, GPU morph path against the CPU path).

Record: ``vertices`` (both lungs), ``glb_bytes``, ``cpu_playback_step_ms``,
``cpu_playback_ratio_to_memcpy`` and ``viewer`` (the browser script's JSON: ``runs``, one per path).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.geometry.mesh import Surface, subdivide, unique_edges
from lungdeform.geometry.remesh import decimate
from lungdeform.model.lung import LungModel, Model, build_lung
from lungdeform.playback.export import glb_bytes
from lungdeform.playback.server import ViewerServer
from lungdeform.progress import Progress, silent

from .kernels import bench_playback

#: The browser script, relative to the viewer folder.
VIEWER_SCRIPT = Path("scripts") / "bench-viewer.mjs"


def upsampled(lung: LungModel, levels: int) -> LungModel:
    """A lung model on a surface subdivided ``levels`` times: every per-vertex array is linearly
    interpolated at the new edge midpoints, as the positions are (benchmark use: same cost per vertex)."""
    v, f = lung.surface.vertices, lung.surface.faces
    per_vertex = {"stiffness": lung.stiffness[:, None], "directions": lung.directions,
                  "force_basis": lung.force_basis.T, "displacement": lung.displacement}
    for _ in range(levels):
        edges, _ = unique_edges(f)
        per_vertex = {k: np.vstack([a, 0.5 * (a[edges[:, 0]] + a[edges[:, 1]])]) for k, a in per_vertex.items()}
        v, f = subdivide(v, f)
    d = per_vertex["directions"]
    return replace(lung, surface=Surface(v, f, lung.surface.name), stiffness=per_vertex["stiffness"][:, 0].copy(),
                   directions=np.ascontiguousarray(d / np.linalg.norm(d, axis=1, keepdims=True)),
                   force_basis=np.ascontiguousarray(per_vertex["force_basis"].T),
                   displacement=np.ascontiguousarray(per_vertex["displacement"]))


def model_with_vertices(total: int, progress: Progress | None = None) -> Model:
    """Two real lungs with about ``total`` vertices together."""
    say = progress or silent
    lungs = {}
    for side, surf in default_lungs().items():
        want = total / 2
        levels = max(0, math.ceil(math.log(want / surf.n_vertices, 4))) if want > surf.n_vertices else 0
        base = surf
        target = int(round(want / 4**levels))
        if target < surf.n_vertices:
            v, f, _ = decimate(np.array(surf.vertices), np.array(surf.faces), target)  # writable copies
            base = Surface(v, f, surf.name)
        say(f"{side}: model on {base.n_vertices} vertices, subdivided {levels}×")
        lungs[side] = upsampled(build_lung(base, side), levels)
    return Model(lungs, {"source": "lungdeform.data.default_lungs (Coronacases 001), for benchmarking"})


def check_viewer_tools(viewer_dir: Path) -> Path:
    """The browser script of ``viewer_dir``; raises :class:`InputError` when node, Playwright
    (``npm ci`` in the viewer folder) or the script is missing."""
    viewer_dir = Path(viewer_dir)
    script = viewer_dir / VIEWER_SCRIPT
    if shutil.which("node") is None or not (viewer_dir / "node_modules" / "playwright-core").is_dir():
        raise InputError(f"{viewer_dir}: bench viewer needs node and 'npm ci' in viewer/ (playwright-core)")
    if not script.is_file():
        raise InputError(f"{script}: missing")
    return script


def run_browser_bench(glb: bytes, viewer_dir: Path, frames: int, size: str, *, vertices: int | None = None) -> dict:
    """Serve ``glb`` on 127.0.0.1 and run the browser script of ``viewer_dir`` on it (``frames``
    synced frames per path, viewport ``size`` ``WIDTHxHEIGHT``); its last JSON line. ``vertices``
    (the size asked for) is named when the run fails."""
    viewer_dir = Path(viewer_dir)
    with ViewerServer(glb) as server:
        res = subprocess.run(["node", str(viewer_dir / VIEWER_SCRIPT), server.url, str(frames), size], cwd=viewer_dir,
                             capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=1800)
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode != 0 or not lines:
        raise InputError(f"viewer benchmark failed at {vertices} vertices: {res.stderr.strip()[-500:]}")
    return json.loads(lines[-1])


def viewer_record(model: Model, browser: Callable[[bytes], dict], *, playback_frames: int = 50,
                  progress: Progress | None = None) -> dict:
    """One size: the model's glb, the CPU playback step on all its vertices against a memory copy
    (same run), and ``browser(glb)`` (:func:`run_browser_bench` with its settings bound)."""
    say = progress or silent
    glb = glb_bytes(model)
    total = sum(lung.n_vertices for lung in model.lungs.values())
    v = np.vstack([lung.surface.vertices for lung in model.lungs.values()])
    playback = bench_playback(Surface(v, model.lungs["left"].surface.faces, "both"), frames=playback_frames)[0]
    say(f"{total} vertices: glb {len(glb) / 1e6:.1f} MB; running Chromium")
    run = browser(glb)
    return {"vertices": total, "glb_bytes": len(glb), "cpu_playback_step_ms": playback["seconds"] * 1e3,
            "cpu_playback_ratio_to_memcpy": playback["ratio_to_memcpy"], "viewer": run}
