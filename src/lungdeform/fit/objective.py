"""The fit's objective for one lung: candidate constants judged against the observed surfaces
(paper Sec. IV-B; docs/METHOD_NOTES.md §8). :class:`LungFitter` precomputes once per end-exhale surface and
evaluates many candidates; :func:`lungdeform.fit.fitting.fit_lung` searches over them.

The model keeps the paper's form: per vertex ``u_i = k·F_i·d_i`` with ``d_i`` from c1…c6 (15)–(17),
``F`` the elastostatic response of the applied force (18) ``f = c7·x̂ + c8·ŷ + c9·ẑ`` through the
spring-node graph, and ``k`` fixed by the exact volume of the calibration target. At volume V the
surface is ``p + s·u`` with ``s = (V − V_EE)/ΔV``: three additions per vertex at run time.

Pipeline for one candidate c1…c6 (:meth:`LungFitter.evaluate`):

1. directions ``d`` from c1…c6;
2. rays from the end-exhale vertices along ``±d`` to the calibration target
   (:func:`lungdeform.fit.rays.correspond`: bounded, both directions, grazing rejected, misses
   explicit) → observed magnitudes ``t`` (mm);
3. observed force ``F_obs ∝ t``; **inverse force** ``f = (I − Qᵀ)(F_obs / T_e[i→i])`` (one sparse
   product; spring nodes take the mean of their two mass nodes' F, docs/METHOD_NOTES.md §4);
4. c7…c9 by weighted linear least squares (weights: vertex area; misses 0; one robust pass drops
   rays more than 3 robust standard deviations, at least 1 mm, from the first fit). Reading chosen: the fit is done on the forward side,
   ``F_obs ≈ c7·F_x + c8·F_y + c9·F_z`` (``F_x`` = precomputed response to the field x̂, …), which
   is the same linear model as ``f ≈ c7·x̂ + c8·ŷ + c9·ẑ`` pushed through the solver but does not
   amplify the ray noise by the sparse differentiation of step 3; the paper's reading (least
   squares on the inverse force ``f / max f``) is also computed and reported
   (:attr:`lungdeform.fit.fitting.FitOutcome.force_constants_inverse`). Misses have zero weight;
5. forward check: ``F`` from the fitted c7…c9, ``u = k·F·d`` calibrated to the exact target volume,
   predicted surface ``p + s·u`` measured against every target by the exact symmetric surface
   distance (:mod:`lungdeform.geometry.distance`).

The objective is the RMS of that forward symmetric surface distance (area weighted) over the
targets in ``fit_on``: the predicted surface, not ray agreement, is judged.

Landmark term (optional; paper Sec. IV-B fitted its constants on corresponding points of 4-D CT):
c1…c6 are weakly identified by the surface objective alone (a surface distance sees only the
predicted shape). Given corresponding interior landmarks, the objective becomes
``sqrt(surface_ms + landmark_weight · landmark_ms)`` where the landmarks are moved by the same
sliding interpolation of the model's surface displacement that the metrics use
(:func:`lungdeform.interior.sliding.surface_weights`).

Crop faces (``keep`` False) are left out everywhere: their rays do not enter the force fit or the
stiffness fit, their vertices do not enter the objective, and they carry no interpolation data.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np

from lungdeform.constants import gravity_vector
from lungdeform.errors import InputError, LungdeformError
from lungdeform.geometry.distance import DistanceStack, SurfaceDistance, barycentric, vertex_areas
from lungdeform.geometry.frame import lung_frame
from lungdeform.geometry.mesh import Surface, as_vertices, thinned
from lungdeform.interior.sliding import checked_operator, surface_weights
from lungdeform.model.direction import directions as direction_field
from lungdeform.model.displacement import calibrate
from lungdeform.model.force import field_basis, height_weights
from lungdeform.model.graph import spring_graph
from lungdeform.model.response import ResponseSolver
from lungdeform.model.stiffness import as_moduli, uniform
from lungdeform.model.transfer import split_transfer

from .rays import RayCaster, RayHits, correspond


@dataclass(frozen=True, eq=False)
class Target:
    """One observed surface at a larger volume, in the end-exhale scan's frame (aligned).

    Attributes
    ----------
    surface : Surface
        mm LPS, already rigidly aligned to the end-exhale scan.
    volume_ml : float
        Its lung volume (mL), measured or given.
    keep : (n_target,) bool
        Target vertices measured (False: an artefact such as a crop face).
    name : str
    """

    surface: Surface
    volume_ml: float
    keep: np.ndarray | None = None
    name: str = "target"


@dataclass(frozen=True, eq=False)
class _PreparedTarget:
    target: Target
    distance: SurfaceDistance
    caster: RayCaster
    samples: np.ndarray  # (k, 3) target points used by the fit objective
    sample_weights: np.ndarray  # (k,) mm², their areas
    root_weights: np.ndarray  # (k,) sqrt(sample_weights / their sum): the residuals' weights, once


@dataclass(frozen=True, eq=False)
class Evaluation:
    """One forward evaluation of candidate constants (:meth:`LungFitter.residuals`).

    Attributes
    ----------
    directions : (n, 3) float
        Unit directions from c1…c6.
    hits : RayHits or None
        Rays to the calibration target (None when they were not cast: c7…c9 given, no ``rays``).
    force_constants : (3,) float or None
        c7…c9 used (unnormalised; None when the rays gave too few hits).
    u : (n, 3) float or None
        Displacement, mm per ``delta_ml`` (None: an unusable candidate, no growth or no hits).
    vector : (r,) float or None
        Weighted residuals (mm) whose sum of squares is the objective squared
        (:meth:`LungFitter.residual_vector`); None with ``u``.
    residuals : dict[str, (k,) float]
        Per target name: symmetric distances (mm) of the fit samples (empty when unusable).
    surface_ms, landmark_ms : float
        Mean squares (mm²) of the surface and landmark parts (NaN when unusable / no landmarks).
    """

    directions: np.ndarray
    hits: RayHits | None
    force_constants: np.ndarray | None
    u: np.ndarray | None
    vector: np.ndarray | None
    residuals: dict
    surface_ms: float
    landmark_ms: float


# --------------------------------------------------------------------------- free functions
def inverse_force(transfer, kept_mass: np.ndarray, spring_ends: np.ndarray) -> np.ndarray:
    """Applied force on all graph nodes from the kept force on mass nodes (paper Sec. IV-B.3; docs/METHOD_NOTES.md §8).

    ``f = (I − Qᵀ)(F / T_e[i→i])`` with spring-node F the mean of its two mass nodes.
    ``kept_mass : (n,) float``; ``spring_ends : (e, 2) int``; returns ``f : (n + e,) float``.
    """
    keep, q = split_transfer(transfer)
    fm = np.asarray(kept_mass, float)
    f_all = np.concatenate([fm, 0.5 * (fm[spring_ends[:, 0]] + fm[spring_ends[:, 1]])])
    x = f_all / keep
    return x - q.T @ x


def least_squares_constants(fields: np.ndarray, values: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted linear least squares ``values ≈ c @ fields``: ``fields (k, n)``, ``values (n,)`` →
    ``c (k,)``. Rows with zero weight are ignored."""
    a = np.asarray(fields, float).T
    b = np.asarray(values, float)
    w = np.ones(len(b)) if weights is None else np.asarray(weights, float)
    m = w > 0
    if m.sum() < a.shape[1]:
        raise LungdeformError(f"too few observations ({int(m.sum())}) to fit {a.shape[1]} constants")
    sw = np.sqrt(w[m])
    c, *_ = np.linalg.lstsq(a[m] * sw[:, None], b[m] * sw, rcond=None)
    return c


