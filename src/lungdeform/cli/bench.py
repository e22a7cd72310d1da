"""``lungdeform bench solve|playback --vertices N [--vertices N …] --json FILE`` and ``bench predict``."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lungdeform.bench.kernels import bench_playback, bench_solve, lung_with_vertices
from lungdeform.bench.prediction import bench_predict
from lungdeform.breathing.stream import MAX_PREDICT_MS
from lungdeform.errors import InputError

from .common import bounded, say, write_bench_json


def _surfaces(vertices: list[int]):
    for n in vertices:
        if n < 100:
            raise InputError(f"--vertices must be at least 100, got {n}")
        say(f"preparing a subdivided real lung with about {n} vertices")
        yield lung_with_vertices(n)


def register(apps) -> None:
    @apps.bench.command("solve")
    def solve(
        vertices: list[int] = typer.Option([10_000], "--vertices", "-n", help="Vertex counts (repeat the option)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write results here."),
        push_max: int = typer.Option(200_000, "--push-max-vertices", help="Skip the push loop above this size."),
        push_tol: float = typer.Option(1e-8, "--push-tol", callback=bounded(0, 1, low_open=True), help="Push loop stops at max|P| ≤ tol·max|f|."),
    ):
        """Push loop (the paper's algorithm) against the sparse solve of its fixed point."""

        results = []
        for s in _surfaces(vertices):
            rows = bench_solve(s, include_push=s.n_vertices <= push_max, push_tol=push_tol)
            results += rows
            sparse = rows[0]
            line = (f"{s.n_vertices:>9} vertices ({sparse['graph_nodes']} nodes): sparse "
                    f"{sparse['seconds']:.3f} s ({sparse['iterations']} it)")
            if len(rows) > 1:
                p = rows[1]
                line += (f", push {p['seconds']:.3f} s ({p['pushes']} pushes), push/sparse "
                         f"{p['seconds'] / sparse['seconds']:.1f}×, max diff {p['max_relative_difference_to_sparse']:.1e}")
            typer.echo(line)
        if json_path:
            write_bench_json(json_path, results, "solve")
            typer.echo(f"results written to {json_path}")

    @apps.bench.command("playback")
    def playback(
        vertices: list[int] = typer.Option([10_000], "--vertices", "-n", help="Vertex counts (repeat the option)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write results here."),
        frames: int = typer.Option(200, "--frames", help="Frames timed per size (median reported)."),
    ):
        """Per-frame playback (x += Δs·u, float32) against a memcpy of the same bytes."""

        results = []
        for s in _surfaces(vertices):
            rows = bench_playback(s, frames=frames)
            results += rows
            p, m = rows
            typer.echo(f"{s.n_vertices:>9} vertices: playback {p['seconds'] * 1e3:.3f} ms/frame "
                       f"({p['frames_per_second']:.0f} fps), memcpy {m['seconds'] * 1e3:.3f} ms, "
                       f"ratio {p['ratio_to_memcpy']:.2f}")
        if json_path:
            write_bench_json(json_path, results, "playback")
            typer.echo(f"results written to {json_path}")

    @apps.bench.command("predict")
    def predict(
        seconds: float = typer.Option(300.0, "--seconds", callback=bounded(0, 86400, "s", low_open=True), help="Length of the synthetic stream (s)."),
        rate_hz: float = typer.Option(100.0, "--rate-hz", callback=bounded(0, 10000, "Hz", low_open=True), help="Samples per second."),
        horizon_ms: float = typer.Option(400.0, "--horizon-ms", callback=bounded(0, MAX_PREDICT_MS, "ms", low_open=True), help="Prediction horizon (ms)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write results here."),
    ):
        """Cost per sample of the breathing predictor against the linear baseline and the 100 Hz budget."""

        say(f"streaming {seconds:g} s of a synthetic breath at {rate_hz:g} Hz through each predictor")
        rows = bench_predict(seconds, rate_hz, horizon_ms)
        for r in rows:
            typer.echo(f"{r['method']:>15}: {r['seconds'] * 1e6:8.1f} µs/sample median (p99 "
                       f"{r['p99_seconds'] * 1e6:.1f} µs), ×{r['ratio_to_linear']:.2f} the linear baseline, "
                       f"{100 * r['budget_fraction']:.2f} % of the {1000 / r['rate_hz']:g} ms between samples")
        if json_path:
            write_bench_json(json_path, rows, "predict")
            typer.echo(f"results written to {json_path}")
