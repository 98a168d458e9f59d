"""Simplices, and the checks that make arrays a usable mesh.

Measures and quality of simplices, and the validation a :class:`datagen.mesh.Mesh` runs on
construction (:func:`check_cells`): array shapes and index ranges, unused nodes, degenerate
and inverted cells, cells repeated over the same nodes, and coincident nodes (copies of one
point that cut a mesh apart). Errors name the first offending cells or nodes.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

__all__ = [
    "MeshError", "SIMPLEX_TYPES", "name_first", "signed_measures", "simplex_quality", "cell_max_edge",
    "as_nodes", "as_cells", "check_cells", "coincident_nodes", "merge_coincident_nodes",
]

SIMPLEX_TYPES = {1: "line", 2: "triangle", 3: "tetra"}
_MEASURE_WORDS = {1: "length", 2: "area", 3: "volume"}
_DEGENERATE_RTOL = 1e-12
_COINCIDENT_RTOL = 1e-8  # nodes closer than this times the median cell size are one point
_NAMED = 5  # how many offending cells/nodes an error message lists


class MeshError(ValueError):
    """A mesh (arrays or file) that cannot be used; the message names the problem."""


def name_first(indices: np.ndarray, what: str) -> str:
    """The offenders for an error message: 'cells [3, 8, 9]' or 'cells [3, 8, 9, 10, 11] and 40 more'."""
    indices = np.asarray(indices).ravel()
    shown = ", ".join(str(int(i)) for i in indices[:_NAMED])
    more = indices.size - _NAMED
    return f"{what} [{shown}]" + (f" and {more} more" if more > 0 else "")


def signed_measures(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed length/area/volume of each simplex: ``det([x1-x0, ..., xd-x0]) / d!``.

    nodes: (N, d), cells: (C, d+1) -> (C,). Positive for positively oriented cells.
    """
    d = nodes.shape[1]
    corner = nodes[cells[:, 0]]
    spans = nodes[cells[:, 1:]] - corner[:, None, :]  # (C, d, d), rows are edge vectors
    return np.linalg.det(spans) / math.factorial(d)


