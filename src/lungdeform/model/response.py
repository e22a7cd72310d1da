"""Force → response: the one sequence from an applied force to the elastostatic force it leaves on
each mass node (paper Sec. III-E to III-G).

The sequence: the spring-node graph of the surface (:mod:`~lungdeform.model.graph`, Sec. III-E),
the local transfer ``T_e`` with the stiffness field ((8)–(9), :mod:`~lungdeform.model.transfer`),
the fixed point of the push iteration ((12)–(14), :class:`~lungdeform.model.solve.ForceSolver`,
spring nodes eliminated exactly), and the kept force ``C`` read at the mass nodes (the response
``F`` of ``u = k·F·d``). :class:`ResponseSolver` does the first three once per (surface, stiffness)
and then answers any number of applied forces; :func:`solve_response` is the one-shot form. Every
caller (model build, fit objective, stiffness fit) goes through here, so one tolerance applies.

Tolerance policy: :data:`RESPONSE_TOL`. A caller that needs another one passes ``tol``.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from lungdeform.geometry.mesh import Surface

from .graph import SpringGraph, spring_graph
from .solve import ForceSolver, LinearSolver
from .stiffness import as_moduli, uniform
from .transfer import local_transfer

#: Relative residual ``‖(I − Qᵀ)x − f‖ / ‖f‖`` at which every force → response solve stops. Why
#: 1e-12: the system is well conditioned (``Q`` is strictly sub-stochastic), so a Krylov solve gets
#: there in tens of iterations (a few more than at 1e-10), and the response is then exact to far
#: below anything a figure or a fit can see; it is the tightest tolerance any caller used (the
#: model build, whose stored files therefore stay byte-identical).
RESPONSE_TOL = 1e-12

#: Iteration budget of the Krylov solve. Tens of iterations suffice (see :data:`RESPONSE_TOL`):
#: reaching this many means a broken transfer, reported as :class:`ConvergenceError`.
MAX_ITERATIONS = 5000


class ResponseSolver:
    """Responses ``F`` at the mass nodes to applied forces, for one graph and stiffness field.

    Parameters
    ----------
    graph : SpringGraph
        The spring-node graph (:func:`~lungdeform.model.graph.spring_graph`); reuse one graph for
        several stiffness fields (see :meth:`from_surface` to build it from a surface).
    stiffness : (n,) float
        Young's modulus per mass node (relative units), finite and > 0.
    d_min : float
        Smallest transfer distance, mm (paper: 1).
    method : "bicgstab" | "gmres" | "direct" | callable
        The linear solver (:class:`~lungdeform.model.solve.ForceSolver`); a callable gets
        ``(A, b)`` and returns ``x``.
    tol : float
        Relative residual tolerance (default :data:`RESPONSE_TOL`; give another only with a reason).
    maxiter : int
        Krylov iteration budget (default :data:`MAX_ITERATIONS`).

    Raises :class:`~lungdeform.errors.InputError` for a bad stiffness or ``d_min`` and
    :class:`~lungdeform.errors.ConvergenceError` from :meth:`response` when a solve does not reach
    ``tol`` within ``maxiter`` iterations.

    Attributes
    ----------
    graph : SpringGraph
    stiffness : (n,) float
    transfer : (N, N) CSR
        ``T_e`` of (8)–(9), row-stochastic (for the inverse force of a fit).
    """

    def __init__(self, graph: SpringGraph, stiffness: np.ndarray, *, d_min: float = 1.0,
                 method: str | LinearSolver = "bicgstab", tol: float = RESPONSE_TOL,
                 maxiter: int = MAX_ITERATIONS):
        self.graph = graph
        self.stiffness = as_moduli(stiffness, graph.n_mass)
        self.transfer: sparse.csr_matrix = local_transfer(graph, self.stiffness, d_min)
        self._solver = ForceSolver(self.transfer, method, n_mass=graph.n_mass, tol=tol, maxiter=maxiter)

    @classmethod
    def from_surface(cls, surface: Surface, stiffness: np.ndarray | None = None, **kwargs) -> "ResponseSolver":
        """The solver of a closed ``surface`` (mass nodes = its vertices, mm); ``stiffness``
        ``(n,) float`` defaults to uniform 1; other keywords as the constructor."""
        e = uniform(surface.n_vertices) if stiffness is None else stiffness
        return cls(spring_graph(surface.vertices, surface.edges), e, **kwargs)

    @property
    def n_mass(self) -> int:
        """Number of mass nodes ``n`` (the surface's vertices)."""
        return self.graph.n_mass

    @property
    def last_iterations(self) -> int:
        """Krylov iterations of the last solve (0 for ``"direct"`` and callables)."""
        return self._solver.last_iterations

    def kept(self, applied: np.ndarray) -> np.ndarray:
        """``C : (N,) float``, the force kept at every graph node (mass nodes, then spring nodes),
        for ``applied : (n,) float`` on the mass nodes (spring nodes start at 0) or ``(N,) float``
        on all graph nodes. Force is conserved: ``ΣC = Σf``."""
        return self._solver.solve(applied)

    def response(self, applied: np.ndarray) -> np.ndarray:
        """``F : (n,) float``, the force kept at each mass node (:meth:`kept` read at the mass
        nodes), for ``applied : (n,)`` or ``(N,) float``."""
        return self.kept(applied)[: self.n_mass]

    def responses(self, applied: np.ndarray) -> np.ndarray:
        """``(k, n) float``: :meth:`response` of each row of ``applied : (k, n)`` or ``(k, N)``
        (e.g. the four fields of :func:`~lungdeform.model.force.field_basis`)."""
        return np.stack([self.response(f) for f in np.atleast_2d(applied)])


def solve_response(surface: Surface, applied: np.ndarray, stiffness: np.ndarray | None = None,
                   **kwargs) -> np.ndarray:
    """One-shot :class:`ResponseSolver`: ``F : (n,)`` for ``applied : (n,)``, or ``(k, n)`` for
    ``(k, n)``, on ``surface`` with ``stiffness : (n,)`` (default uniform 1); keywords as
    :class:`ResponseSolver` (``d_min``, ``method``, ``tol``, ``maxiter``)."""
    solver = ResponseSolver.from_surface(surface, stiffness, **kwargs)
    f = np.asarray(applied, dtype=float)
    return solver.responses(f) if f.ndim == 2 else solver.response(f)
