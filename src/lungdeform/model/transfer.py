"""Force transfer between graph nodes: the local estimate (8)–(9) and the Green's matrix (7), (10)–(11).

Reading chosen (docs/METHOD_NOTES.md §3): ``S_i = 1/E_i`` for a mass node and ``S_i = E_i`` for a spring node;
``clique(j)`` is j's graph neighbours plus j itself; ``d(l, j) = max(|x_l − x_j|, d_min)`` with
``d_min = 1`` mm, and the self distance is ``d_min``. Then

    T_e[j→i] = (S_i / d(j, i)) / Σ_{l ∈ clique(j)} S_l / d(l, j),   i ∈ clique(j),

so each row ``j`` of ``T_e`` sums to 1: ``T_e[j→j]`` is the share node j keeps, the rest is handed
to its neighbours. Extending T_e along paths, (10)–(11), is the same operator as the push iteration
applied to a unit force, so :func:`green_matrix` materialises it by a dense solve (small meshes only).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from lungdeform.errors import InputError

from .graph import SpringGraph
from .stiffness import node_moduli

#: Largest graph for which dense matrices are built (N × N float64 = 200 MB at 5000 nodes).
DENSE_LIMIT = 5000


def compliance(moduli: np.ndarray, n_mass: int) -> np.ndarray:
    """``S : (N,) float``: 1/E on mass nodes (0..n_mass-1), E on spring nodes (paper, after (8))."""
    e = np.asarray(moduli, dtype=float)
    s = e.copy()
    s[:n_mass] = 1.0 / e[:n_mass]
    return s


def local_transfer(graph: SpringGraph, mass_moduli: np.ndarray, d_min: float = 1.0) -> sparse.csr_matrix:
    """The local transfer estimate ``T_e``, (8)–(9).

    Parameters
    ----------
    graph : SpringGraph
    mass_moduli : (n,) float
        Young's modulus per mass node (relative units); spring nodes take the mean of their ends.
    d_min : float
        Smallest distance, mm (paper: 1).

    Returns
    -------
    T : (N, N) CSR, row-stochastic, ``T[j, i] = T_e[j→i]``, diagonal stored explicitly.
    """
    if not d_min > 0:
        raise InputError(f"d_min must be > 0 mm, got {d_min!r}")
    n = graph.n_nodes
    s = compliance(node_moduli(mass_moduli, graph.spring_ends), graph.n_mass)
    adj = graph.adjacency.tocoo()
    rows = np.concatenate([adj.row, np.arange(n)])
    cols = np.concatenate([adj.col, np.arange(n)])
    dist = np.linalg.norm(graph.positions[rows] - graph.positions[cols], axis=1)
    dist = np.maximum(dist, d_min)
    dist[len(adj.row):] = d_min  # self distance
    w = s[cols] / dist
    row_sum = np.bincount(rows, weights=w, minlength=n)
    t = sparse.csr_matrix((w / row_sum[rows], (rows, cols)), shape=(n, n))
    t.sum_duplicates()
    t.sort_indices()
    return t


def split_transfer(t: sparse.csr_matrix) -> tuple[np.ndarray, sparse.csr_matrix]:
    """``(keep (N,), Q (N, N) CSR)``: the diagonal share kept and the off-diagonal part handed on."""
    keep = t.diagonal().copy()
    q = (t - sparse.diags(keep)).tocsr()
    q.eliminate_zeros()
    return keep, q


def green_matrix(t: sparse.csr_matrix) -> np.ndarray:
    """Dense Green's matrix ``G : (N, N)``, ``G[i, j]`` = force kept at i for a unit force at j.

    The fixed point of the push iteration (12)–(14) (docs/METHOD_NOTES.md §4): ``C = diag(keep) (I − Qᵀ)⁻¹ f``, so
    ``G = diag(keep) (I − Qᵀ)⁻¹``. Column sums are 1 (force is conserved). Small graphs only.
    """
    n = t.shape[0]
    if n > DENSE_LIMIT:
        raise InputError(f"green_matrix is for small graphs (≤ {DENSE_LIMIT} nodes), got {n}")
    keep, q = split_transfer(t)
    a = np.eye(n) - q.T.toarray()
    return keep[:, None] * np.linalg.solve(a, np.eye(n))


def full_transfer(t: sparse.csr_matrix, kept: np.ndarray, applied: np.ndarray) -> sparse.csr_matrix:
    """Equation (7): ``T[j→i] = (F[j] / f[j]) · T_e[j→i]`` once the kept force F is known.

    ``kept : (N,) float`` (F), ``applied : (N,) float`` (f); rows with ``f[j] = 0`` are zero.
    """
    f = np.asarray(applied, dtype=float)
    ratio = np.divide(kept, f, out=np.zeros_like(f), where=f != 0)
    return sparse.diags(ratio) @ t
