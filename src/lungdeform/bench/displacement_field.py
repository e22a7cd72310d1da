"""``lungdeform bench dvf``: a displacement-field image against a plain trilinear resampling.

The model of the embedded lungs (:func:`lungdeform.data.default_lungs`, Table I, supine) on a CT-sized
grid (512 × 512 × 150 voxels by default, 0.8 × 0.8 × 2.5 mm about the lungs): the forward field at
end-inhale of a tidal breath (:func:`lungdeform.playback.displacement_field.displacement_field`) and, as the
yardstick in the same run, SimpleITK's linear resampling of a float32 image of that grid through a
rigid shift. The ratio of the two median times is the figure (docs/RADIOTHERAPY.md); the ratio of
their CPU times (the process's, every thread) is recorded beside it, as the figure on a loaded
machine, where the wall times of both grow with the load. Both run on the same number of threads by
default (SimpleITK's global default and numba's, each the number of cores; ``threads`` and
``field_threads`` record them).
"""

from __future__ import annotations

import time

import numba
import numpy as np
import SimpleITK as sitk

from lungdeform.constants import TIDAL_VOLUME_ML
from lungdeform.data import default_lungs
from lungdeform.errors import InputError
from lungdeform.model.lung import build_model
from lungdeform.playback import displacement_field as D


def bench_grid(model, shape=(150, 512, 512), spacing=(0.8, 0.8, 2.5)) -> D.Grid:
    """A grid of ``shape`` (z, y, x) voxels of ``spacing`` (x, y, z) mm centred on the model's lungs."""
    v = np.concatenate([lung.surface.vertices for lung in model.lungs.values()])
    sp = np.asarray(spacing, float)
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    origin = centre - sp * (np.array(shape[::-1]) - 1) / 2
    return D.Grid(tuple(int(n) for n in shape), sp, origin, np.eye(3))


def _median_time(fn, repeats: int) -> tuple[float, float]:
    """The medians over ``repeats`` calls of ``fn`` after one untimed warm-up call (the field's first
    call loads the compiled kernels and builds the tapered prior's depth grids, once a model): wall
    seconds, and the process's CPU seconds (every thread: user + system; a thread waiting for a busy
    core costs none)."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def bench_dvf(shape=(150, 512, 512), repeats: int = 3, node_mm: float = D.NODE_SPACING_MM) -> dict:
    """Median seconds of the forward field and of the trilinear resampling on the same grid (wall, and
    CPU of the process), their ratios, the field's Jacobian range, margin and lattice size."""
    if repeats < 1 or len(shape) != 3 or min(shape) < 2:
        raise InputError(f"need repeats >= 1 and a 3-D shape of at least 2 voxels a side, got {repeats}, {shape}")
    model = build_model(default_lungs())
    grid = bench_grid(model, shape)
    out = {}
    field, field_cpu = _median_time(lambda: out.setdefault("r", D.displacement_field(model, grid, TIDAL_VOLUME_ML,
                                                                          spacing_mm=node_mm)), repeats)
    img = sitk.GetImageFromArray(np.random.default_rng(0).normal(size=grid.shape).astype(np.float32))
    img.SetSpacing(grid.spacing.tolist())
    img.SetOrigin(grid.origin.tolist())
    shift = sitk.TranslationTransform(3, (1.3, -0.7, 2.1))
    resample, resample_cpu = _median_time(lambda: sitk.Resample(img, img, shift, sitk.sitkLinear, 0.0), repeats)
    r = out["r"]
    return {"shape_zyx": list(grid.shape), "spacing_mm": grid.spacing.tolist(), "field_seconds": field,
            "resample_seconds": resample, "ratio": field / resample, "field_cpu_seconds": field_cpu,
            "resample_cpu_seconds": resample_cpu, "cpu_ratio": field_cpu / resample_cpu, "jacobian_min": r.jacobian_min,
            "jacobian_max": r.jacobian_max, "margin_mm": r.info["margin_mm"], "nodes": r.info["nodes"],
            "nodes_evaluated": r.info["nodes_evaluated"], "lattice_error_mm": r.info["lattice_error_mm"],
            "node_mm": float(node_mm), "threads": sitk.ProcessObject.GetGlobalDefaultNumberOfThreads(),
            "field_threads": numba.get_num_threads()}
