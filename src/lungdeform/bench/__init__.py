"""Benchmarks, each reported as a ratio against a yardstick measured in the same run.

Owns: :mod:`~lungdeform.bench.kernels` (the force solve: push loop against the sparse solve; playback
against a memory copy of the same bytes).

May import: everything below it (:mod:`lungdeform.cohort`, :mod:`lungdeform.playback`, …); never the CLI.
"""

from .kernels import bench_playback, bench_solve, lung_with_vertices

__all__ = [
    "bench_playback",
    "bench_solve",
    "lung_with_vertices",
]
