"""Baselines the fitted model is compared with, and the shared metrics (issue 3, item 6).

Every method here, like the model, maps the end-exhale mesh vertices ``p (n, 3)`` mm to predicted
vertices at the larger volume (same faces), all in the end-exhale scan's frame after the rigid
alignment. :func:`measure` then applies the same metrics to every method: exact symmetric surface
distance to the target surface (area weighted; crop faces optionally left out) and landmark error
after moving the end-exhale landmarks by the thin-plate-spline interpolation of the method's
surface displacement (:mod:`lungdeform.interpolate`).

Baselines:

- :func:`no_motion`: the end-exhale surface itself (after the rigid alignment);
- :func:`affine_fit`: the best affine map (12 parameters) by symmetric iterative closest points;
- :func:`apex_scaling`: uniform scaling about the apex by ``(V / V_EE)^(1/3)`` (exact volume);
- :func:`cpd_deformable`: non-physical deformable surface registration, Coherent Point Drift
  (Myronenko & Song 2010) via ``pycpd`` (MIT), on coordinates normalised to unit RMS radius,
  beta = 2, alpha = 2 (beta 0.2–1 gave tangential sliding of 15–30 mm on the ITK pair).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .distance import SurfaceDistance, symmetric_distance
from .errors import ConvergenceError, InputError, require
from .interpolate import displacement_field
from .mesh import Surface, as_vertices


def no_motion(surface: Surface) -> np.ndarray:
    """``(n, 3)`` mm: the end-exhale vertices unchanged."""
    return np.array(surface.vertices)


def apex_scaling(surface: Surface, volume_ml: float, apex=None) -> np.ndarray:
    """``(n, 3)`` mm: ``surface`` scaled about its apex so that it encloses ``volume_ml``.

    ``apex : (3,)`` mm defaults to the highest vertex (largest LPS z).
    """
    if not volume_ml > 0:
        raise InputError(f"volume_ml must be > 0 mL, got {volume_ml!r}")
    a = surface.vertices[np.argmax(surface.vertices[:, 2])] if apex is None else np.asarray(apex, float)
    factor = (float(volume_ml) / surface.volume_ml) ** (1.0 / 3.0)
    return a + factor * (surface.vertices - a)


def _affine_lsq(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray:
    h = np.hstack([src, np.ones((len(src), 1))])
    sw = np.sqrt(w)[:, None]
    m, *_ = np.linalg.lstsq(h * sw, dst * sw, rcond=None)
    return m  # (4, 3): x' = [x 1] @ m


def affine_fit(surface: Surface, target: Surface, *, keep=None, keep_target=None,
               samples: int = 6000, iterations: int = 100, tol_mm: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """Best affine map of ``surface`` onto ``target`` (symmetric ICP with exact closest points).

    Returns ``(predicted vertices (n, 3) mm, matrix (4, 4))``. Each iteration pairs the moved
    source vertices with their closest target points and target samples with their closest
    points on the moved source (mapped back through barycentric coordinates), then solves the
    12-parameter least squares.
    """
    p = surface.vertices
    ks = np.ones(len(p), bool) if keep is None else np.asarray(keep, bool)
    kt = np.ones(target.n_vertices, bool) if keep_target is None else np.asarray(keep_target, bool)
    idx = np.nonzero(kt)[0]
    if len(idx) > samples:
        idx = np.sort(np.random.default_rng(0).choice(idx, samples, replace=False))
    tpts = target.vertices[idx]
    tdist = SurfaceDistance(target.vertices, target.faces)
    m = np.vstack([np.eye(3), np.zeros((1, 3))])
    last = np.inf
    for _ in range(iterations):
        cur = np.hstack([p, np.ones((len(p), 1))]) @ m
        _, c1, _ = tdist.query(cur[ks])
        sd = SurfaceDistance(cur, surface.faces)
        d2, c2, face = sd.query(tpts)
        # source point (end-exhale) behind each closest point: barycentric on the moved face
        src2 = _barycentric_source(cur, p, surface.faces, face, c2)
        src = np.vstack([p[ks], src2])
        dst = np.vstack([c1, tpts])
        w = np.concatenate([np.full(int(ks.sum()), 1.0 / max(ks.sum(), 1)), np.full(len(tpts), 1.0 / len(tpts))])
        m = _affine_lsq(src, dst, w)
        err = float(np.sqrt(np.average(np.concatenate([np.linalg.norm(c1 - cur[ks], axis=1), d2]) ** 2, weights=w)))
        if abs(last - err) < tol_mm:
            break
        last = err
    mat = np.eye(4)
    mat[:3, :3] = m[:3].T
    mat[:3, 3] = m[3]
    return np.hstack([p, np.ones((len(p), 1))]) @ m, mat


def _barycentric_source(moved, rest, faces, face, points):
    a, b, c = (moved[faces[face, k]] for k in range(3))
    v0, v1, v2 = b - a, c - a, points - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-18, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    u = 1.0 - v - w
    ra, rb, rc = (rest[faces[face, k]] for k in range(3))
    return u[:, None] * ra + v[:, None] * rb + w[:, None] * rc


def cpd_deformable(surface: Surface, target: Surface, *, samples: int = 1500, alpha: float = 2.0,
                   beta: float = 2.0, w: float = 0.05, max_iterations: int = 100, tolerance: float = 1e-5,
                   seed: int = 0) -> np.ndarray:
    """Coherent Point Drift (deformable) of the end-exhale vertices onto the target surface.

    ``samples`` random vertices of each surface are registered (CPD is O(N·M) per iteration); the
    fitted Gaussian-kernel displacement ``G(y, Y_s) W`` is then evaluated at every vertex.
    Coordinates are centred on the source and scaled by its RMS radius, so ``beta`` (kernel width)
    is relative to the lung size (2 = twice the RMS radius, the usual CPD setting on unit-variance data); ``alpha`` is the smoothness
    weight and ``w`` the outlier weight (pycpd's meanings). Returns ``(n, 3)`` mm.
    """
    pycpd = require("pycpd", "the CPD baseline", "pycpd")
    from scipy.spatial.distance import cdist

    rng = np.random.default_rng(seed)
    p = surface.vertices
    c = p.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1))))
    ys = np.sort(rng.choice(len(p), min(samples, len(p)), replace=False))
    xs = np.sort(rng.choice(target.n_vertices, min(samples, target.n_vertices), replace=False))
    x = (target.vertices[xs] - c) / scale
    y = (p[ys] - c) / scale
    reg = pycpd.DeformableRegistration(X=x, Y=y, alpha=alpha, beta=beta, w=w,
                                       max_iterations=max_iterations, tolerance=tolerance)
    reg.register()
    g = np.exp(-cdist((p - c) / scale, y, "sqeuclidean") / (2.0 * beta**2))
    moved = c + scale * ((p - c) / scale + g @ reg.W)
    if not np.all(np.isfinite(moved)):
        raise ConvergenceError("CPD produced non-finite points")
    return moved


@dataclass(frozen=True)
class MethodMetrics:
    """Metrics of one method (mm)."""

    surface_mean_mm: float
    surface_rms_mm: float
    surface_p95_mm: float
    surface_max_mm: float
    surface_mean_all_mm: float
    landmark_mean_mm: float
    landmark_max_mm: float
    landmark_rms_mm: float

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def measure(rest: Surface, predicted, target: Surface, *, keep=None, keep_target=None,
            landmarks=None, landmarks_target=None, target_distance: SurfaceDistance | None = None):
    """Metrics of a predicted surface and its interpolated landmark motion.

    Parameters
    ----------
    rest : Surface
        End-exhale surface (the model mesh), mm.
    predicted : (n, 3) float
        Predicted vertices at the target volume, mm (faces of ``rest``).
    target : Surface
        Observed surface at that volume, aligned, mm.
    keep, keep_target : (n,), (n_target,) bool
        Vertices measured (e.g. the crop face left out); ``surface_mean_all_mm`` uses all.
    landmarks, landmarks_target : (k, 3) float
        End-exhale landmarks and their observed positions at the target volume (aligned), mm.

    Returns ``(MethodMetrics, per-vertex distance of predicted to target (n,), landmark errors (k,))``.
    """
    x = as_vertices(predicted, "predicted")
    if x.shape != rest.vertices.shape:
        raise InputError(f"predicted must have shape {rest.vertices.shape}, got {x.shape}")
    pred = Surface(x, rest.faces, "predicted")
    td = target_distance or SurfaceDistance(target.vertices, target.faces)
    sym = symmetric_distance(pred, target, keep_a=keep, keep_b=keep_target, b_distance=td)
    all_ = symmetric_distance(pred, target, b_distance=td)
    per_vertex = td.distance(x)
    lm_err = np.zeros(0)
    if landmarks is not None:
        field = displacement_field(rest.vertices, x - rest.vertices)
        lm_err = np.linalg.norm(field.move(landmarks) - as_vertices(landmarks_target, "landmarks_target"), axis=1)
    st = sym.stats
    nan = float("nan")
    m = MethodMetrics(st.mean, st.rms, st.p95, st.max, all_.stats.mean,
                      float(lm_err.mean()) if len(lm_err) else nan, float(lm_err.max()) if len(lm_err) else nan,
                      float(np.sqrt(np.mean(lm_err**2))) if len(lm_err) else nan)
    return m, per_vertex, lm_err
