"""Force distribution: the Pitcher/Catcher push iteration (12)–(14) and its sparse fixed point.

Push iteration (paper Sec. III-G; docs/METHOD_NOTES.md §4). Pitcher ``P`` (force still to hand on) starts at the
applied force on mass nodes and 0 on spring nodes; Catcher ``C`` (force kept) starts at 0. Repeat:
take the node ``i`` with the largest ``|P|``; ``C[i] += P[i]·T_e[i→i]``; ``P[j] += P[i]·T_e[i→j]``
for each neighbour; ``P[i] = 0``; stop when ``max |P| ≤ tol · max |f|``. Invariant:
``ΣC + ΣP = Σf`` (force is conserved), checked by the kernel. (The paper takes the largest ``P``; we
take the largest magnitude so that signed forces, e.g. from an inverse fit, are handled too.)

Fixed point: with ``Q`` the off-diagonal part of ``T_e``, ``x = f + Qᵀx``, i.e. ``(I − Qᵀ) x = f``
and ``C = diag(T_e[i→i]) x``. ``Q`` is strictly sub-stochastic, so the system is non-singular; a
Krylov solver gives the same ``C`` far faster. :class:`ForceSolver` factorises/prepares once and
solves for many applied forces; the linear solver is a choice (``"bicgstab"``, ``"gmres"``,
``"direct"`` or any callable ``(A, b) -> x``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np
from scipy import sparse
from scipy.sparse import linalg as spla

from lungdeform.errors import ConvergenceError, InputError

from .transfer import split_transfer


# --------------------------------------------------------------------------- push loop
@numba.njit(cache=True)
def _sift_up(heap, pos, key, k):
    node = heap[k]
    while k > 0:
        parent = (k - 1) >> 1
        if key[heap[parent]] >= key[node]:
            break
        heap[k] = heap[parent]
        pos[heap[k]] = k
        k = parent
    heap[k] = node
    pos[node] = k


@numba.njit(cache=True)
def _sift_down(heap, pos, key, k):
    n = heap.shape[0]
    node = heap[k]
    while True:
        child = 2 * k + 1
        if child >= n:
            break
        if child + 1 < n and key[heap[child + 1]] > key[heap[child]]:
            child += 1
        if key[heap[child]] <= key[node]:
            break
        heap[k] = heap[child]
        pos[heap[k]] = k
        k = child
    heap[k] = node
    pos[node] = k


@numba.njit(cache=True)
def _push_kernel(indptr, indices, data, keep, f, stop, max_pushes, record_every):
    """Indexed max-heap on |P|. Returns (C, P, pushes, history of max|P| every record_every pushes)."""
    n = f.shape[0]
    pitcher = f.copy()
    catcher = np.zeros(n)
    key = np.abs(pitcher)
    heap = np.arange(n)
    pos = np.arange(n)
    for k in range(n // 2 - 1, -1, -1):
        _sift_down(heap, pos, key, k)
    n_hist = min(max_pushes // record_every + 2, 65536)
    history = np.empty(n_hist)
    h = 0
    pushes = 0
    while pushes < max_pushes:
        i = heap[0]
        if key[i] <= stop:
            break
        if pushes % record_every == 0:
            if h == n_hist - 1:  # full: keep every second sample, record half as often
                for k in range(h // 2):
                    history[k] = history[2 * k]
                h = h // 2
                record_every *= 2
            if pushes % record_every == 0:
                history[h] = key[i]
                h += 1
        p = pitcher[i]
        catcher[i] += p * keep[i]
        pitcher[i] = 0.0
        key[i] = 0.0
        _sift_down(heap, pos, key, 0)
        for ptr in range(indptr[i], indptr[i + 1]):
            j = indices[ptr]
            if j == i:
                continue
            pitcher[j] += p * data[ptr]
            new = abs(pitcher[j])
            old = key[j]
            key[j] = new
            if new > old:
                _sift_up(heap, pos, key, pos[j])
            else:
                _sift_down(heap, pos, key, pos[j])
        pushes += 1
    history[h] = key[heap[0]]
    h += 1
    return catcher, pitcher, pushes, history[:h], record_every


@dataclass(frozen=True)
class PushResult:
    """Result of :func:`push`.

    Attributes
    ----------
    kept : (N,) float
        Catcher: force kept per node (the elastostatic force F on mass nodes).
    remaining : (N,) float
        Pitcher left when the loop stopped (≤ tol · max|f| everywhere).
    pushes : int
        Number of push steps.
    history : (h,) float
        ``max |P|`` every ``record_every`` pushes (the convergence curve, paper Fig. 7); at most
        65 536 samples (``record_every`` doubles whenever the buffer fills).
    record_every : int
    conservation_error : float
        ``|ΣC + ΣP − Σf| / Σ|f|`` at the end.
    """

    kept: np.ndarray
    remaining: np.ndarray
    pushes: int
    history: np.ndarray
    record_every: int
    conservation_error: float


def push(
    transfer: sparse.csr_matrix,
    applied: np.ndarray,
    *,
    tol: float = 1e-10,
    max_pushes: int | None = None,
    record_every: int = 1,
) -> PushResult:
    """Run the Pitcher/Catcher iteration (12)–(14) to ``max |P| ≤ tol · max |f|``.

    Parameters
    ----------
    transfer : (N, N) CSR
        ``T_e`` from :func:`lungdeform.model.transfer.local_transfer` (row j = what j hands on).
    applied : (N,) or (n_mass,) float
        Applied force; a shorter vector is padded with zeros (spring nodes start at 0).
    Raises :class:`ConvergenceError` if ``max_pushes`` is reached first or conservation fails.
    """
    t = sparse.csr_matrix(transfer)
    n = t.shape[0]
    f = _pad(applied, n)
    scale = float(np.abs(f).max()) if len(f) else 0.0
    if max_pushes is None:
        max_pushes = max(1000, 2000 * n)
    record_every = max(1, int(record_every))
    keep = t.diagonal().astype(np.float64)
    c, p, pushes, hist, record_every = _push_kernel(
        t.indptr.astype(np.int64), t.indices.astype(np.int64), t.data.astype(np.float64),
        keep, f, tol * scale, int(max_pushes), record_every,
    )
    denom = float(np.abs(f).sum()) or 1.0
    cons = abs(c.sum() + p.sum() - f.sum()) / denom
    if cons > 1e-9:
        raise ConvergenceError(f"push iteration lost force: relative conservation error {cons:.3g}")
    if np.abs(p).max(initial=0.0) > tol * scale:
        raise ConvergenceError(
            f"push iteration did not reach tol={tol:g} within {max_pushes} pushes "
            f"(max remaining {np.abs(p).max() / scale:.3g} of max force)"
        )
    return PushResult(c, p, int(pushes), hist, record_every, cons)


# --------------------------------------------------------------------------- sparse solve
LinearSolver = Callable[[sparse.csr_matrix, np.ndarray], np.ndarray]


class ForceSolver:
    """Solve the push iteration's fixed point for many applied forces; prepare once.

    Parameters
    ----------
    transfer : (N, N) CSR
        ``T_e``.
    method : "bicgstab" | "gmres" | "direct" | callable
        The linear solver for ``(I − Qᵀ) x = f``. A callable gets ``(A, b)`` and returns ``x``.
    n_mass : int, optional
        Number of mass nodes (numbered first). When given and the graph has no mass–mass or
        spring–spring links (the spring-node graph), spring nodes are eliminated exactly and the
        linear solve runs over the mass nodes only.
    tol : float
        Relative residual tolerance for the Krylov methods.
    maxiter : int
        Iteration cap; reaching it raises :class:`ConvergenceError`.
    """

    def __init__(
        self,
        transfer: sparse.csr_matrix,
        method: str | LinearSolver = "bicgstab",
        *,
        n_mass: int | None = None,
        tol: float = 1e-12,
        maxiter: int = 5000,
    ):
        t = sparse.csr_matrix(transfer)
        self.n_nodes = t.shape[0]
        self.keep, q = split_transfer(t)
        if np.any(self.keep <= 0):
            raise InputError("transfer has a node that keeps no force (zero diagonal)")
        self.method = method
        self.tol = float(tol)
        self.maxiter = int(maxiter)
        self._lu = None
        self.last_iterations = 0
        self.n_mass = None
        if n_mass is not None and 0 < n_mass < self.n_nodes:
            m = int(n_mass)
            q_mm, q_ss = q[:m, :m], q[m:, m:]
            if q_mm.nnz == 0 and q_ss.nnz == 0:
                # Spring-node elimination (exact): with no mass–mass or spring–spring links,
                # x_S = f_S + Q_MSᵀ x_M, so (I − Q_SMᵀ Q_MSᵀ) x_M = f_M + Q_SMᵀ f_S: a system over
                # the mass nodes only (¼ of the unknowns, about half the non-zeros).
                self.n_mass = m
                self._q_ms_t = q[:m, m:].T.tocsr()  # (S, M)
                self._q_sm_t = q[m:, :m].T.tocsr()  # (M, S)
                reduced = (self._q_sm_t @ self._q_ms_t).tocsr()
                self.matrix = (sparse.identity(m, format="csr") - reduced).tocsr()
        if self.n_mass is None:
            self.matrix = (sparse.identity(self.n_nodes, format="csr") - q.T).tocsr()

    def solve(self, applied: np.ndarray) -> np.ndarray:
        """Kept force ``C : (N,) float`` for applied force ``f : (N,)`` or ``(n_mass,)``."""
        f = _pad(applied, self.n_nodes)
        if not np.any(f):
            return np.zeros(self.n_nodes)
        if self.n_mass is None:
            x = self._solve_linear(f)
        else:
            m = self.n_mass
            x_m = self._solve_linear(f[:m] + self._q_sm_t @ f[m:])
            x = np.concatenate([x_m, f[m:] + self._q_ms_t @ x_m])
        return self.keep * x

    def solve_many(self, applied: np.ndarray) -> np.ndarray:
        """``(k, N)`` kept forces for ``(k, N)`` or ``(k, n_mass)`` applied forces."""
        return np.stack([self.solve(f) for f in np.atleast_2d(applied)])

    def _solve_linear(self, b: np.ndarray) -> np.ndarray:
        a = self.matrix
        if callable(self.method):
            x = np.asarray(self.method(a, b), dtype=float)
        elif self.method == "direct":
            if self._lu is None:
                self._lu = spla.splu(a.tocsc())
            x = self._lu.solve(b)
        elif self.method in ("bicgstab", "gmres"):
            x = self._krylov(b)
        else:
            raise InputError(f"method must be 'bicgstab', 'gmres', 'direct' or a callable, got {self.method!r}")
        residual = np.linalg.norm(a @ x - b) / np.linalg.norm(b)
        if not np.isfinite(residual) or residual > max(1e3 * self.tol, 1e-8):
            raise ConvergenceError(f"force solve ({self.method}) residual {residual:.3g} above tolerance")
        return x

    def _krylov(self, b: np.ndarray) -> np.ndarray:
        count = [0]

        def tick(_):
            count[0] += 1

        # Jacobi is the identity here (Q has a zero diagonal); the system is well conditioned
        # because Q is strictly sub-stochastic, so plain Krylov converges in tens of iterations.
        if self.method == "bicgstab":
            x, info = spla.bicgstab(self.matrix, b, x0=b.copy(), rtol=self.tol, atol=0.0,
                                    maxiter=self.maxiter, callback=tick)
        else:
            x, info = spla.gmres(self.matrix, b, x0=b.copy(), rtol=self.tol, atol=0.0, restart=50,
                                 maxiter=self.maxiter, callback=tick, callback_type="pr_norm")
        self.last_iterations = count[0]
        if info != 0:
            raise ConvergenceError(
                f"force solve ({self.method}) did not converge in {self.maxiter} iterations (info={info})"
            )
        return x


def solve_force(
    transfer: sparse.csr_matrix, applied: np.ndarray, method: str | LinearSolver = "bicgstab", **kwargs
) -> np.ndarray:
    """One-shot: kept force ``C : (N,)`` for one applied force (see :class:`ForceSolver`)."""
    return ForceSolver(transfer, method, **kwargs).solve(applied)


def _pad(applied: np.ndarray, n: int) -> np.ndarray:
    f = np.asarray(applied, dtype=np.float64).ravel()
    if len(f) > n:
        raise InputError(f"applied force has {len(f)} entries, the graph has only {n} nodes")
    if not np.all(np.isfinite(f)):
        raise InputError("applied force contains NaN or infinity")
    out = np.zeros(n)
    out[: len(f)] = f
    return out