def cell_max_edge(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Longest edge of each simplex, (C,)."""
    k = cells.shape[1]
    longest = np.zeros(len(cells))
    for a in range(k):
        for b in range(a + 1, k):
            longest = np.maximum(longest, np.linalg.norm(nodes[cells[:, a]] - nodes[cells[:, b]], axis=1))
    return longest


def simplex_quality(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(C,) |measure| over that of the regular simplex with the same RMS edge length."""
    d, k = nodes.shape[1], cells.shape[1]
    squares = sum(
        ((nodes[cells[:, a]] - nodes[cells[:, b]]) ** 2).sum(axis=1)
        for a in range(k) for b in range(a + 1, k)
    )
    rms = np.sqrt(squares / (k * (k - 1) / 2))
    regular = {1: 1.0, 2: math.sqrt(3) / 4, 3: 1 / (6 * math.sqrt(2))}[d]
    return np.abs(signed_measures(nodes, cells)) / (regular * rms**d)


def as_nodes(nodes) -> np.ndarray:
    try:
        arr = np.array(nodes, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"mesh nodes must be a numeric (N, d) array: {exc}") from None
    if arr.ndim != 2 or arr.shape[1] not in (1, 2, 3) or arr.shape[0] == 0:
        raise MeshError(
            f"mesh nodes must have shape (N, d) with N >= 1 and d in 1, 2, 3; got shape {arr.shape}"
        )
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
    if bad.size:
        raise MeshError(f"non-finite coordinates (NaN or inf) at {name_first(bad, 'nodes')}")
    return arr


def as_cells(cells, n_nodes: int, dim: int) -> np.ndarray:
    arr = np.asarray(cells)
    if arr.dtype == bool or not (np.issubdtype(arr.dtype, np.integer) or arr.size == 0):
        raise MeshError(f"mesh cells must be an integer array of node indices; got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[0] == 0:
        raise MeshError(f"mesh cells must have shape (C, d+1) with C >= 1; got shape {arr.shape}")
    if arr.shape[1] != dim + 1:
        raise MeshError(
            f"wrong cell arity: cells have {arr.shape[1]} nodes each, but nodes have {dim} "
            f"coordinates, so each cell must be a {SIMPLEX_TYPES[dim]} with {dim + 1} nodes"
        )
    arr = arr.astype(np.int64)
    bad = np.flatnonzero(((arr < 0) | (arr >= n_nodes)).any(axis=1))
    if bad.size:
        raise MeshError(f"node indices out of range [0, {n_nodes}) in {name_first(bad, 'cells')}")
    return arr


def _duplicate_cells(cells: np.ndarray) -> np.ndarray:
    """(k, 2) pairs (first, copy) of cells over the same node set, in any order."""
    keys = np.sort(cells, axis=1)
    order = np.lexsort(keys.T[::-1])
    same = np.flatnonzero((keys[order[1:]] == keys[order[:-1]]).all(axis=1))
    return np.stack([order[same], order[same + 1]], axis=1)


def coincident_nodes(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(k, 2) pairs (i < j) of used nodes closer than ``_COINCIDENT_RTOL`` times the median
    longest cell edge: copies of one point that leave the mesh cut along them."""
    used = np.unique(cells)
    tol = _COINCIDENT_RTOL * float(np.median(cell_max_edge(nodes, cells)))
    pairs = cKDTree(nodes[used]).query_pairs(tol, output_type="ndarray")
    pairs = np.sort(used[pairs], axis=1)
    return pairs[np.lexsort(pairs.T[::-1])]


def merge_coincident_nodes(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """``cells`` with every node of a group of coincident nodes (:func:`coincident_nodes`)
    replaced by the group's smallest index; the other copies become unused."""
    pairs = coincident_nodes(nodes, cells)
    n = len(nodes)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = csgraph.connected_components(graph, directed=False)
    first = np.full(labels.max() + 1, n)
    np.minimum.at(first, labels, np.arange(n))
    return first[labels][cells]


def _check_distinct(nodes: np.ndarray, cells: np.ndarray) -> None:
    """MeshError for cells repeated over the same nodes or nodes that are copies of one point."""
    copies = _duplicate_cells(cells)
    if len(copies):
        shown = ", ".join(f"{a} and {b}" for a, b in copies[:_NAMED])
        raise MeshError(f"duplicate cells: {len(copies)} cells repeat another over the same nodes (cells {shown}"
                        f"{' ...' if len(copies) > _NAMED else ''}); remove the copies (re-export the mesh)")
    pairs = coincident_nodes(nodes, cells)
    if len(pairs):
        shown = ", ".join(f"{a} and {b}" for a, b in pairs[:_NAMED])
        raise MeshError(
            f"coincident nodes: {len(pairs)} pairs of nodes lie at the same point (nodes {shown}"
            f"{' ...' if len(pairs) > _NAMED else ''}), so the mesh is cut along them into separate pieces; "
            "merge them in the mesher (gmsh: Coherence Mesh) and re-export, or build with "
            "Mesh.read(path, merge_coincident=True) / Mesh.from_arrays(..., merge_coincident=True)")


def check_cells(nodes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The (C,) signed measures of a mesh's cells, or MeshError for a mesh that cannot be used:
    nodes no cell uses, degenerate or inverted cells, repeated cells, coincident nodes.

    nodes (N, d) and cells (C, d+1) as :func:`as_nodes` and :func:`as_cells` return them.
    """
    used = np.zeros(len(nodes), dtype=bool)
    used[cells.ravel()] = True
    if not used.all():
        raise MeshError(
            f"{name_first(np.flatnonzero(~used), 'nodes')} are used by no cell; remove them "
            "(Mesh.from_arrays(..., drop_unused=True) does)"
        )
    measures = signed_measures(nodes, cells)
    tol = _DEGENERATE_RTOL * cell_max_edge(nodes, cells) ** nodes.shape[1]
    degenerate = np.flatnonzero(np.abs(measures) <= tol)
    if degenerate.size:
        raise MeshError(
            f"degenerate cells (zero {_MEASURE_WORDS[nodes.shape[1]]}): {name_first(degenerate, 'cells')}"
        )
    inverted = np.flatnonzero(measures < 0)
    if inverted.size:
        raise MeshError(
            f"inverted cells (negative signed {_MEASURE_WORDS[nodes.shape[1]]}): "
            f"{name_first(inverted, 'cells')}, {inverted.size} of {len(cells)} cells; "
            "if the mesh is valid but its cells are ordered inconsistently, build it with "
            "Mesh.from_arrays(..., orient=True) or Mesh.read(path, orient=True)"
        )
    _check_distinct(nodes, cells)
    return measures