def _unit(v: np.ndarray, length: np.ndarray) -> np.ndarray:
    """``v : (k, 3)`` divided by ``length : (k,)`` (its norm), rows of length 0 left 0."""
    return np.where(length[:, None] > 0, v / np.where(length > 0, length, 1.0)[:, None], 0.0)


def _sample(surface: Surface, keep: np.ndarray, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``count`` kept vertices (random, reproducible) with area weights rescaled to the kept area."""
    idx = np.nonzero(keep)[0]
    w = vertex_areas(surface.vertices, surface.faces)
    idx = idx[thinned(len(idx), count, seed)]
    return surface.vertices[idx], w[idx]


# --------------------------------------------------------------------------- the fitter
@dataclass(frozen=True)
class ObjectiveSettings:
    """How :class:`LungFitter` measures a candidate (the same for every candidate of one fit).

    Attributes
    ----------
    gravity : str or (3,) float
        Posture or gravity direction (:func:`lungdeform.constants.gravity_vector`).
    max_distance : float
        Ray search bound, mm.
    min_cosine : float
        Grazing threshold of a ray hit (cosine between the ray and the target's normal).
    samples : int
        Target points per target used by the objective.
    d_min : float
        Smallest spring rest length of the force solve, mm (:class:`lungdeform.model.response.ResponseSolver`).
    """

    gravity: object = "supine"
    max_distance: float = 25.0
    min_cosine: float = 0.25
    samples: int = 6000
    d_min: float = 1.0


@dataclass(frozen=True, eq=False)
class LandmarkTerm:
    """The objective's optional landmark term (:class:`LungFitter`).

    Attributes
    ----------
    rest : (m, 3) float
        Landmarks at end-exhale, mm, same frame as the fitted surface.
    targets : dict[int, (m, 3) float]
        Observed positions of those landmarks at target ``i`` (aligned, mm), for the targets that
        have them (only targets in ``fit_on`` enter the objective).
    weight : float
        Weight of the landmark mean square against the surface mean square (1: both in mm²).
    matrix : (m, k) operator, optional
        The sliding interpolation from the kept vertices to ``rest``
        (:func:`lungdeform.interior.sliding.surface_weights` of the surface with ``keep`` at
        ``rest``; an ``(m, k)`` array is also accepted), precomputed by the caller (one dense solve
        of size ~k saved per fitter); computed by the fitter when not given. Row ``j`` depends only
        on landmark ``j``, so rows of one matrix serve any subset of the landmarks.
    """

    rest: object
    targets: dict
    weight: float = 1.0
    matrix: object = None


class LungFitter:
    """Precompute once for one end-exhale surface, then evaluate many candidate constants.

    Parameters
    ----------
    surface : Surface
        End-exhale surface p (the model mesh; a few thousand vertices), mm LPS.
    side : 'left' | 'right'
    targets : sequence of Target
        Aligned surfaces at larger volumes (all above V_EE, never decreasing; equal volumes allowed).
    fit_on : sequence of int, optional
        Indices of the targets in the objective (default: all). The first is the calibration
        target (``k`` makes its volume exact) and the one rays are cast to.
    keep : (n,) bool, optional
        Model vertices measured by the objective (False: e.g. the crop face).
    settings : ObjectiveSettings
        Gravity, ray search bounds, target samples, the force solve's shortest spring.
    stiffness : (n,) float, optional
        Young's moduli to start from (default uniform).
    landmarks : LandmarkTerm, optional
        The landmark term of the objective (none without).
    """

    def __init__(self, surface: Surface, side: str, targets: Sequence[Target], *, fit_on=None, keep=None,
                 settings: ObjectiveSettings = ObjectiveSettings(), stiffness=None,
                 landmarks: LandmarkTerm | None = None):
        if not targets:
            raise InputError("targets: fitting needs at least one larger-volume surface")
        self.surface = surface
        self.side = side
        self.p = surface.vertices
        self.n = surface.n_vertices
        self.v_ee = surface.volume_ml
        vols = [float(t.volume_ml) for t in targets]
        for t, v in zip(targets, vols):
            if not np.isfinite(v) or v <= self.v_ee:
                raise InputError(
                    f"{t.name}: volume {v:.1f} mL is not larger than the end-exhale volume "
                    f"{self.v_ee:.1f} mL; volumes must increase from the end-exhale surface")
        if any(b < a for a, b in zip(vols, vols[1:])):  # equal: inhale and exhale phases of one volume
            raise InputError(f"target volumes must not decrease, got {', '.join(f'{v:.1f}' for v in vols)} mL")
        self.targets = list(targets)
        self.fit_on = list(range(len(targets))) if fit_on is None else [int(i) for i in fit_on]
        if not self.fit_on or any(i < 0 or i >= len(targets) for i in self.fit_on):
            raise InputError(f"fit_on must index the {len(targets)} targets, got {fit_on!r}")
        self.keep = np.ones(self.n, bool) if keep is None else np.asarray(keep, bool)
        self.gravity = gravity_vector(settings.gravity)
        self.max_distance = float(settings.max_distance)
        self.min_cosine = float(settings.min_cosine)
        self.d_min = float(settings.d_min)
        self.frame = lung_frame(self.p, side)
        self.xyz = self.frame.normalized(self.p)
        self.graph = spring_graph(self.p, surface.edges)
        self.areas = vertex_areas(self.p, surface.faces)
        self.prepared = []
        for i, t in enumerate(self.targets):
            k = np.ones(t.surface.n_vertices, bool) if t.keep is None else np.asarray(t.keep, bool)
            pts, w = _sample(t.surface, k, settings.samples, seed=i)
            self.prepared.append(_PreparedTarget(t, SurfaceDistance(t.surface.vertices, t.surface.faces),
                                                 RayCaster(t.surface.vertices, t.surface.faces), pts, w,
                                                 np.sqrt(w / w.sum())))
        kept_areas = self.areas[self.keep]
        self.root_areas = np.sqrt(kept_areas / kept_areas.sum())  # (kept,): the model vertices' residual weights
        self.calib = self.fit_on[0]
        self.delta_ml = vols[self.calib] - self.v_ee
        if landmarks is None:
            self._set_landmarks(None, None, 1.0)
        else:
            self._set_landmarks(landmarks.rest, landmarks.targets, landmarks.weight, landmarks.matrix)
        self.set_stiffness(uniform(self.n) if stiffness is None else as_moduli(stiffness, self.n))
        self.evaluations = 0
        self._last: dict = {}  # each kind of distance query: its last points, model and answer (:meth:`_queries`)

    def _set_landmarks(self, rest, observed, weight, matrix=None) -> None:
        self.landmark_weight = float(weight)
        self.lm_rest, self.lm_targets, self.lm_matrix = None, {}, None
        if rest is None or not observed:
            return

        rest = as_vertices(rest, "landmarks_rest")
        if not (np.isfinite(self.landmark_weight) and self.landmark_weight >= 0):
            raise InputError(f"landmark_weight must be >= 0, got {weight!r}")
        for i, pts in observed.items():
            if int(i) not in range(len(self.targets)):
                raise InputError(f"landmarks_targets: no target {i} (there are {len(self.targets)})")
            if np.shape(pts) != rest.shape:
                raise InputError(f"landmarks of target {i} have shape {np.shape(pts)}, the end-exhale "
                                 f"landmarks {rest.shape}; rows must correspond")
        self.lm_rest = rest
        self.lm_targets = {int(i): as_vertices(v, "landmarks") for i, v in observed.items() if int(i) in self.fit_on}
        # the metrics' interpolation: the sliding interpolation from the kept vertices (crop face out)
        if matrix is None:
            self.lm_matrix = surface_weights(self.surface, rest, self.keep)
        else:
            self.lm_matrix = checked_operator(matrix, (len(rest), int(self.keep.sum())))

    def landmark_positions(self, u: np.ndarray, target: int) -> np.ndarray:
        """``(m, 3)`` mm: the landmarks moved by the sliding interpolation of ``s·u`` at ``target``."""
        return self.lm_rest + self.scale_at(target) * (self.lm_matrix @ u[self.keep])

    # ----------------------------------------------------------------- stiffness-dependent part
    def set_stiffness(self, stiffness: np.ndarray) -> None:
        """(Re)build the transfer and the force responses for a stiffness field ``(n,)``."""
        self.stiffness = stiffness
        response = ResponseSolver(self.graph, stiffness, d_min=self.d_min)
        self.transfer = response.transfer
        self.basis = response.responses(field_basis(self.xyz))  # (4, n)
        w = height_weights(self.frame, self.gravity)
        # the three fields of (18) for this gravity: x̂, ĥ(gravity), ẑ
        self.fields = np.stack([self.basis[1], w @ self.basis, self.basis[3]])  # responses F_x, F_h, F_z
        self.applied_fields = np.stack([self.xyz[:, 0], w @ field_basis(self.xyz), self.xyz[:, 2]])

    # ----------------------------------------------------------------- one candidate
    def ray_force_constants(self, d: np.ndarray, hits: RayHits) -> np.ndarray | None:
        """c7…c9 ``(3,)`` (unnormalised) fitted to the ray magnitudes of ``hits`` along ``d`` (steps
        2–4 of the module docstring); None when fewer than 10 kept rays hit."""
        w = np.where(hits.valid & self.keep, self.areas, 0.0)  # crop-face rays carry no data
        t = np.nan_to_num(hits.distance)
        if (w > 0).sum() < 10:
            return None
        c_force = least_squares_constants(self.fields, t, w)
        # one robust pass: rays whose magnitude is far from the fitted force (a wrong wall) are dropped
        resid = np.abs(c_force @ self.fields - t)
        mad = 1.4826 * np.median(resid[w > 0])
        w2 = np.where(resid <= max(3.0 * mad, 1.0), w, 0.0)
        if (w2 > 0).sum() >= 10:
            c_force = least_squares_constants(self.fields, t, w2)
        return c_force

    def displacement(self, d: np.ndarray, c_force: np.ndarray) -> np.ndarray | None:
        """``u (n, 3)`` mm per ``delta_ml``: ``k·F·d`` calibrated on the calibration target's volume
        for directions ``d (n, 3)`` and c7…c9 ``c_force (3,)``; None when it gives no volume growth."""
        force = np.asarray(c_force, float) @ self.fields
        try:
            return calibrate(self.p, self.surface.faces, force[:, None] * d, calibration_ml=self.delta_ml,
                             unit_ml=self.delta_ml)
        except LungdeformError:
            return None

    def residual_vector(self, u: np.ndarray, shifts=None) -> tuple[np.ndarray, dict, float, float]:
        """Weighted per-point residuals (mm) of the displacement ``u (n, 3)`` whose sum of squares is
        the objective squared: both directions of the symmetric surface distance for every target
        in ``fit_on`` (area weights), then the landmark errors (x, y, z) scaled by
        ``landmark_weight``. ``shifts : (k, 3)`` mm, optional: target ``i`` is taken as its surface
        (and landmarks) translated by ``shifts[i]``. Returns ``(r, residuals by target name,
        surface_ms, landmark_ms)``."""
        sh = np.zeros((len(self.targets), 3)) if shifts is None else np.asarray(shifts, float)
        parts, residuals = [], {}
        norm = np.sqrt(2.0 * len(self.fit_on))
        for i, (a_to_b, _, _), (b_to_a, _, _) in zip(self.fit_on, *self._two_sided(u, sh)):
            pt = self.prepared[i]
            residuals[pt.target.name] = np.concatenate([a_to_b, b_to_a])
            parts += [a_to_b * self.root_areas / norm, b_to_a * pt.root_weights / norm]
        surface_ms = float(sum(np.sum(r**2) for r in parts))
        lm_ms = float("nan")
        if self.lm_targets:
            errs = [(self.landmark_positions(u, i) - (obs + sh[i])).ravel() for i, obs in self.lm_targets.items()]
            lm_ms = float(np.mean([np.sum(e**2) / len(self.lm_rest) for e in errs]))
            scale = np.sqrt(self.landmark_weight / (len(errs) * len(self.lm_rest)))
            parts += [e * scale for e in errs]
        return np.concatenate(parts), residuals, surface_ms, lm_ms

    def residual_jacobian(self, u: np.ndarray, du: np.ndarray, shifts=None, *,
                          translations: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The Jacobian of :meth:`residual_vector` at the displacement ``u : (n, 3)`` mm per unit, one
        forward evaluation (counted in :attr:`evaluations`): ``(J (r, p), J_shift (r, 3·len(fit_on)))``
        for parameters that move ``u`` by ``du : (n, 3, p)`` (mm per unit per parameter) and for the
        translation of each target in ``fit_on`` (in that order, x y z each); ``J_shift`` None when
        ``translations`` is False (a search without translations: its mostly-zero block grows with the
        square of the targets, 4 MB per Jacobian for a 10-phase 4-D CT).

        Every residual is a distance between a point and a surface, so its derivative is the unit
        vector from the closest point times the motion of the two (the envelope theorem: the
        closest point's own motion along the surface does not change the distance to first order):
        a model vertex ``x_v = p_v + s·u_v`` against the target, ``ĝ · s·∂u_v``; a target sample
        against the model surface, ``−ĝ · s·Σ_c b_c ∂u_c`` over the corners of the face of its closest
        point (barycentric ``b``); a landmark, ``s·M ∂u`` (its sliding interpolation). A distance of 0
        has no direction: its row is 0."""
        self.evaluations += 1
        sh = np.zeros((len(self.targets), 3)) if shifts is None else np.asarray(shifts, float)
        du = np.asarray(du, float)
        keep = np.flatnonzero(self.keep)
        norm = np.sqrt(2.0 * len(self.fit_on))
        col = {i: c for c, i in enumerate(self.fit_on)}
        rows_p, rows_t, cols, lm_cols = [], [], [c for c in range(len(self.fit_on)) for _ in (0, 1)], []
        fa, du_kept = self.root_areas / norm, du[keep]
        for i, (dist, closest, _), on_model in zip(self.fit_on, *self._two_sided(u, sh)):
            pt = self.prepared[i]
            s = self.scale_at(i)
            x = self.p + s * u
            # model vertices → target surface
            g = _unit(x[keep] - sh[i] - closest, dist)
            rows_p.append(fa[:, None] * s * np.einsum("kc,kcp->kp", g, du_kept))
            rows_t.append(-fa[:, None] * g)
            # target samples → model surface
            q = pt.samples + sh[i]
            dist, closest, face = on_model
            g = _unit(q - closest, dist)
            corners = self.surface.faces[face]  # (k, 3)
            b = barycentric(closest, *(x[corners[:, c]] for c in range(3)))
            moved = np.einsum("kv,kvcp->kcp", b, du[corners])
            fb = pt.root_weights / norm
            rows_p.append(-fb[:, None] * s * np.einsum("kc,kcp->kp", g, moved))
            rows_t.append(fb[:, None] * g)
        if self.lm_targets:
            scale = np.sqrt(self.landmark_weight / (len(self.lm_targets) * len(self.lm_rest)))
            m = len(self.lm_rest)
            moved = np.stack([self.lm_matrix @ du_kept[..., k] for k in range(du.shape[2])], axis=2)  # (m, 3, p)
            for i in self.lm_targets:
                rows_p.append(scale * self.scale_at(i) * moved.reshape(3 * m, -1))
                rows_t.append(-scale * np.tile(np.eye(3), (m, 1)))
                lm_cols.append(col[i])
        return np.concatenate(rows_p), (self._shift_block(rows_t, cols + lm_cols) if translations else None)

    def _shift_block(self, blocks: list, cols: list) -> np.ndarray:
        """``(r, 3·len(fit_on))``: the translation columns of :meth:`residual_jacobian`, block ``k``
        (``(r_k, 3)``, its rows' derivatives in the translation of target ``fit_on[cols[k]]``) in that
        target's three columns, zeros elsewhere."""
        out = np.zeros((sum(len(b) for b in blocks), 3 * len(self.fit_on)))
        start = 0
        for b, c in zip(blocks, cols):
            out[start:start + len(b), 3 * c:3 * c + 3] = b
            start += len(b)
        return out

    def directions(self, c_dir: np.ndarray) -> np.ndarray:
        """Unit directions ``(n, 3)`` from c1…c6 ``c_dir (6,)`` (step 1)."""
        return direction_field(self.frame, self.p, np.concatenate([np.asarray(c_dir, float)[:6], [0.0, 1.0, 0.0]]))

    def rays(self, d: np.ndarray) -> RayHits:
        """Rays from the end-exhale vertices along ``±d (n, 3)`` to the calibration target (step 2)."""
        return correspond(self.p, d, self.prepared[self.calib].caster, max_distance=self.max_distance,
                          min_cosine=self.min_cosine)

    def residuals(self, c_dir: np.ndarray, force=None, shifts=None, *, rays: bool = False,
                  directions=None) -> Evaluation:
        """One forward evaluation (counted in :attr:`evaluations`) of direction constants
        ``c_dir (6,)``: directions, c7…c9 (``force``, or fitted to the ray magnitudes when None,
        steps 2–4), displacement and the residual vector of :meth:`residual_vector` for the targets
        translated by ``shifts : (k, 3)`` mm. ``rays``: cast the rays even when ``force`` is given
        (for :attr:`Evaluation.hits`). ``directions (n, 3)``: unit directions to use instead of
        those of ``c_dir`` (a corrected field, :mod:`lungdeform.fit.direction_correction`)."""
        self.evaluations += 1
        d = self.directions(c_dir) if directions is None else np.asarray(directions, float)
        hits = self.rays(d) if force is None or rays else None
        c_force = self.ray_force_constants(d, hits) if force is None else np.asarray(force, float)
        u = None if c_force is None else self.displacement(d, c_force)
        if u is None:
            return Evaluation(d, hits, c_force, None, None, {}, float("nan"), float("nan"))
        r, residuals, surface_ms, lm_ms = self.residual_vector(u, shifts)
        return Evaluation(d, hits, c_force, u, r, residuals, surface_ms, lm_ms)

    def evaluate(self, c_dir: np.ndarray, *, full: bool = False, force=None, shifts=None, directions=None):
        """Objective (mm) for direction constants ``c_dir (6,)``; with ``full`` also the parts.

        ``force``: c7…c9 to use (default: fitted to the ray magnitudes, steps 2–4);
        ``shifts : (k, 3)`` mm: translations of the targets (see :meth:`residual_vector`);
        ``directions``: as :meth:`residuals`."""
        ev = self.residuals(c_dir, force, shifts, rays=full, directions=directions)
        if ev.u is None:
            return (np.inf, None) if full else np.inf
        obj = self._combine(ev.surface_ms, ev.landmark_ms)
        return (obj, self._parts(ev, c_dir)) if full else obj

    def objective(self, u: np.ndarray, shifts=None) -> float:
        """The objective (mm) of a displacement ``u (n, 3)`` mm per unit."""
        _, _, surface_ms, lm_ms = self.residual_vector(u, shifts)
        return self._combine(surface_ms, lm_ms)

    def _combine(self, surface_ms: float, landmark_ms: float) -> float:
        return float(np.sqrt(surface_ms + (self.landmark_weight * landmark_ms if self.lm_targets else 0.0)))

    def _parts(self, ev: Evaluation, c_dir) -> dict:
        c_force = ev.force_constants
        scale = np.abs(c_force).max()
        return dict(directions=ev.directions, hits=ev.hits, force=c_force @ self.fields, u=ev.u,
                    residuals=ev.residuals, constants=np.concatenate([np.asarray(c_dir, float)[:6], c_force / scale]),
                    surface_rms=float(np.sqrt(ev.surface_ms)), landmark_rms=float(np.sqrt(ev.landmark_ms)))

    def scale_at(self, target: int) -> float:
        """The model's scale ``s`` (units of ``delta_ml``) at target ``target``'s volume."""
        return (self.targets[target].volume_ml - self.v_ee) / self.delta_ml

    def _two_sided(self, u: np.ndarray, shifts: np.ndarray) -> tuple[list, list]:
        """For the displacement ``u : (n, 3)`` mm per unit, per target in ``fit_on`` (moved by ``shifts :
        (k, 3)`` mm): ``(model vertices → target, target samples → model)``, each a list of
        ``(distance, closest, face)`` (:meth:`_queries`: every target's in one search)."""
        x = [self.p + self.scale_at(i) * u for i in self.fit_on]
        to_target = self._queries([(i, xi[self.keep] - shifts[i], None) for i, xi in zip(self.fit_on, x)])
        to_model = self._queries([(i, self.prepared[i].samples + shifts[i], xi) for i, xi in zip(self.fit_on, x)])
        return to_target, to_model

    def target_query(self, target: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(distance (k,) mm, closest (k, 3) mm, face (k,) int)`` of ``points : (k, 3)`` mm (the fitted
        surface's frame) on target ``target``'s surface: the query of :meth:`residual_vector`, so the
        model's vertices at the displacement just evaluated (the same points) cost no search again."""
        return self._queries([(int(target), np.ascontiguousarray(points, float), None)])[0]

    def _queries(self, items: list) -> list:
        """``(distance, closest, face)`` of each ``(target, points (k, 3), model)``: the points on target
        ``target``'s surface, or with ``model : (n, 3)`` on the model surface of those vertices (the model's
        faces). The same query as the last of its kind for that target (the same points and model: the
        Jacobian at the point just evaluated) returns the last answer; the others are searched together,
        one kernel call for the targets' surfaces and one for the models'
        (:class:`lungdeform.geometry.distance.DistanceStack`), each started from the closest faces of its
        last (candidates move little between evaluations, so each face found last time bounds the search
        tightly; exact distances either way, :meth:`lungdeform.geometry.distance.SurfaceDistance.query`)."""
        out, todo = [None] * len(items), {True: [], False: []}
        for j, (i, points, model) in enumerate(items):
            last = self._last.get((i, model is None))
            if last is not None and np.array_equal(last[0], points) and (
                    model is None or np.array_equal(last[1], model)):
                out[j] = last[2]
            else:
                todo[model is None].append(j)
        for on_target, js in todo.items():
            if not js:
                continue
            hints = [self._last[(items[j][0], on_target)][2][2] if (items[j][0], on_target) in self._last else None
                     for j in js]
            if on_target:
                stack, which = self._target_stack, [items[j][0] for j in js]
            else:
                stack = DistanceStack([SurfaceDistance(items[j][2], self.surface.faces) for j in js])
                which = range(len(js))
            for j, answer in zip(js, stack.query(which, [items[j][1] for j in js], hints)):
                i, points, model = items[j]
                self._last[(i, on_target)] = (points.copy(), None if model is None else model.copy(), answer)
                out[j] = answer
        return out

    @cached_property
    def _target_stack(self) -> DistanceStack:
        """Every target's surface in one :class:`~lungdeform.geometry.distance.DistanceStack` (built on first use)."""
        return DistanceStack([pt.distance for pt in self.prepared])

    def inverse_parts(self, force_obs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(f (n,) normalised by max |f|, c7…c9 (3,))``: inverse force and its paper-style fit."""
        f = inverse_force(self.transfer, force_obs, self.graph.spring_ends)[: self.n]
        scale = np.abs(f[weights > 0]).max() if np.any(weights > 0) else 1.0
        f = f / (scale or 1.0)
        c = least_squares_constants(self.applied_fields, f, weights)
        return f, c / (np.abs(c).max() or 1.0)
