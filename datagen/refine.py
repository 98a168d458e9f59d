"""Uniform refinement of a simplicial mesh by midpoint subdivision.

Each edge gets a node at its midpoint; a triangle becomes four (its three corners and the
middle one), a tetrahedron eight (four at its corners, the inner octahedron cut along its
shortest diagonal into four), a segment two. Every child is similar to, or no worse than, its
parent, so the mesh's quality is kept while its spacing halves. The mesh's own nodes come
first, in their order, so that anything computed on the refined mesh is read at the original
nodes as its first ``n_nodes`` rows (:func:`refine_to` relies on it to report on a user's mesh).
"""

from __future__ import annotations

import math

import numpy as np

from datagen.mesh import Mesh

__all__ = ["subdivide", "subdivisions_for", "refine_to"]

# Local edges of a simplex of 2, 3 and 4 nodes, in the order their midpoints are numbered below.
_EDGES = {2: [(0, 1)], 3: [(0, 1), (1, 2), (2, 0)], 4: [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]}


def subdivide(mesh: Mesh) -> Mesh:
    """``mesh`` with every cell split at its edges' midpoints (2D: 4 children, 3D: 8, 1D: 2);
    its nodes first, then one node per edge. The total measure is unchanged."""
    cells = mesh.cells
    k = cells.shape[1]
    local = _EDGES[k]
    pairs = np.sort(np.concatenate([cells[:, [a, b]] for a, b in local]), axis=1)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    mid = mesh.n_nodes + inverse.reshape(len(local), -1).T  # (C, edges per cell)
    nodes = np.concatenate([mesh.nodes, mesh.nodes[edges].mean(axis=1)])
    c = [cells[:, i] for i in range(k)]
    m = [mid[:, i] for i in range(len(local))]
    if k == 2:
        children = [(c[0], m[0]), (m[0], c[1])]
    elif k == 3:  # m: 01, 12, 20
        children = [(c[0], m[0], m[2]), (m[0], c[1], m[1]), (m[2], m[1], c[2]), (m[0], m[1], m[2])]
    else:  # m: 01, 02, 03, 12, 13, 23
        children = [(c[0], m[0], m[1], m[2]), (m[0], c[1], m[3], m[4]), (m[1], m[3], c[2], m[5]),
                    (m[2], m[4], m[5], c[3])]
        children += _octahedron(nodes, m)
    new_cells = np.concatenate([np.stack(child, axis=1) for child in children])
    return Mesh.from_arrays(nodes, new_cells, orient=k == 4)


def _octahedron(nodes: np.ndarray, m: list[np.ndarray]) -> list[tuple]:
    """The inner octahedron of each tetrahedron (vertices: its six edge midpoints) as four
    tetrahedra around its shortest diagonal (the three diagonals join opposite edges' midpoints:
    01-23, 02-13, 03-12). Orientation is fixed by the caller."""
    diagonals = [(m[0], m[5]), (m[1], m[4]), (m[2], m[3])]
    # the four midpoints around each diagonal, in cyclic order
    rings = [(m[1], m[3], m[4], m[2]), (m[0], m[3], m[5], m[2]), (m[0], m[1], m[5], m[4])]
    lengths = np.stack([np.linalg.norm(nodes[a] - nodes[b], axis=1) for a, b in diagonals], axis=1)
    pick = np.argmin(lengths, axis=1)
    out = []
    for j in range(4):
        parts = []
        for (a, b), ring in zip(diagonals, rings, strict=True):
            parts.append(np.stack([a, b, ring[j], ring[(j + 1) % 4]], axis=1))
        chosen = np.choose(pick[:, None], parts)
        out.append(tuple(chosen.T))
    return out


def subdivisions_for(mesh: Mesh, spacing: float) -> int:
    """How many subdivisions bring the median edge length of ``mesh`` to at most sqrt(2) times
    ``spacing`` (each halves it): 0 where it already is (a mesh as fine or finer is kept)."""
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    ratio = float(np.median(mesh.edge_lengths)) / spacing
    return max(0, math.ceil(math.log2(ratio) - 0.5)) if ratio > math.sqrt(2) else 0


def refine_to(mesh: Mesh, spacing: float) -> tuple[Mesh, int]:
    """``mesh`` subdivided :func:`subdivisions_for` times, and that number."""
    times = subdivisions_for(mesh, spacing)
    for _ in range(times):
        mesh = subdivide(mesh)
    return mesh, times
