"""Benchmarks, each reported as a ratio against a yardstick measured in the same run.

Owns: :mod:`~lungdeform.bench.kernels` (the force solve: push loop against the sparse solve; playback
against a memory copy of the same bytes), :mod:`~lungdeform.bench.cohort` (cohort-fit throughput:
a serial loop against Dask at each worker count) and :mod:`~lungdeform.bench.viewer` (models of N
vertices, the browser viewer's frame time beside the CPU playback step) and :mod:`~lungdeform.bench.displacement_field`
(a displacement-field image against a trilinear resampling of the same grid),
:mod:`~lungdeform.bench.export` (the OpenUSD / USDZ exports' bytes and seconds against the glb's) and
:mod:`~lungdeform.bench.fit` (the model's fit of a two-volume subject against elastix's Par0011
registration of the same masks).

May import: everything below it (:mod:`lungdeform.cohort`, :mod:`lungdeform.playback`, …); never the CLI.
"""

from .cohort import bench_cohort, make_bench_cohort
from .kernels import bench_playback, bench_solve, lung_with_vertices
from .viewer import model_with_vertices, viewer_record

__all__ = [
    "bench_cohort",
    "bench_playback",
    "bench_solve",
    "lung_with_vertices",
    "make_bench_cohort",
    "model_with_vertices",
    "viewer_record",
]
