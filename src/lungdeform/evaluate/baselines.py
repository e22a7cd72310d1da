"""Baselines the fitted model is compared with, and the shared metrics (the rows of ``metrics.json``).

Every method here, like the model, maps the end-exhale mesh vertices ``p (n, 3)`` mm to predicted
vertices at the larger volume (same faces), all in the end-exhale scan's frame after the rigid
alignment. Each surface baseline aligns itself (since 0.8): it fits its own translation by iterative
closest points started from the kept vertices' centroids (:func:`best_translation`; the affine fit's
own twelve parameters include one), so it does not start from the alignment the model's fit chose
(``--align joint`` fits a translation with the model's constants). :func:`measure` then applies the
same metrics to every method: exact symmetric surface distance to the target surface (area
weighted; crop faces optionally left out) and landmark error after moving the end-exhale landmarks
by the sliding interpolation of the method's surface displacement at the kept vertices
(:mod:`lungdeform.interior.sliding`: the smoothest field with the surface's normal motion, which
reproduces a translation exactly; one operator, :func:`landmark_matrix`, shared by all methods),
or, for landmark-informed methods, from their held-out predictions.

Landmark-informed references (used only when corresponding landmarks are given, and scored on
landmarks held out from their fit, k-fold, with the same folds as the landmark-informed model):

- :func:`affine_landmarks_cv`: the affine fit with the training landmarks added to its least
  squares (same weighting as the model's objective: surface mean square + landmark mean square);
- :func:`landmark_tps_cv`: no surface at all, the thin-plate spline through the training
  landmarks' displacements (what the landmarks alone predict), its smoothing chosen, like the
  model's landmark correction's, by cross-validation inside the training landmarks (since 0.8;
  until then none).

Baselines:

- :func:`no_motion`: the end-exhale surface itself, moved by its own best translation;
- :func:`affine_fit`: the best affine map (12 parameters) by symmetric iterative closest points;
- :func:`apex_scaling`: uniform scaling about the apex by ``(V / V_EE)^(1/3)`` (exact volume), then
  its own best translation;
- :func:`cpd_deformable`: non-physical deformable surface registration, Coherent Point Drift
  (Myronenko & Song 2010) on coordinates normalised to unit RMS radius, beta = 2, alpha = 2 (beta
  0.2–1 gave tangential sliding of 15–30 mm on the ITK pair), after its own best translation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial.distance import cdist
from skimage.measure import marching_cubes

from lungdeform.errors import ConvergenceError, InputError
from lungdeform.fit import registration
from lungdeform.fit.cpd import deformable_cpd
from lungdeform.geometry.distance import SurfaceDistance, barycentric, symmetric_distance
from lungdeform.geometry.mesh import Surface, as_vertices, farthest_points, thinned
from lungdeform.interior.interpolate import interpolation_weights
from lungdeform.interior.sliding import surface_weights

from .folds import select_smoothing


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


@dataclass(frozen=True)
class IcpSettings:
    """The ICP of the affine baseline and of every baseline's own translation (:func:`affine_fit`,
    :func:`best_translation`): ``samples`` target points, at most ``iterations`` iterations,
    stopping when the objective improves by less than ``tol_mm``."""

    samples: int = 6000
    iterations: int = 100
    tol_mm: float = 1e-5


@dataclass(frozen=True)
class CpdSettings:
    """The CPD baseline (:func:`cpd_deformable`): ``samples`` vertices of each surface (drawn with
    ``seed``); pycpd's ``alpha`` (smoothness), ``beta`` (kernel width, relative to the lung's RMS
    radius), ``w`` (outlier weight), ``max_iterations`` and ``tolerance``.

    ``beta`` and ``w`` were searched leave one subject out on the 10 DIR-Lab COPDgene lungs, as the
    model's settings were (docs/FITTING.md "DIR-Lab COPDgene, five subjects"):
    ``scripts/tune_cpd_baseline.py --data $LUNGDEFORM_DATA/dirlab-copd-lung-masks --out cpd_search.json``,
    β ∈ {1, 2, 4, 8, 16, 32, 64, 128} × w ∈ {0, 0.05}. The folds picked β 32 (three of five cases, w 0 in
    two of them), β 8 and β 4; β 32, w 0 is that majority (until 0.8 pycpd's usual β 2, w 0.05)."""

    samples: int = 1500
    alpha: float = 2.0
    beta: float = 32.0
    w: float = 0.0
    max_iterations: int = 100
    tolerance: float = 1e-5
    seed: int = 0


def _translation_lsq(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray:
    m = np.vstack([np.eye(3), np.zeros((1, 3))])
    m[3] = np.average(dst - src, axis=0, weights=w)
    return m  # (4, 3): x' = [x 1] @ m


def _kept(n: int, keep) -> np.ndarray:
    return np.ones(n, bool) if keep is None else np.asarray(keep, bool)


def _icp(surface: Surface, target: Surface, icp: IcpSettings, kept, lm_pairs, solve) -> np.ndarray:
    """Symmetric ICP with exact closest points from the kept vertices' centroids: the ``(4, 3)`` map
    ``x' = [x 1] @ m`` that ``solve(src, dst, weights)`` fits (affine or translation). ``kept``: the
    ``(keep, keep_target)`` masks; ``lm_pairs``: ``(landmarks, targets, weight)`` joining the least squares."""
    p = surface.vertices
    ks, kt = kept
    idx = np.nonzero(kt)[0]
    idx = idx[thinned(len(idx), icp.samples)]
    tpts = target.vertices[idx]
    tdist = SurfaceDistance(target.vertices, target.faces)
    lm_src, lm_dst, landmark_weight = lm_pairs
    m = np.vstack([np.eye(3), target.vertices[kt].mean(axis=0) - p[ks].mean(axis=0)])  # centroids together
    last = np.inf
    for _ in range(icp.iterations):
        cur = np.hstack([p, np.ones((len(p), 1))]) @ m
        _, c1, _ = tdist.query(cur[ks])
        sd = SurfaceDistance(cur, surface.faces)
        d2, c2, face = sd.query(tpts)
        # source point (end-exhale) behind each closest point: barycentric on the moved face
        src2 = _barycentric_source(cur, p, surface.faces, face, c2)
        src = np.vstack([p[ks], src2, lm_src])
        dst = np.vstack([c1, tpts, lm_dst])
        w = np.concatenate([np.full(int(ks.sum()), 0.5 / max(ks.sum(), 1)), np.full(len(tpts), 0.5 / len(tpts)),
                            np.full(len(lm_src), float(landmark_weight) / max(len(lm_src), 1))])
        m = solve(src, dst, w)
        err = float(np.sqrt(np.average(np.concatenate([np.linalg.norm(c1 - cur[ks], axis=1), d2]) ** 2,
                                       weights=w[: len(c1) + len(d2)])))
        if abs(last - err) < icp.tol_mm:
            break
        last = err
    return m


def best_translation(surface: Surface, target: Surface, icp: IcpSettings = IcpSettings(), *, keep=None,
                     keep_target=None) -> np.ndarray:
    """``(3,)`` mm: the translation of ``surface`` onto ``target`` by symmetric ICP (exact closest
    points, both ways, crop faces left out by ``keep``/``keep_target``), started from the kept
    vertices' centroids: a baseline's own alignment, whatever frame the two arrive in."""
    kept = (_kept(surface.n_vertices, keep), _kept(target.n_vertices, keep_target))
    return _icp(surface, target, icp, kept, (np.zeros((0, 3)), np.zeros((0, 3)), 0.0), _translation_lsq)[3].copy()


def self_aligned(surface: Surface, predicted, target: Surface, *, keep=None, keep_target=None,
                 icp: IcpSettings = IcpSettings()) -> np.ndarray:
    """``(n, 3)`` mm: a baseline's ``predicted`` vertices (``surface``'s faces) moved by their own
    :func:`best_translation` onto ``target``."""
    x = as_vertices(predicted, "predicted")
    moved = Surface(x, surface.faces, surface.name)
    return x + best_translation(moved, target, icp, keep=keep, keep_target=keep_target)


def affine_fit(surface: Surface, target: Surface, icp: IcpSettings = IcpSettings(), *, keep=None, keep_target=None,
               landmarks=None, landmarks_target=None, landmark_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Best affine map of ``surface`` onto ``target`` (symmetric ICP with exact closest points, ``icp``,
    started from the kept vertices' centroids).

    Returns ``(predicted vertices (n, 3) mm, matrix (4, 4))``. Each iteration pairs the moved
    source vertices with their closest target points and target samples with their closest
    points on the moved source (mapped back through barycentric coordinates), then solves the
    12-parameter least squares. With ``landmarks`` / ``landmarks_target : (m, 3)`` mm the
    landmark pairs join the least squares: the objective is the mean of the two one-sided surface
    mean squares plus ``landmark_weight`` × the landmark mean square (the model's weighting).
    """
    p = surface.vertices
    if landmarks is not None:
        lm_src = as_vertices(landmarks, "landmarks")
        lm_dst = as_vertices(landmarks_target, "landmarks_target")
        if lm_src.shape != lm_dst.shape:
            raise InputError(f"landmarks {lm_src.shape} and landmarks_target {lm_dst.shape} must correspond row by row")
    else:
        lm_src = lm_dst = np.zeros((0, 3))
    kept = (_kept(len(p), keep), _kept(target.n_vertices, keep_target))
    m = _icp(surface, target, icp, kept, (lm_src, lm_dst, landmark_weight), _affine_lsq)
    mat = np.eye(4)
    mat[:3, :3] = m[:3].T
    mat[:3, 3] = m[3]
    return np.hstack([p, np.ones((len(p), 1))]) @ m, mat


def _barycentric_source(moved, rest, faces, face, points):
    weights = barycentric(points, *(moved[faces[face, k]] for k in range(3)))
    return sum(weights[:, k, None] * rest[faces[face, k]] for k in range(3))


def cpd_deformable(surface: Surface, target: Surface, settings: CpdSettings = CpdSettings(), *, keep=None,
                   keep_target=None) -> np.ndarray:
    """Coherent Point Drift (deformable) of the end-exhale vertices onto the target surface.

    ``settings.samples`` random vertices of each surface are registered (CPD is O(N·M) per iteration), drawn
    from the kept ones (``keep``, ``keep_target``: e.g. crop faces left out, as for every method);
    the fitted Gaussian-kernel displacement ``G(y, Y_s) W`` is then evaluated at every vertex.
    Coordinates are centred on the source and scaled by its RMS radius, so ``beta`` (kernel width)
    is relative to the lung size (2 = twice the RMS radius, the usual CPD setting on unit-variance data); ``alpha`` is the smoothness
    weight and ``w`` the outlier weight (pycpd's meanings). Returns ``(n, 3)`` mm.
    """
    samples, beta = settings.samples, settings.beta
    rng = np.random.default_rng(settings.seed)
    p = surface.vertices
    c = p.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1))))
    src = np.nonzero(np.ones(len(p), bool) if keep is None else np.asarray(keep, bool))[0]
    dst = np.nonzero(np.ones(target.n_vertices, bool) if keep_target is None else np.asarray(keep_target, bool))[0]
    if len(src) < 10 or len(dst) < 10:
        raise InputError(f"CPD needs at least 10 kept vertices on each surface, got {len(src)} and {len(dst)}")
    ys = np.sort(rng.choice(src, min(samples, len(src)), replace=False))
    xs = np.sort(rng.choice(dst, min(samples, len(dst)), replace=False))
    x = (target.vertices[xs] - c) / scale
    y = (p[ys] - c) / scale
    weights = deformable_cpd(x, y, alpha=settings.alpha, beta=beta, w=settings.w,
                             max_iterations=settings.max_iterations, tolerance=settings.tolerance)
    g = np.exp(-cdist((p - c) / scale, y, "sqeuclidean") / (2.0 * beta**2))
    moved = c + scale * ((p - c) / scale + g @ weights)
    if not np.all(np.isfinite(moved)):
        raise ConvergenceError("CPD produced non-finite points")
    return moved


def landmark_tps_cv(surface: Surface, landmarks, landmarks_target, folds) -> tuple[np.ndarray, np.ndarray]:
    """Reference without surfaces: the thin-plate spline through the landmark displacements, its
    smoothing chosen inside the training landmarks as the model's thin-plate landmark correction's
    is (:func:`lungdeform.evaluate.folds.select_smoothing`: the grid
    :data:`lungdeform.interior.field.SMOOTHING_MM2`, 5 inner folds).

    ``landmarks`` / ``landmarks_target : (m, 3)`` mm; ``folds``: index arrays (e.g.
    :func:`lungdeform.evaluate.folds.landmark_folds`). Returns ``(surface vertices moved by the spline of all
    landmarks (n, 3) mm, held-out predictions (m, 3) mm)``: each fold's landmarks are predicted by
    the spline through the other folds only, with the smoothing those chose.
    """
    a = as_vertices(landmarks, "landmarks")
    b = as_vertices(landmarks_target, "landmarks_target")
    d = b - a
    held = np.full_like(a, np.nan)
    for test in folds:
        train = np.setdiff1d(np.arange(len(a)), test)
        lam = select_smoothing(a[train], d[train])
        held[test] = a[test] + interpolation_weights(a[train], a[test], smoothing=lam) @ d[train]
    moved = surface.vertices + interpolation_weights(a, surface.vertices, smoothing=select_smoothing(a, d)) @ d
    return moved, held


@dataclass(frozen=True, eq=False)
class LandmarkPairs:
    """Landmarks of one target: ``rest (k, 3)`` mm at end-exhale and ``target (k, 3)`` mm, their
    observed positions at the target volume (aligned). For :func:`measure`, optionally ``weights``,
    the ``(k, n_kept)`` :func:`landmark_matrix` of these landmarks precomputed (the same for every
    method), and ``predicted (k, 3)`` mm, landmark positions predicted some other way (held-out
    predictions of a landmark-informed method; then no interpolation is done)."""

    rest: np.ndarray
    target: np.ndarray
    weights: np.ndarray | None = None
    predicted: np.ndarray | None = None


def affine_landmarks_cv(surface: Surface, target: Surface, pairs: LandmarkPairs, folds,
                        icp: IcpSettings = IcpSettings(), *, keep=None, keep_target=None,
                        landmark_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The affine baseline informed by the landmark ``pairs``, scored held out.

    Returns ``(vertices (n, 3) mm of the affine fitted with all landmarks, held-out predictions
    (m, 3) mm)``: each fold's landmarks are moved by the affine fitted on the surfaces and the other
    folds' landmarks. ``icp`` and the keywords as :func:`affine_fit`.
    """
    a = as_vertices(pairs.rest, "landmarks")
    b = as_vertices(pairs.target, "landmarks_target")
    held = np.full_like(a, np.nan)
    for test in folds:
        train = np.setdiff1d(np.arange(len(a)), test)
        _, mat = affine_fit(surface, target, icp, keep=keep, keep_target=keep_target, landmarks=a[train],
                            landmarks_target=b[train], landmark_weight=landmark_weight)
        held[test] = a[test] @ mat[:3, :3].T + mat[:3, 3]
    moved, _ = affine_fit(surface, target, icp, keep=keep, keep_target=keep_target, landmarks=a, landmarks_target=b,
                          landmark_weight=landmark_weight)
    return moved, held


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
    landmark_median_mm: float = float("nan")

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def landmark_matrix(rest: Surface, landmarks, keep=None):
    """The sliding interpolation (:mod:`lungdeform.interior.sliding`) from the kept vertices of ``rest`` to
    ``landmarks``, an operator of shape ``(m, k)`` with ``W @ u`` for ``u : (k, 3)`` mm: the interior
    interpolation every method is measured with (crop faces carry no data)."""

    return surface_weights(rest, as_vertices(landmarks, "landmarks"), keep)


def measure(rest: Surface, predicted, target: Surface, *, keep=None, keep_target=None,
            landmarks: LandmarkPairs | None = None, target_distance: SurfaceDistance | None = None):
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
        Vertices measured (e.g. the crop face left out); ``surface_mean_all_mm`` uses all. Only
        kept vertices of ``rest`` carry data for the landmark interpolation.
    landmarks : LandmarkPairs, optional
        End-exhale landmarks and their observed positions at the target volume (aligned), mm, with
        the optional precomputed weights and other predictions (:class:`LandmarkPairs`).

    Returns ``(MethodMetrics, per-vertex distance of predicted to target (n,), landmark errors (k,))``.
    """
    x = as_vertices(predicted, "predicted")
    if x.shape != rest.vertices.shape:
        raise InputError(f"predicted must have shape {rest.vertices.shape}, got {x.shape}")
    pred = Surface(x, rest.faces, "predicted")
    td = target_distance or SurfaceDistance(target.vertices, target.faces)
    all_ = symmetric_distance(pred, target, b_distance=td)  # every vertex both ways, measured once
    if (keep is not None and np.shape(keep) != (rest.n_vertices,)) or (
            keep_target is not None and np.shape(keep_target) != (target.n_vertices,)):
        raise InputError("keep / keep_target must be one boolean per vertex of rest / target")
    sym = all_.restricted(keep, keep_target)
    per_vertex = all_.a_to_b
    lm_err = np.zeros(0)
    if landmarks is not None:
        landmark_weights, landmarks_predicted = landmarks.weights, landmarks.predicted
        obs = as_vertices(landmarks.target, "landmarks_target")
        if landmarks_predicted is None:
            kept = np.ones(rest.n_vertices, bool) if keep is None else np.asarray(keep, bool)
            w = landmark_matrix(rest, landmarks.rest, keep) if landmark_weights is None else landmark_weights
            moved = as_vertices(landmarks.rest, "landmarks") + w @ (x - rest.vertices)[kept]
        else:
            moved = as_vertices(landmarks_predicted, "landmarks_predicted")
        if moved.shape != obs.shape:
            raise InputError(f"landmark predictions {moved.shape} and observations {obs.shape} must match")
        lm_err = np.linalg.norm(moved - obs, axis=1)
    st = sym.stats
    nan = float("nan")
    has = len(lm_err) > 0
    m = MethodMetrics(st.mean, st.rms, st.p95, st.max, all_.stats.mean,
                      float(lm_err.mean()) if has else nan, float(lm_err.max()) if has else nan,
                      float(np.sqrt(np.mean(lm_err**2))) if has else nan,
                      float(np.median(lm_err)) if has else nan)
    return m, per_vertex, lm_err


# =========================================================================== mask-only, calibrated
# The mask-only baselines of docs/FITTING.md "DIR-Lab COPDgene, five subjects", as calibrated there:
# every map takes a point at the smaller volume (its scan's frame, mm) to the larger volume's frame.
#: Surface points per phase of :func:`mask_cpd_map`, Gaussian smoothing (voxels) before marching cubes.
MASK_CPD_POINTS = 1500
MASK_CPD_SIGMA = 0.7
#: How the surface points are chosen: ``"farthest"`` (the default: the farthest-point subset the model's
#: correspondence field uses, deterministic; 8.01 mm on the ten lungs) or ``"random"`` (a seeded
#: draw, the calibration's reading: 8.29 mm with seed 0, 8.3–10.0 on case 5 with other seeds).
MASK_CPD_SAMPLING = "farthest"
#: CPD's smoothness weight and kernel width (mm): those of :mod:`lungdeform.fit.registration`.
MASK_CPD_ALPHA = registration.ALPHA
MASK_CPD_BETA_MM = registration.BETA_MM


def centroid_map(points_small, points_large) -> tuple[np.ndarray, np.ndarray]:
    """``(A (3, 3), t (3,))`` with ``x' = A x + t``: no deformation, the centroids of the two point
    sets (``(n, 3)``, ``(k, 3)`` mm, e.g. mask voxel centres) brought together."""
    a, b = as_vertices(points_small, "points_small"), as_vertices(points_large, "points_large")
    return np.eye(3), b.mean(axis=0) - a.mean(axis=0)


def moment_affine_map(points_small, points_large) -> tuple[np.ndarray, np.ndarray]:
    """``(A, t)``: the affine of the mask moments, ``x' = mu_l + C_l^1/2 C_s^-1/2 (x - mu_s)`` with
    ``mu``, ``C`` the mean and covariance of each point set (``(n, 3)`` mm voxel centres;
    :func:`lungdeform.fit.registration.moment_affine`)."""
    a, b = as_vertices(points_small, "points_small"), as_vertices(points_large, "points_large")
    return registration.moment_affine(a.mean(axis=0), np.cov(a.T), b.mean(axis=0), np.cov(b.T))


def mask_surface_points(image, mask: np.ndarray, n: int = MASK_CPD_POINTS, *, sigma: float = MASK_CPD_SIGMA,
                        sampling: str = MASK_CPD_SAMPLING, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` mm: ``n`` vertices of the marching-cubes surface (level 0.5) of the ``(z, y, x)``
    boolean ``mask`` on ``image``'s grid, smoothed with a Gaussian of ``sigma`` voxels: its
    farthest-point subset (``sampling="farthest"``, :func:`lungdeform.geometry.mesh.farthest_points`)
    or a draw seeded by ``seed`` (``"random"``)."""
    if sampling not in ("farthest", "random"):
        raise InputError(f"sampling must be 'farthest' or 'random', got {sampling!r}")
    smooth = ndi.gaussian_filter(np.asarray(mask, np.float32), sigma)
    verts, *_ = marching_cubes(smooth, level=0.5)
    world = image.index_to_world(verts[:, ::-1])
    if sampling == "farthest":
        return world[farthest_points(world, n)]
    idx = np.sort(np.random.default_rng(seed).choice(len(world), min(n, len(world)), replace=False))
    return world[idx]


def mask_cpd_map(affine: tuple[np.ndarray, np.ndarray], surface_small, surface_large, *,
                 alpha: float = MASK_CPD_ALPHA, beta_mm: float = MASK_CPD_BETA_MM):
    """A function ``(k, 3) mm → (k, 3) mm``: the ``affine`` ``(A, t)`` then CPD's Gaussian field fitted
    from the affine image of ``surface_small`` to ``surface_large`` (``(n, 3)`` mm points): the map
    of :func:`lungdeform.fit.registration.register_points`, the one the model's correspondence field uses."""
    return registration.register_points(affine, surface_small, surface_large, alpha=alpha, beta_mm=beta_mm)
