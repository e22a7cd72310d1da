"""A mass–spring–damper (MSD) network integrated in time to rest: the paper's yardstick (Sec. IV-A).

The paper validates its transfer model against a mass–spring–damper simulation (Figs. 7–8). This
module is that simulation: a real time integration, not a linear solve.

Model. ``N`` point masses with scalar displacement ``u`` (e.g. out of plane), each tied to its rest
position by a *ground* spring ``g_i`` and a dashpot, and linked to others by springs ``k_ij``:

    m_i ü_i + c·m_i u̇_i + g_i u_i + Σ_j k_ij (u_i − u_j) = f_i ,

i.e. ``M ü + c M u̇ + K u = f`` with ``K = diag(g) + L_k`` (``L_k`` the weighted graph Laplacian).
Damping is mass-proportional (one rate ``c`` for every node). ``u`` may also be ``(N, k)``: the
columns are independent scalar problems sharing ``K`` (linearised, small displacements).

Integrator: semi-implicit (symplectic) Euler with the damping term taken implicitly,

    v ← (v + dt·(f − K u)/m) / (1 + dt·c),   u ← u + dt·v,

one sparse product per step. For a mode of angular frequency ω this is stable for
``dt·ω < sqrt(2(2 + dt·c))``; we take ``dt = safety · 2 / ω_max`` with ``ω_max`` bounded above by
Gershgorin (``ω_max² ≤ max_i (g_i + 2 Σ_j k_ij) / m_i``), so every mode is stable.
The run stops at rest: relative residual force ``max|f − K u| / max|f| ≤ tol`` *and* kinetic energy
``½ vᵀM v ≤ tol² · ½ uᵀK u`` (the strain energy). Otherwise :class:`ConvergenceError`.

How the MSD parameters are chosen (so that it is the *same* physics as the transfer model). Write
the push iteration's fixed point (docs/METHOD_NOTES.md §4) as ``C = diag(t) x`` with ``(I − Qᵀ) x = f``,
``t = diag(T_e)``. Eliminating ``x`` gives ``K C = f`` with ``K_ii = 1/t_i`` and
``K_ij = −T_e[j→i] / t_j``. With ``d(l, j) = max(dist, d_min)`` and the compliance ``S`` (1/E on mass
nodes, E on spring nodes), ``T_e[j→i] / t_j = (d_min / d_ij) · S_i / S_j``. When ``S`` is the same on
every node — uniform ``E = 1`` (any other uniform E gives 1/E on mass and E on spring nodes, which is
*not* uniform) — ``K = I + L`` with link weights ``k_ij = d_min / d_ij``: exactly the stiffness matrix
of a network in which every node (mass and spring nodes) has a unit ground spring and each graph
link is a spring of stiffness ``d_min / d_ij``. :func:`transfer_network` builds that network; with
unit masses and damping critical for the lowest mode (``c = 2 ω_min``), integrated to rest, it must
agree with the transfer model (displacement ∝ F, M = 1) up to the integration tolerance.
For heterogeneous E, ``K_ij / K_ji = (S_i / S_j)²``: ``K`` is not symmetric, so no MSD with the same
applied forces reproduces it exactly (``K`` is similar to an SPD matrix, ``K = D A D⁻¹`` with
``D = diag(S)``, but mapping it to springs needs per-node force rescaling ``f / S²``).

Residuals are comparable: after the push loop has handed on ``x_k`` from each node, its Pitcher is
``P = f − (I − Qᵀ) x_k``; the MSD residual is ``f − K u = f − (I − Qᵀ) diag(1/t) u``. With
``u = diag(t) x`` both are the residual of the same linear system, so ``max|P|`` and
``max|f − K u|`` can be plotted on one axis (paper Fig. 7).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as spla

from lungdeform.errors import ConvergenceError, InputError
from lungdeform.model.graph import SpringGraph

#: Below this many nodes the lowest frequency is found with a dense eigen-solver.
DENSE_EIGEN_LIMIT = 400

#: A relative residual above this means the integration is unstable.
BLOW_UP = 1e30


@dataclass(frozen=True, eq=False)
class SpringNetwork:
    """A linear mass–spring network with ground springs.

    Attributes
    ----------
    links : (L, 2) int
        Node pairs joined by a spring (each pair once, no self links).
    stiffness : (L,) float
        Spring stiffness per link, force per unit displacement (relative units), > 0.
    ground : (N,) float
        Stiffness of each node's spring to its rest position, ≥ 0 (the network must still be
        anchored: ``K`` positive definite).
    mass : (N,) float
        Node masses, > 0.
    """

    links: np.ndarray
    stiffness: np.ndarray
    ground: np.ndarray
    mass: np.ndarray

    @property
    def n_nodes(self) -> int:
        return len(self.mass)

    @cached_property
    def stiffness_matrix(self) -> sparse.csr_matrix:
        """``K : (N, N)`` CSR, symmetric: ``diag(ground)`` plus the weighted graph Laplacian."""
        a, b = self.links[:, 0], self.links[:, 1]
        k = self.stiffness
        n = self.n_nodes
        rows = np.concatenate([a, b, a, b, np.arange(n)])
        cols = np.concatenate([b, a, a, b, np.arange(n)])
        vals = np.concatenate([-k, -k, k, k, self.ground])
        m = sparse.csr_matrix((vals, (rows, cols)), shape=(n, n))
        m.sum_duplicates()
        m.sort_indices()
        return m

    def static_displacement(self, force: np.ndarray) -> np.ndarray:
        """The exact rest state ``K⁻¹ f`` by a sparse direct solve (a reference, not the MSD)."""
        f = _as_force(force, self.n_nodes)
        return spla.splu(self.stiffness_matrix.tocsc()).solve(f)


def spring_network(links, stiffness, ground, mass=1.0) -> SpringNetwork:
    """Validate and bundle a network (see :class:`SpringNetwork`); ``mass`` may be a scalar."""
    ground = np.ascontiguousarray(ground, dtype=np.float64)
    if ground.ndim != 1:
        raise InputError(f"ground must have shape (N,), got {ground.shape}")
    n = len(ground)
    lk = np.ascontiguousarray(links, dtype=np.int64).reshape(-1, 2) if np.size(links) else np.zeros((0, 2), np.int64)
    k = np.ascontiguousarray(stiffness, dtype=np.float64).ravel()
    if len(k) != len(lk):
        raise InputError(f"stiffness must have one value per link ({len(lk)}), got {len(k)}")
    if lk.size and (lk.min() < 0 or lk.max() >= n):
        raise InputError(f"links index a node outside 0..{n - 1}")
    if np.any(lk[:, 0] == lk[:, 1]):
        raise InputError("links contain a self link")
    if not (np.all(np.isfinite(k)) and np.all(k > 0)):
        raise InputError("stiffness must be finite and > 0 on every link")
    if not (np.all(np.isfinite(ground)) and np.all(ground >= 0)) or not np.any(ground > 0):
        raise InputError("ground stiffness must be finite, ≥ 0, and > 0 somewhere (the network must be anchored)")
    m = np.broadcast_to(np.asarray(mass, dtype=np.float64), (n,)).copy()
    if not (np.all(np.isfinite(m)) and np.all(m > 0)):
        raise InputError("mass must be finite and > 0")
    return SpringNetwork(lk, k, ground, m)


def transfer_network(graph: SpringGraph, d_min: float = 1.0, mass: float = 1.0) -> SpringNetwork:
    """The MSD equivalent of the transfer model for uniform ``E = 1`` (see the module docstring).

    Every graph node (mass and spring nodes) gets a unit ground spring and mass ``mass``; every graph
    link a spring of stiffness ``d_min / d_ij``, ``d_ij = max(|x_i − x_j|, d_min)`` (mm), exactly as
    :func:`lungdeform.model.transfer.local_transfer` measures distances. At rest, ``u = K⁻¹ f`` equals the
    kept force ``C`` of the push iteration with ``T_e = local_transfer(graph, 1, d_min)``.
    """
    if not d_min > 0:
        raise InputError(f"d_min must be > 0 mm, got {d_min!r}")
    links = graph.links
    dist = np.linalg.norm(graph.positions[links[:, 0]] - graph.positions[links[:, 1]], axis=1)
    k = d_min / np.maximum(dist, d_min)
    return spring_network(links, k, np.ones(graph.n_nodes), mass)


def lowest_frequency(network: SpringNetwork) -> float:
    """``ω_min``: square root of the smallest eigenvalue of ``K`` relative to ``M`` (rad per time unit)."""
    k = network.stiffness_matrix
    m = network.mass
    if network.n_nodes <= DENSE_EIGEN_LIMIT:
        s = 1.0 / np.sqrt(m)
        lam = float(np.linalg.eigvalsh(s[:, None] * k.toarray() * s[None, :])[0])
    else:
        vals = spla.eigsh(k.tocsc(), k=1, M=sparse.diags(m).tocsc(), sigma=0.0, which="LM",
                          return_eigenvectors=False)
        lam = float(vals[0])
    if not lam > 0:
        raise InputError("the spring network is not anchored (its stiffness matrix is singular)")
    return float(np.sqrt(lam))


def highest_frequency_bound(network: SpringNetwork) -> float:
    """Upper bound of ``ω_max`` by Gershgorin: ``sqrt(max_i (g_i + 2 Σ_j k_ij) / m_i)``."""
    n = network.n_nodes
    a, b = network.links[:, 0], network.links[:, 1]
    deg = np.bincount(a, weights=network.stiffness, minlength=n) + np.bincount(
        b, weights=network.stiffness, minlength=n
    )
    return float(np.sqrt(np.max((network.ground + 2.0 * deg) / network.mass)))


@dataclass(frozen=True)
class MSDResult:
    """The state of an MSD run at rest.

    Attributes
    ----------
    displacement : (N,) or (N, k) float
        Displacement at rest (same unit as force / stiffness).
    velocity : (N,) or (N, k) float
        Final velocity (≈ 0).
    steps : int
        Time steps taken (each updates every node once: one sweep).
    time : float
        Simulated time, ``steps · dt``.
    dt, damping : float
        Time step and mass-proportional damping rate ``c`` used.
    residual : float
        Final ``max|f − K u| / max|f|``.
    kinetic_ratio : float
        Final kinetic energy over strain energy.
    residual_history : (steps + 1,) float
        ``max|f − K u| / max|f|`` before the first step and after each step.
    error_history : (steps + 1,) float or None
        ``max|u − u_ref| / max|u_ref|`` per step when a reference was given.
    converged : bool
        Always True when returned (a run that does not settle raises :class:`ConvergenceError`).
    """

    displacement: np.ndarray
    velocity: np.ndarray
    steps: int
    time: float
    dt: float
    damping: float
    residual: float
    kinetic_ratio: float
    residual_history: np.ndarray
    error_history: np.ndarray | None
    converged: bool = True


class MSDIntegrator:
    """Integrate ``M ü + c M u̇ + K u = f`` to rest; choose ``dt`` and ``c`` once, run many forces.

    Parameters
    ----------
    network : SpringNetwork
    dt : float, optional
        Time step; default ``safety · 2 / ω_max`` (Gershgorin bound), stable for every mode.
    damping : float, optional
        Mass-proportional damping rate ``c`` (1 / time); default ``2 ω_min``: critical damping of
        the lowest mode, the slowest to settle.
    safety : float
        Fraction of the stability limit used for the default ``dt`` (0 < safety < 1).
    """

    def __init__(self, network: SpringNetwork, *, dt: float | None = None, damping: float | None = None,
                 safety: float = 0.9):
        if not 0 < safety < 1:
            raise InputError(f"safety must be in (0, 1), got {safety!r}")
        self.network = network
        self.matrix = network.stiffness_matrix
        self.omega_max = highest_frequency_bound(network)
        self.omega_min = lowest_frequency(network) if damping is None else None
        self.dt = float(dt) if dt is not None else safety * 2.0 / self.omega_max
        self.damping = float(damping) if damping is not None else 2.0 * self.omega_min
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise InputError(f"dt must be a finite time step > 0, got {dt!r}")
        if not (np.isfinite(self.damping) and self.damping >= 0):
            raise InputError(f"damping must be finite and ≥ 0, got {damping!r}")

    def run(
        self,
        force: np.ndarray,
        *,
        tol: float = 1e-10,
        max_steps: int = 100_000,
        reference: np.ndarray | None = None,
        progress: Callable[[int, float], None] | None = None,
    ) -> MSDResult:
        """Start at rest (``u = v = 0``), integrate until at rest under ``force``.

        ``force : (N,) or (N, k) float``. ``reference``: the exact rest state, to record the
        displacement error per step (for convergence plots). Raises :class:`ConvergenceError` when
        ``max_steps`` pass first or the state blows up.
        """
        n = self.network.n_nodes
        f = _as_force(force, n)
        if not tol > 0:
            raise InputError(f"tol must be > 0, got {tol!r}")
        scale = float(np.abs(f).max()) if f.size else 0.0
        u = np.zeros_like(f)
        v = np.zeros_like(f)
        hist_r = [1.0 if scale > 0 else 0.0]
        ref = None
        hist_e = None
        if reference is not None:
            ref = _as_force(reference, n)
            if ref.shape != f.shape:
                raise InputError(f"reference must have shape {f.shape}, got {ref.shape}")
            ref_scale = float(np.abs(ref).max()) or 1.0
            hist_e = [1.0 if np.any(ref) else 0.0]
        if scale == 0:
            return MSDResult(u, v, 0, 0.0, self.dt, self.damping, 0.0, 0.0, np.array(hist_r),
                             None if hist_e is None else np.array(hist_e))
        m = self.network.mass if f.ndim == 1 else self.network.mass[:, None]
        dt, beta = self.dt, 1.0 / (1.0 + self.dt * self.damping)
        k = self.matrix
        r = f.copy()  # f − K u at u = 0
        steps = 0
        while True:
            v = (v + dt * r / m) * beta
            u = u + dt * v
            ku = k @ u
            r = f - ku
            steps += 1
            res = float(np.abs(r).max()) / scale
            if not res <= BLOW_UP:  # also catches NaN; long before float overflow
                raise ConvergenceError(
                    f"mass–spring–damper blew up at step {steps} (residual {res:.3g}; dt={dt:g} too large?)"
                )
            kinetic = 0.5 * float(np.sum(m * v * v))
            strain = 0.5 * float(np.sum(u * ku))
            hist_r.append(res)
            if hist_e is not None:
                hist_e.append(float(np.abs(u - ref).max()) / ref_scale)
            if progress is not None:
                progress(steps, res)
            if res <= tol and kinetic <= tol * tol * strain:
                break
            if steps >= max_steps:
                raise ConvergenceError(
                    f"mass–spring–damper did not settle within {max_steps} steps "
                    f"(residual {res:.3g}, kinetic/strain {kinetic / max(strain, 1e-300):.3g}, tol {tol:g})"
                )
        return MSDResult(
            u, v, steps, steps * dt, dt, self.damping, res, kinetic / max(strain, 1e-300),
            np.array(hist_r), None if hist_e is None else np.array(hist_e),
        )


def integrate_to_rest(network: SpringNetwork, force: np.ndarray, *, tol: float = 1e-10,
                      max_steps: int = 100_000, dt: float | None = None,
                      damping: float | None = None) -> MSDResult:
    """One-shot: :class:`MSDIntegrator` ``(network, dt, damping).run(force, tol, max_steps)``."""
    return MSDIntegrator(network, dt=dt, damping=damping).run(force, tol=tol, max_steps=max_steps)


def _as_force(force, n: int) -> np.ndarray:
    f = np.ascontiguousarray(force, dtype=np.float64)
    if f.ndim not in (1, 2) or f.shape[0] != n:
        raise InputError(f"force must have shape ({n},) or ({n}, k) (one row per node), got {f.shape}")
    if not np.all(np.isfinite(f)):
        raise InputError("force contains NaN or infinity")
    return f
