"""lungdeform.bench.kernels: the records of the solve and playback benchmarks (structure and invariants;
timings are never asserted, the machines are shared and noisy)."""

from __future__ import annotations

import numpy as np
import pytest

from lungdeform.bench.kernels import bench_playback, bench_solve, lung_with_vertices
from lungdeform.data import default_lungs


def test_lung_with_vertices_reaches_about_the_target():
    # truth: decimation to target/4^k then k midpoint subdivisions, each V → 4V − 6 on a closed surface
    base = default_lungs()["right"]
    small = lung_with_vertices(500)
    assert abs(small.n_vertices - 500) <= 5 and small.n_vertices < base.n_vertices
    big = lung_with_vertices(4 * base.n_vertices - 6)  # one subdivision of the whole lung, no decimation
    assert big.n_vertices == 4 * base.n_vertices - 6
    assert big.volume == pytest.approx(base.volume, rel=0.05)  # midpoints on the flat faces: a little less


def test_playback_record_is_a_ratio_to_memcpy_of_the_same_run():
    # truth: both records come from one call; the ratio is the playback median over the memcpy median,
    # the frame is n·3 floats (float32: 4 bytes, float64: 8)
    s = lung_with_vertices(300)
    for dtype, size in ((np.float32, 4), (np.float64, 8)):
        rows = bench_playback(s, frames=3, dtype=dtype)
        assert [r["method"] for r in rows] == ["playback", "memcpy"]
        play, copy = rows
        assert play["vertices"] == copy["vertices"] == s.n_vertices
        assert play["bytes_per_frame"] == copy["bytes_per_frame"] == s.n_vertices * 3 * size
        assert play["ratio_to_memcpy"] == play["seconds"] / copy["seconds"]
        assert play["frames_per_second"] == 1.0 / play["seconds"]


def test_solve_records_compare_push_with_sparse():
    # truth: the push loop converges to the sparse solve's fixed point (tolerance 1e-8 of the force);
    # without the push loop only the sparse record is made
    s = lung_with_vertices(300)
    rows = bench_solve(s, repeats=1)
    assert [r["method"] for r in rows] == ["sparse", "push"]
    sparse, push = rows
    assert sparse["vertices"] == push["vertices"] == s.n_vertices
    assert sparse["graph_nodes"] == push["graph_nodes"] >= s.n_vertices
    assert sparse["iterations"] > 0 and push["pushes"] > 0
    assert push["max_relative_difference_to_sparse"] < 1e-6
    only = bench_solve(s, include_push=False, repeats=1)
    assert [r["method"] for r in only] == ["sparse"]
