"""``lungdeform bench viewer --vertices N``: frame time of the browser viewer at N vertices (both
lungs together), GPU morph path against the CPU path, beside lungdeform's own CPU playback step.

Needs node, viewer/node_modules (npm ci in viewer/) and Chromium (software GL unless CHROMIUM_GL names
a hardware ANGLE backend). The model is the embedded pair of real lungs, built once, then
midpoint-subdivided (surface and per-vertex model data interpolated alike) to reach N.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lungdeform.atomic import write_json
from lungdeform.bench.kernels import bench_playback
from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.geometry.mesh import Surface, subdivide, unique_edges
from lungdeform.geometry.remesh import decimate
from lungdeform.model.lung import Model, build_lung
from lungdeform.playback.export import glb_bytes
from lungdeform.playback.server import ViewerServer

from .common import say

REPO_VIEWER = Path(__file__).resolve().parents[3] / "viewer"


def upsampled(lung, levels: int):
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


def model_with_vertices(total: int, say):
    """Two real lungs with about ``total`` vertices together."""



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


def register(apps) -> None:
    @apps.bench.command("viewer")
    def viewer_command(
        vertices: list[int] = typer.Option([100_000], "--vertices", "-n", help="Total vertex counts (repeat the option)."),
        frames: int = typer.Option(30, "--frames", help="Synced frames timed per size and path."),
        size: str = typer.Option("960x640", "--size", help="Viewport WIDTHxHEIGHT (CSS px)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write results here."),
        viewer_dir: Path = typer.Option(REPO_VIEWER, "--viewer-dir", help="viewer/ with node_modules installed."),
    ):
        """Viewer frame time (GPU morph targets vs CPU blending) and the CPU playback step, per size."""



        for n in vertices:
            if n < 1000:
                raise InputError(f"--vertices must be at least 1000, got {n}")
        script = viewer_dir / "scripts" / "bench-viewer.mjs"
        if shutil.which("node") is None or not (viewer_dir / "node_modules" / "playwright-core").is_dir():
            raise InputError(f"{viewer_dir}: bench viewer needs node and 'npm ci' in viewer/ (playwright-core)")
        if not script.is_file():
            raise InputError(f"{script}: missing")
        if frames < 1:
            raise InputError(f"--frames must be ≥ 1, got {frames}")
        results = []
        for n in vertices:
            model = model_with_vertices(n, say)
            glb = glb_bytes(model)
            total = sum(l.n_vertices for l in model.lungs.values())
            v = np.vstack([l.surface.vertices for l in model.lungs.values()])
            playback = bench_playback(Surface(v, model.lungs["left"].surface.faces, "both"), frames=50)[0]
            say(f"{total} vertices: glb {len(glb) / 1e6:.1f} MB; running Chromium")
            with ViewerServer(glb) as server:
                res = subprocess.run(["node", str(script), server.url, str(frames), size], cwd=viewer_dir,
                                     capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=1800)
            lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
            if res.returncode != 0 or not lines:
                raise InputError(f"viewer benchmark failed at {n} vertices: {res.stderr.strip()[-500:]}")
            run = json.loads(lines[-1])
            row = {"vertices": total, "glb_bytes": len(glb), "cpu_playback_step_ms": playback["seconds"] * 1e3,
                   "cpu_playback_ratio_to_memcpy": playback["ratio_to_memcpy"], "viewer": run}
            results.append(row)
            typer.echo(f"{total:>9} vertices, glb {len(glb) / 1e6:.1f} MB, renderer "
                       f"{run['runs'][0]['info']['renderer']}:")
            for r in run["runs"]:
                b = r["bench"]
                typer.echo(f"  viewer {r['deform'].upper()}: frame {b['frameMs']['median']:.1f} ms median "
                           f"(p95 {b['frameMs']['p95']:.1f}), per-frame CPU deform {b['deformCpuMs']['median'] * 1e3:.1f} µs, "
                           f"real-time {r['realtime']['fps']:.1f} fps, load {r['loadS']:.1f} s")
            typer.echo(f"  python CPU playback step (x += Δs·u, float32, numpy): {playback['seconds'] * 1e3:.3f} ms "
                       f"({playback['ratio_to_memcpy']:.2f}× memcpy)")
        if json_path:
            write_json(json_path, {"benchmark": "viewer", "size": size, "frames": frames, "results": results})
            typer.echo(f"results written to {json_path}")
