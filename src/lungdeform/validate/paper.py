"""The paper's own validation of the transfer model (Sec. IV-A, Figs. 7–9), as three experiments.

1. :func:`planar_experiment` (Fig. 8). A regular planar mesh with uniform ``E = 1`` under a bending
   force pattern, solved by the transfer model (sparse fixed point and push loop) and by a
   mass–spring–damper (MSD) simulation integrated in time to rest (:mod:`lungdeform.validate.msd`). Reported:
   the RMS difference of the mass-node displacements as a % of the largest MSD displacement (paper:
   < 0.1 %).

   - Mesh (:func:`planar_mesh`): ``nx × ny`` vertices on a square grid of ``spacing`` mm in the plane
     ``z = 0``, each grid square split into two triangles along the same diagonal. Spring nodes sit at
     edge midpoints, so graph links are half an edge long: ``spacing/2`` (axis edges) and
     ``spacing/√2`` (diagonals). The default 3 mm keeps every link longer than ``d_min = 1`` mm; with
     ``spacing < 2·d_min`` the axis links are clipped to ``d_min`` (weight 1, purely topological) —
     the MSD uses the same clipped distances, so the comparison still holds, but the geometry then
     no longer shapes the transfer.
   - Boundary: none is fixed. The transfer model has no contact forces (the paper's point), and its
     MSD equivalent ties *every* node to its rest position by a unit ground spring, so edge nodes are
     simply nodes with fewer neighbours.
   - Bending force (:func:`bending_force`): out of plane on mass nodes,
     ``f = sin(π·(x − x0)/L) · sin(π·(y − y0)/W)`` over the mesh's bounding box (L × W): zero on
     the border, 1 at the centre — the sheet bulges like an expanding lung surface. Spring nodes get
     no applied force (Sec. III-G; docs/METHOD_NOTES.md §4).
   - The MSD: :func:`lungdeform.validate.msd.transfer_network` — the parameters are *derived* from the
     transfer model, see :mod:`lungdeform.validate.msd`: every node has unit mass and a unit ground spring,
     every graph link a spring ``d_min / d_ij``, damping critical for the lowest mode (``c = 2 ω_min``),
     time step 0.9 of the explicit stability limit. Displacement of the transfer model = kept force
     ``C`` (paper (1) with ``M = 1``, unit time).

2. :func:`circular_experiment` (Fig. 9). A 2-D disc mesh (:func:`circular_mesh`: a centre vertex and
   rings of ``6k`` vertices at radius ``k·spacing``, Delaunay-triangulated) with a variable ``E`` per
   vertex (:func:`circular_moduli`: smooth lobes, stiff along ±x and soft along ±y, or seeded
   log-uniform random) under a unit radial force on every vertex (the centre gets none: its
   radius has no direction). Displacement = ``C_i`` along the outward radius. Reported: the
   stiff/soft displacement ratio (mean radial displacement of the stiffest ``fraction`` of vertices
   over that of the softest) — < 1 means stiffer nodes move less — and the same ratio after dividing
   each node's displacement by its displacement under uniform ``E`` (which removes the effect of
   position, e.g. border nodes having fewer neighbours). For heterogeneous E no MSD with the same
   forces matches the transfer operator (it is not symmetric; see :mod:`lungdeform.validate.msd`), so this
   experiment checks behaviour, not a number against an MSD.

3. :func:`convergence_experiment` (Fig. 7). On the planar problem: ``max |P| / max |f|`` of the push
   loop (one push = one node hands on its Pitcher) against the MSD's ``max |f − K u| / max |f|``
   (one step = every node updated). Both are residuals of the same linear system (see
   :mod:`lungdeform.validate.msd`), so they share an axis. Work is reported as raw iterations and as sweeps
   (node updates / number of graph nodes). "Converged" means the relative residual is at most
   ``tol`` (default 1e-6); the MSD must in addition be at rest (kinetic ≤ tol² · strain energy).

Figure writers draw with :mod:`lungdeform.plot` and write atomically.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import Delaunay
from scipy.stats import spearmanr

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import unique_edges
from lungdeform.model.graph import SpringGraph, spring_graph
from lungdeform.model.solve import ForceSolver, push
from lungdeform.model.transfer import local_transfer
from lungdeform.plot.figure import save_png
from lungdeform.plot.paper import circular_figure, convergence_figure, planar_figure

from .msd import MSDIntegrator, MSDResult, transfer_network

CONVERGENCE_DEFINITION = (
    "relative residual of (I - Q^T) x = f: push loop max|Pitcher|/max|f|, MSD max|f - K u|/max|f| "
    "(the same quantity, u = diag(T_e[i->i]) x); converged when <= tol, the MSD also at rest "
    "(kinetic energy <= tol^2 * strain energy). One push updates one node; one MSD step updates all "
    "n_nodes; sweeps = node updates / n_nodes."
)


# --------------------------------------------------------------------------- meshes and loads
def planar_mesh(nx: int = 41, ny: int = 41, spacing: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """A regular triangulated grid in the plane ``z = 0``.

    Returns ``vertices : (nx·ny, 3) float`` mm (vertex ``i·ny + j`` at ``(i·spacing, j·spacing, 0)``)
    and ``faces : (2(nx−1)(ny−1), 3) int`` (each square split along its ``(i, j)–(i+1, j+1)``
    diagonal, counter-clockwise seen from +z).
    """
    if int(nx) < 2 or int(ny) < 2:
        raise InputError(f"planar mesh needs at least 2 × 2 vertices, got nx={nx}, ny={ny}")
    if not (np.isfinite(spacing) and spacing > 0):
        raise InputError(f"spacing must be > 0 mm, got {spacing!r}")
    nx, ny = int(nx), int(ny)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    v = np.stack([i.ravel() * spacing, j.ravel() * spacing, np.zeros(nx * ny)], 1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return np.ascontiguousarray(v), np.ascontiguousarray(f, dtype=np.int64)


def circular_mesh(rings: int = 12, spacing: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """A disc: a centre vertex plus rings ``k = 1..rings`` of ``6k`` vertices at radius ``k·spacing``.

    Returns ``vertices : (1 + 3·rings·(rings+1), 3) float`` mm in the plane ``z = 0``, centre first,
    and ``faces : (m, 3) int`` from a Delaunay triangulation (counter-clockwise seen from +z).
    """

    if int(rings) < 1:
        raise InputError(f"rings must be ≥ 1, got {rings!r}")
    if not (np.isfinite(spacing) and spacing > 0):
        raise InputError(f"spacing must be > 0 mm, got {spacing!r}")
    pts = [np.zeros((1, 2))]
    for k in range(1, int(rings) + 1):
        theta = 2 * np.pi * (np.arange(6 * k) + 0.5 * (k % 2)) / (6 * k)
        pts.append(k * spacing * np.stack([np.cos(theta), np.sin(theta)], 1))
    xy = np.concatenate(pts)
    tri = Delaunay(xy).simplices.astype(np.int64)
    p = xy[tri]
    cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    tri[cross < 0] = tri[cross < 0][:, ::-1]
    v = np.concatenate([xy, np.zeros((len(xy), 1))], 1)
    return np.ascontiguousarray(v), np.ascontiguousarray(tri)


def bending_force(vertices: np.ndarray) -> np.ndarray:
    """``f : (n,) float`` = ``sin(π·(x − x0)/L) · sin(π·(y − y0)/W)`` over the x–y bounding box.

    Zero on the border, 1 at the centre: an out-of-plane dome load (relative force units).
    """
    v = np.asarray(vertices, dtype=float)
    lo, hi = v[:, :2].min(0), v[:, :2].max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    s = (v[:, :2] - lo) / span
    f = np.sin(np.pi * s[:, 0]) * np.sin(np.pi * s[:, 1])
    return np.where(np.abs(f) < 1e-12, 0.0, f)


def mesh_graph(vertices: np.ndarray, faces: np.ndarray) -> SpringGraph:
    """The spring-node graph of a triangle mesh (edges from the faces)."""
    return spring_graph(vertices, unique_edges(np.asarray(faces, dtype=np.int64))[0])


def rms_percent(test: np.ndarray, reference: np.ndarray) -> float:
    """``100 · RMS(test − reference) / max|reference|`` (the paper's "% RMS")."""
    ref = np.asarray(reference, dtype=float)
    scale = float(np.abs(ref).max())
    if scale == 0:
        raise InputError("reference displacement is zero everywhere; % RMS is undefined")
    return float(100.0 * np.sqrt(np.mean((np.asarray(test, float) - ref) ** 2)) / scale)


# --------------------------------------------------------------------------- 1. planar (Fig. 8)
@dataclass(frozen=True)
class PlanarResult:
    """Fig. 8: transfer model vs MSD on a planar mesh, uniform E = 1.

    Attributes
    ----------
    vertices : (n, 3) float
        Mesh vertices, mm, plane z = 0.
    faces : (m, 3) int
    force : (n,) float
        Applied out-of-plane force per vertex (relative units).
    transfer_displacement : (N,) float
        Kept force C from the sparse fixed point (ForceSolver, direct) = displacement, all graph nodes.
    push_displacement : (N,) float
        Kept force from the push loop (tol ``tol``).
    msd_displacement : (N,) float
        MSD displacement at rest, all graph nodes.
    rms_percent : float
        RMS(MSD − transfer) over mass nodes, % of the largest MSD displacement.
    rms_percent_push : float
        The same with the push loop as the transfer solution.
    rms_percent_all_nodes : float
        The same over all graph nodes (mass and spring nodes).
    msd : MSDResult
    omega_min, omega_max_bound : float
        Lowest MSD frequency and the Gershgorin bound of the highest (rad per time unit).
    spacing, d_min, tol : float
    seconds : dict
        Wall time of the sparse solve, the push loop and the MSD run.
    """

    vertices: np.ndarray
    faces: np.ndarray
    force: np.ndarray
    transfer_displacement: np.ndarray
    push_displacement: np.ndarray
    msd_displacement: np.ndarray
    rms_percent: float
    rms_percent_push: float
    rms_percent_all_nodes: float
    msd: MSDResult
    omega_min: float
    omega_max_bound: float
    spacing: float
    d_min: float
    tol: float
    seconds: dict

    def to_dict(self) -> dict:
        n = len(self.vertices)
        return {
            "rms_percent": self.rms_percent,
            "rms_percent_push": self.rms_percent_push,
            "rms_percent_all_nodes": self.rms_percent_all_nodes,
            "paper_rms_percent_bound": 0.1,
            "max_msd_displacement": float(np.abs(self.msd_displacement[:n]).max()),
            "mesh": {"vertices": n, "faces": len(self.faces), "graph_nodes": len(self.msd_displacement),
                     "spacing_mm": self.spacing, "d_min_mm": self.d_min},
            "force": "out of plane, f = sin(pi (x-x0)/L) sin(pi (y-y0)/W) on mass nodes, 0 on spring nodes",
            "modulus": "uniform E = 1",
            "msd": {
                "model": "unit mass and unit ground spring on every graph node, link springs d_min/d_ij, "
                         "mass-proportional damping critical for the lowest mode, semi-implicit Euler",
                "steps": self.msd.steps, "dt": self.msd.dt, "damping": self.msd.damping,
                "omega_min": self.omega_min, "omega_max_bound": self.omega_max_bound,
                "tol": self.tol, "final_residual": self.msd.residual,
                "final_kinetic_over_strain": self.msd.kinetic_ratio,
            },
            "seconds": self.seconds,
        }


def planar_experiment(nx: int = 41, ny: int = 41, spacing: float = 3.0, *, d_min: float = 1.0,
                      tol: float = 1e-10) -> PlanarResult:
    """Run Fig. 8 (see the module docstring); ``tol`` is the MSD's and the push loop's tolerance."""
    v, f = planar_mesh(nx, ny, spacing)
    g = mesh_graph(v, f)
    n = len(v)
    force = bending_force(v)
    t = local_transfer(g, np.ones(n), d_min)
    sec = {}
    t0 = time.perf_counter()
    c = ForceSolver(t, "direct").solve(force)
    sec["sparse_solve"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    p = push(t, force, tol=tol)
    sec["push"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    integrator = MSDIntegrator(transfer_network(g, d_min))
    full_force = np.concatenate([force, np.zeros(g.n_nodes - n)])
    msd = integrator.run(full_force, tol=tol)
    sec["msd"] = time.perf_counter() - t0
    u = msd.displacement
    return PlanarResult(
        v, f, force, c, p.kept, u,
        rms_percent(c[:n], u[:n]), rms_percent(p.kept[:n], u[:n]), rms_percent(c, u),
        msd, float(integrator.omega_min), float(integrator.omega_max), float(spacing), float(d_min),
        float(tol), sec,
    )


# --------------------------------------------------------------------------- 2. circular (Fig. 9)
@dataclass(frozen=True)
class CircularResult:
    """Fig. 9: a disc with variable E under a unit radial force.

    Attributes
    ----------
    vertices : (n, 3) float
        Disc vertices, mm, plane z = 0, centre first (at the origin).
    faces : (m, 3) int
    moduli : (n,) float
        Young's modulus per vertex (relative units).
    force : (n,) float
        Applied radial force magnitude (1, centre 0).
    radial_displacement : (n,) float
        Kept force ``C`` = displacement along the outward radius (per unit time, M = 1).
    uniform_displacement : (n,) float
        The same with uniform ``E = 1``.
    displacement : (n, 3) float
        ``radial_displacement`` times the unit outward radius (centre 0).
    stiff, soft : (k,) int
        Vertex indices of the stiffest and softest ``fraction`` (centre excluded).
    stiff_to_soft_displacement_ratio : float
        mean radial displacement over ``stiff`` / over ``soft``.
    position_controlled_ratio : float
        The same on ``radial_displacement / uniform_displacement`` (position effects removed).
    min_radial_displacement : float
        Smallest radial displacement over non-centre vertices (> 0: every node moves outward).
    correlation_log_modulus : float
        Spearman correlation of ``log E`` with the position-controlled displacement (< 0: stiffer
        moves less, over all vertices rather than two groups).
    spacing : float
        Ring spacing, mm.
    pattern : str
        ``"lobes"`` or ``"random"`` (:func:`circular_moduli`).
    modulus_range : (float, float)
    fraction : float
        Share of vertices in each of the stiff and soft groups.
    seconds : dict
        Wall time of the two sparse solves.
    """

    vertices: np.ndarray
    faces: np.ndarray
    moduli: np.ndarray
    force: np.ndarray
    radial_displacement: np.ndarray
    uniform_displacement: np.ndarray
    displacement: np.ndarray
    stiff: np.ndarray
    soft: np.ndarray
    stiff_to_soft_displacement_ratio: float
    position_controlled_ratio: float
    min_radial_displacement: float
    correlation_log_modulus: float
    spacing: float
    pattern: str
    modulus_range: tuple[float, float]
    fraction: float
    seconds: dict

    def to_dict(self) -> dict:
        return {
            "stiff_to_soft_displacement_ratio": self.stiff_to_soft_displacement_ratio,
            "position_controlled_ratio": self.position_controlled_ratio,
            "min_radial_displacement": self.min_radial_displacement,
            "all_nodes_move_outward": bool(self.min_radial_displacement > 0),
            "spearman_log_modulus_vs_displacement_ratio": self.correlation_log_modulus,
            "mesh": {"vertices": len(self.vertices), "faces": len(self.faces), "spacing_mm": self.spacing},
            "modulus": {"lobes": "log E linear in cos(2 theta): stiffest along +-x, softest along +-y",
                        "random": "independent log-uniform draws per vertex, seeded"}[self.pattern]
                       + f", E in [{self.modulus_range[0]:g}, {self.modulus_range[1]:g}]",
            "force": "unit force along the outward radius on every vertex (centre: none)",
            "groups": f"stiffest and softest {self.fraction:.0%} of non-centre vertices by E",
            "seconds": self.seconds,
        }


def circular_moduli(vertices: np.ndarray, pattern: str = "lobes", modulus_range: tuple[float, float] = (0.25, 4.0),
                    rng: np.random.Generator | None = None) -> np.ndarray:
    """``E : (n,) float`` per vertex of a disc centred at the origin, within ``modulus_range``.

    ``"lobes"``: smooth in angle, ``log E`` linear in ``cos 2θ`` — stiffest along ±x, softest along
    ±y (the centre gets the geometric mean). ``"random"``: independent log-uniform draws from ``rng``
    (default: seed 2008).
    """
    lo, hi = (float(x) for x in modulus_range)
    if not (0 < lo <= hi and np.isfinite(hi)):
        raise InputError(f"modulus_range must be 0 < low ≤ high, got {modulus_range!r}")
    v = np.asarray(vertices, dtype=float)
    if pattern == "lobes":
        theta = np.arctan2(v[:, 1], v[:, 0])
        w = np.where(np.hypot(v[:, 0], v[:, 1]) > 0, 0.5 + 0.5 * np.cos(2 * theta), 0.5)
    elif pattern == "random":
        w = (np.random.default_rng(2008) if rng is None else rng).uniform(0.0, 1.0, len(v))
    else:
        raise InputError(f"pattern must be 'lobes' or 'random', got {pattern!r}")
    return np.exp(np.log(lo) + w * (np.log(hi) - np.log(lo)))


def circular_experiment(rings: int = 12, spacing: float = 3.0, *, pattern: str = "lobes",
                        modulus_range: tuple[float, float] = (0.25, 4.0), fraction: float = 0.2,
                        d_min: float = 1.0, rng: np.random.Generator | None = None) -> CircularResult:
    """Run Fig. 9 (see the module docstring); moduli from :func:`circular_moduli`."""
    lo, hi = (float(x) for x in modulus_range)
    if not 0 < fraction <= 0.5:
        raise InputError(f"fraction must be in (0, 0.5], got {fraction!r}")
    v, f = circular_mesh(rings, spacing)
    n = len(v)
    g = mesh_graph(v, f)
    e = circular_moduli(v, pattern, modulus_range, rng)
    force = np.ones(n)
    force[0] = 0.0  # centre: no radial direction
    t0 = time.perf_counter()
    c = ForceSolver(local_transfer(g, e, d_min), "direct").solve(force)[:n]
    c1 = ForceSolver(local_transfer(g, np.ones(n), d_min), "direct").solve(force)[:n]
    sec = {"two_sparse_solves": time.perf_counter() - t0}
    r = np.linalg.norm(v[:, :2], axis=1)
    direction = np.zeros_like(v)
    direction[1:, :2] = v[1:, :2] / r[1:, None]
    rim = np.arange(1, n)
    k = max(1, int(round(fraction * len(rim))))
    order = rim[np.argsort(e[rim], kind="stable")]
    soft, stiff = order[:k], order[-k:]
    rel = c / c1

    rho = float(spearmanr(np.log(e[rim]), rel[rim]).statistic)
    return CircularResult(
        v, f, e, force, c, c1, c[:, None] * direction, stiff, soft,
        float(c[stiff].mean() / c[soft].mean()), float(rel[stiff].mean() / rel[soft].mean()),
        float(c[rim].min()), rho, float(spacing), pattern, (lo, hi), float(fraction), sec,
    )


# --------------------------------------------------------------------------- 3. convergence (Fig. 7)
@dataclass(frozen=True)
class ConvergenceResult:
    """Fig. 7: the push loop against MSD integration on the planar problem.

    Attributes
    ----------
    n_nodes : int
        Graph nodes N (mass + spring nodes); one sweep = N node updates.
    tol : float
        Relative residual that counts as converged.
    push_iterations, msd_iterations : int
        Pushes (one node each) and MSD steps (all nodes each) to reach ``tol``.
    push_history : (h,) float
        ``max |P| / max |f|`` sampled ``samples_per_sweep`` times per sweep, down to ``curve_tol``.
    push_history_sweeps : (h,) float
        Where each ``push_history`` entry was taken, in sweeps (pushes / N).
    msd_residual_history, msd_error_history : (s,) float
        MSD ``max |f − K u| / max |f|`` and ``max |u − C| / max |C|`` per step, down to ``curve_tol``.
    seconds : dict
        Wall time of each method to ``tol`` (push kernel compiled beforehand).
    """

    n_nodes: int
    tol: float
    curve_tol: float
    push_iterations: int
    msd_iterations: int
    push_history: np.ndarray
    push_history_sweeps: np.ndarray
    msd_residual_history: np.ndarray
    msd_error_history: np.ndarray
    seconds: dict

    @property
    def push_sweeps(self) -> float:
        return self.push_iterations / self.n_nodes

    @property
    def msd_sweeps(self) -> float:
        return float(self.msd_iterations)

    def to_dict(self) -> dict:
        return {
            "push_iterations": self.push_iterations,
            "msd_iterations": self.msd_iterations,
            "push_sweeps": self.push_sweeps,
            "msd_sweeps": self.msd_sweeps,
            "push_node_updates": self.push_iterations,
            "msd_node_updates": self.msd_iterations * self.n_nodes,
            "push_to_msd_work_ratio": self.push_sweeps / self.msd_sweeps,
            "push_reduction_per_sweep": float(self.tol ** (1.0 / self.push_sweeps)),
            "msd_reduction_per_sweep": float(self.tol ** (1.0 / self.msd_sweeps)),
            "tol": self.tol,
            "curve_tol": self.curve_tol,
            "n_nodes": self.n_nodes,
            "definition": CONVERGENCE_DEFINITION,
            "seconds": self.seconds,
        }


def convergence_experiment(nx: int = 41, ny: int = 41, spacing: float = 3.0, *, d_min: float = 1.0,
                           tol: float = 1e-6, curve_tol: float = 1e-10, samples_per_sweep: int = 20) -> ConvergenceResult:
    """Run Fig. 7 on the planar problem of :func:`planar_experiment` (see the module docstring)."""
    if not 0 < curve_tol <= tol < 1:
        raise InputError(f"need 0 < curve_tol ≤ tol < 1, got tol={tol!r}, curve_tol={curve_tol!r}")
    v, f = planar_mesh(nx, ny, spacing)
    g = mesh_graph(v, f)
    n = g.n_nodes
    force = np.zeros(n)
    force[: len(v)] = bending_force(v)
    t = local_transfer(g, np.ones(len(v)), d_min)
    exact = ForceSolver(t, "direct").solve(force)
    scale = float(np.abs(force).max())
    # curves first (this also compiles / loads the push kernel before it is timed)
    every = max(1, n // int(samples_per_sweep))
    curve = push(t, force, tol=curve_tol, record_every=every)
    integrator = MSDIntegrator(transfer_network(g, d_min))
    msd_curve = integrator.run(force, tol=curve_tol, reference=exact)
    t0 = time.perf_counter()
    p = push(t, force, tol=tol)
    t_push = time.perf_counter() - t0
    t0 = time.perf_counter()
    m = integrator.run(force, tol=tol)
    t_msd = time.perf_counter() - t0
    t0 = time.perf_counter()
    ForceSolver(t, "bicgstab").solve(force)
    t_krylov = time.perf_counter() - t0
    at = np.arange(len(curve.history), dtype=float) * curve.record_every
    at[-1] = curve.pushes  # the kernel appends the final max|P| after the last push
    return ConvergenceResult(
        n, float(tol), float(curve_tol), int(p.pushes), int(m.steps), curve.history / scale, at / n,
        msd_curve.residual_history, msd_curve.error_history,
        {"push": t_push, "msd": t_msd, "bicgstab": t_krylov},
    )


# --------------------------------------------------------------------------- figures
def write_planar_figure(result: PlanarResult, path) -> Path:
    """Fig. 8 as a PNG: (a) the planar mesh, (b) deformed by the transfer model, (c) MSD − transfer."""
    n = len(result.vertices)
    return save_png(planar_figure(result.vertices, result.faces, result.transfer_displacement[:n],
                                  result.msd_displacement[:n], result.rms_percent), path)


def write_circular_figure(result: CircularResult, path) -> Path:
    """Fig. 9 as a PNG: (a) the disc mesh, node size ∝ E; (b) deformed (displacement exaggerated)."""
    return save_png(circular_figure(result.vertices, result.faces, result.moduli, result.displacement,
                                    result.radial_displacement, result.stiff_to_soft_displacement_ratio,
                                    result.position_controlled_ratio), path)


def write_convergence_figure(result: ConvergenceResult, path) -> Path:
    """Fig. 7 as a PNG: relative residual vs sweeps (node updates / N) for both methods, log scale."""
    title = (f"Convergence to {result.tol:g}: push {result.push_sweeps:.1f} sweeps "
             f"({result.push_iterations} pushes), MSD {result.msd_iterations} steps")
    return save_png(convergence_figure(result.push_history_sweeps, result.push_history, result.msd_residual_history,
                                       result.msd_error_history, tol=result.tol, n_nodes=result.n_nodes,
                                       title=title), path)
