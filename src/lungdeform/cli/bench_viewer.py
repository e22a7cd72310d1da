"""``lungdeform bench viewer --vertices N``: frame time of the browser viewer at N vertices (both
lungs together), GPU morph path against the CPU path, beside lungdeform's own CPU playback step
(:mod:`lungdeform.bench.viewer`).

Needs node, viewer/node_modules (npm ci in viewer/) and Chromium (software GL unless CHROMIUM_GL names
a hardware ANGLE backend).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lungdeform.atomic import write_json
from lungdeform.bench.viewer import check_viewer_tools, model_with_vertices, run_browser_bench, viewer_record
from lungdeform.errors import InputError

from .common import say

REPO_VIEWER = Path(__file__).resolve().parents[3] / "viewer"


def _print(row: dict) -> None:
    run = row["viewer"]
    typer.echo(f"{row['vertices']:>9} vertices, glb {row['glb_bytes'] / 1e6:.1f} MB, renderer "
               f"{run['runs'][0]['info']['renderer']}:")
    for r in run["runs"]:
        b = r["bench"]
        typer.echo(f"  viewer {r['deform'].upper()}: frame {b['frameMs']['median']:.1f} ms median "
                   f"(p95 {b['frameMs']['p95']:.1f}), per-frame CPU deform {b['deformCpuMs']['median'] * 1e3:.1f} µs, "
                   f"real-time {r['realtime']['fps']:.1f} fps, load {r['loadS']:.1f} s")
    typer.echo(f"  python CPU playback step (x += Δs·u, float32, numpy): {row['cpu_playback_step_ms']:.3f} ms "
               f"({row['cpu_playback_ratio_to_memcpy']:.2f}× memcpy)")


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
        check_viewer_tools(viewer_dir)
        if frames < 1:
            raise InputError(f"--frames must be ≥ 1, got {frames}")
        results = []
        for n in vertices:
            model = model_with_vertices(n, say)
            row = viewer_record(model, lambda glb, n=n: run_browser_bench(glb, viewer_dir, frames, size, vertices=n),
                                progress=say)
            results.append(row)
            _print(row)
        if json_path:
            write_json(json_path, {"benchmark": "viewer", "size": size, "frames": frames, "results": results})
            typer.echo(f"results written to {json_path}")
