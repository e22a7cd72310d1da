"""The spring-node graph (paper Sec. III-E): node and link counts, numbering, positions, bad input."""

import numpy as np
import pytest

from lungdeform.errors import InputError
from lungdeform.geometry.mesh import icosphere, unique_edges
from lungdeform.model.graph import spring_graph


def _graph(k=2, r=60.0):
    s = icosphere(k, r)
    return s, spring_graph(s.vertices, s.edges)


def _torus(m=8, k=6, big=50.0, small=20.0):
    """A closed genus-1 triangle mesh by hand: an ``m × k`` grid of quads on a torus, two triangles
    each (V = mk, F = 2mk, E = 3mk)."""
    u, w = np.meshgrid(np.arange(m) * 2 * np.pi / m, np.arange(k) * 2 * np.pi / k, indexing="ij")
    v = np.stack([(big + small * np.cos(w)) * np.cos(u), (big + small * np.cos(w)) * np.sin(u),
                  small * np.sin(w)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(m), np.arange(k), indexing="ij")
    a, b = i * k + j, ((i + 1) % m) * k + j
    c, d = ((i + 1) % m) * k + (j + 1) % k, i * k + (j + 1) % k
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, faces


def test_graph_counts_and_links():
    s, g = _graph()
    # n mass nodes + one spring node per edge; each spring node links to its two mass nodes.
    assert g.n_nodes == s.n_vertices + len(s.edges)
    assert g.adjacency.nnz == 4 * len(s.edges)
    deg = np.asarray(g.adjacency.sum(axis=1)).ravel()
    assert np.all(deg[g.n_mass:] == 2)
    assert np.allclose(g.positions[g.n_mass:], s.vertices[s.edges].mean(axis=1))


@pytest.mark.parametrize("k", [0, 1, 3])
def test_closed_sphere_counts_follow_euler(k):
    # Truth: an icosphere of k subdivisions has V = 10·4^k + 2 vertices, E = 30·4^k edges and
    # F = 20·4^k faces (each subdivision: E → 4E, F → 4F, V → V + E), and a closed genus-0
    # triangle mesh has V − E + F = 2 with 3F = 2E. The graph has V mass nodes, E spring nodes,
    # 2E links (two per spring node) and the mass-node degrees sum to 2E.
    s, g = _graph(k)
    v, e, f = 10 * 4**k + 2, 30 * 4**k, 20 * 4**k
    assert (s.n_vertices, len(s.edges), len(s.faces)) == (v, e, f)
    assert v - e + f == 2 and 3 * f == 2 * e
    assert (g.n_mass, g.n_spring, g.n_nodes) == (v, e, v + e)
    assert g.links.shape == (2 * e, 2)
    deg = np.asarray(g.adjacency.sum(axis=1)).ravel()
    assert deg[: g.n_mass].sum() == 2 * e
    # the twelve icosahedron corners keep valence 5, every other vertex has valence 6
    assert np.count_nonzero(deg[: g.n_mass] == 5) == 12
    assert np.count_nonzero(deg[: g.n_mass] == 6) == v - 12


def test_closed_torus_counts_follow_euler():
    # Truth: the hand-built torus has V = 48, F = 96, E = 144 (each quad adds 3 edges), Euler
    # characteristic V − E + F = 0 (genus 1); every vertex has valence 6, so each mass node links
    # to 6 spring nodes.
    v, faces = _torus()
    edges = unique_edges(faces)[0]
    assert (len(v), len(edges), len(faces)) == (48, 144, 96)
    assert len(v) - len(edges) + len(faces) == 0
    g = spring_graph(v, edges)
    assert (g.n_mass, g.n_spring) == (48, 144)
    deg = np.asarray(g.adjacency.sum(axis=1)).ravel()
    assert np.all(deg[: g.n_mass] == 6) and np.all(deg[g.n_mass:] == 2)


def test_numbering_and_bipartite_links():
    # Numbering (graph module docstring): mass nodes 0..n-1 are the vertices in order, spring node
    # n + k sits on edge k; mass nodes meet only through spring nodes (no mass–mass or
    # spring–spring link), and the adjacency is symmetric without self loops.
    s, g = _graph(1)
    n = g.n_mass
    assert np.array_equal(g.positions[:n], s.vertices)
    adj = g.adjacency.toarray()
    assert np.array_equal(adj, adj.T) and np.all(np.diag(adj) == 0)
    assert not adj[:n, :n].any() and not adj[n:, n:].any()
    for k, (a, b) in enumerate(s.edges):
        assert set(np.flatnonzero(adj[n + k])) == {a, b}


def test_single_triangle_by_hand():
    # One triangle (0, 0, 0), (2, 0, 0), (0, 2, 0): three mass nodes, three spring nodes at the
    # edge midpoints (1, 0, 0), (1, 1, 0), (0, 1, 0) for the edges (0, 1), (1, 2), (0, 2).
    v = np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 2.0, 0]])
    g = spring_graph(v, np.array([[0, 1], [1, 2], [0, 2]]))
    assert (g.n_mass, g.n_spring, g.n_nodes) == (3, 3, 6)
    assert np.allclose(g.positions[3:], [[1, 0, 0], [1, 1, 0], [0, 1, 0]])
    assert sorted(map(tuple, g.links.tolist())) == [(0, 3), (0, 5), (1, 3), (1, 4), (2, 4), (2, 5)]


def test_bad_edges_are_refused():
    # each refusal names the parameter and what was expected
    v = np.zeros((3, 3))
    with pytest.raises(InputError, match=r"edges must have shape \(e, 2\)"):
        spring_graph(v, np.array([0, 1, 2]))
    with pytest.raises(InputError, match="outside 0..2"):
        spring_graph(v, np.array([[0, 3]]))
    with pytest.raises(InputError, match="self loop"):
        spring_graph(v, np.array([[1, 1]]))
