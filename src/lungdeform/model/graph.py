"""The spring-node graph of the model (paper Sec. III-E; docs/METHOD_NOTES.md §2).

Mass node = mesh vertex. Spring node = one per mesh edge, at the edge midpoint. Graph links join
each spring node to its two mass nodes; mass nodes meet only through spring nodes.

Node numbering everywhere: mass nodes ``0 .. n-1`` (the mesh vertices, in order), then spring nodes
``n .. n+e-1`` (one per edge, in the order of ``edges``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import sparse

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import as_vertices


@dataclass(frozen=True, eq=False)
class SpringGraph:
    """The mass/spring node graph.

    Attributes
    ----------
    positions : (N, 3) float
        Node positions, mm, same frame as the mesh vertices; mass nodes first, then spring nodes.
    n_mass : int
        Number of mass nodes ``n`` (mesh vertices).
    spring_ends : (e, 2) int
        The two mass nodes of each spring node (spring node ``n + k`` sits on edge ``k``).
    """

    positions: np.ndarray
    n_mass: int
    spring_ends: np.ndarray

    @property
    def n_nodes(self) -> int:
        return len(self.positions)

    @property
    def n_spring(self) -> int:
        return len(self.spring_ends)

    @cached_property
    def links(self) -> np.ndarray:
        """``(2e, 2) int`` graph links ``(mass node, spring node)``."""
        spring = self.n_mass + np.arange(self.n_spring)
        return np.concatenate(
            [np.stack([self.spring_ends[:, 0], spring], 1), np.stack([self.spring_ends[:, 1], spring], 1)]
        )

    @cached_property
    def adjacency(self) -> sparse.csr_matrix:
        """``(N, N)`` symmetric 0/1 adjacency of the links (no self loops), CSR, sorted indices."""
        a, b = self.links[:, 0], self.links[:, 1]
        n = self.n_nodes
        adj = sparse.csr_matrix(
            (np.ones(2 * len(a)), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(n, n)
        )
        adj.sort_indices()
        return adj


def spring_graph(vertices: np.ndarray, edges: np.ndarray) -> SpringGraph:
    """Build the spring-node graph of a mesh.

    Parameters
    ----------
    vertices : (n, 3) float
        Mass-node positions, mm (any frame; 2-D meshes use z = 0).
    edges : (e, 2) int
        Undirected mesh edges (each once), e.g. :attr:`lungdeform.geometry.mesh.Surface.edges`.
    """
    v = as_vertices(vertices)
    e = np.ascontiguousarray(edges, dtype=np.int64)
    if e.ndim != 2 or e.shape[1] != 2:
        raise InputError(f"edges must have shape (e, 2), got {e.shape}")
    if e.size and (e.min() < 0 or e.max() >= len(v)):
        raise InputError(f"edges index a vertex outside 0..{len(v) - 1}")
    if np.any(e[:, 0] == e[:, 1]):
        raise InputError("edges contain a self loop")
    mid = 0.5 * (v[e[:, 0]] + v[e[:, 1]])
    pos = np.ascontiguousarray(np.vstack([v, mid]))
    return SpringGraph(pos, len(v), e)
