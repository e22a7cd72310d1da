"""Benchmarks: the force solve (push loop against sparse solve) and per-frame playback against a
plain memory copy of the same bytes, measured in the same run (machines here are shared and noisy,
so ratios against a yardstick are what to compare).

Each function returns records ``{"vertices": N, "method": …, "seconds": median}`` plus extra keys.
"""

from __future__ import annotations

import statistics
import time
from typing import Callable

import numpy as np

from lungdeform.constants import table_constants
from lungdeform.data import default_lungs
from lungdeform.geometry.frame import lung_frame
from lungdeform.geometry.mesh import Surface, subdivide
from lungdeform.geometry.remesh import decimate
from lungdeform.model.displacement import Playback
from lungdeform.model.force import applied_force
from lungdeform.model.graph import spring_graph
from lungdeform.model.solve import ForceSolver, push
from lungdeform.model.transfer import local_transfer


def lung_with_vertices(target: int, base: Surface | None = None) -> Surface:
    """A real lung surface with about ``target`` vertices: the embedded right lung decimated to
    ``target / 4^k`` vertices, then midpoint-subdivided ``k`` times (each ×4, shape unchanged)."""

    lung = base if base is not None else default_lungs()["right"]
    k = 0
    while target / 4**k > lung.n_vertices:
        k += 1
    v, f = lung.vertices, lung.faces
    want = int(round(target / 4**k))
    if want < lung.n_vertices:
        v, f, _ = decimate(v, f, want)
    for _ in range(k):
        v, f = subdivide(v, f)
    return Surface(v, f, f"{lung.name} ({len(v)} vertices)")


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_solve(surface: Surface, *, push_tol: float = 1e-8, sparse_tol: float = 1e-10,
                include_push: bool = True, repeats: int = 3) -> list[dict]:
    """Time the supine force solve on ``surface`` by the sparse solver and by the push loop."""

    n = surface.n_vertices
    t0 = time.perf_counter()
    graph = spring_graph(surface.vertices, surface.edges)
    t = local_transfer(graph, np.ones(n))
    setup = time.perf_counter() - t0
    f = applied_force(lung_frame(surface.vertices, "right").normalized(surface.vertices),
                      table_constants("right"))
    solver = ForceSolver(t, "bicgstab", n_mass=n, tol=sparse_tol)
    kept = None

    def run_sparse():
        nonlocal kept
        kept = solver.solve(f)

    run_sparse()  # warm-up: the first Krylov call in a process pays a one-off initialisation
    sparse_s = _median_time(run_sparse, repeats)
    out = [{"vertices": n, "method": "sparse", "seconds": sparse_s, "graph_nodes": graph.n_nodes,
            "setup_seconds": setup, "iterations": solver.last_iterations, "tol": sparse_tol}]
    if include_push:
        push(t, f, tol=0.5)  # compile the kernel (first call) outside the timing
        result = {}

        def run_push():
            result["r"] = push(t, f, tol=push_tol)

        push_s = _median_time(run_push, repeats)
        r = result["r"]
        diff = float(np.abs(r.kept - kept).max() / np.abs(kept).max())
        out.append({"vertices": n, "method": "push", "seconds": push_s, "graph_nodes": graph.n_nodes,
                    "pushes": r.pushes, "tol": push_tol, "max_relative_difference_to_sparse": diff})
    return out


def bench_playback(surface: Surface, *, frames: int = 200, dtype=np.float32) -> list[dict]:
    """Per-frame cost of ``x += Δs·u`` (in place) against ``memcpy`` of the same frame bytes."""

    rng = np.random.default_rng(0)
    n = surface.n_vertices
    u = rng.normal(scale=1e-3, size=(n, 3))
    pb = Playback(surface.vertices, u, dtype=dtype)
    pb.set_step(1.5)
    src = pb.positions.copy()
    dst = np.empty_like(src)
    for _ in range(3):  # warm caches and page in the buffers
        pb.step()
        np.copyto(dst, src)
    step_s = _median_time(pb.step, frames)
    copy_s = _median_time(lambda: np.copyto(dst, src), frames)
    nbytes = src.nbytes
    return [
        {"vertices": n, "method": "playback", "seconds": step_s, "bytes_per_frame": nbytes,
         "ratio_to_memcpy": step_s / copy_s, "frames_per_second": 1.0 / step_s},
        {"vertices": n, "method": "memcpy", "seconds": copy_s, "bytes_per_frame": nbytes},
    ]
