"""Breadth-first search on unweighted graphs, vectorised through scipy.sparse.csgraph.

All graphs here are symmetric CSR adjacency matrices without self-loops whose stored values
are ignored (only the pattern counts). Hop distances are int64; -1 marks "unreachable".
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

__all__ = ["adjacency_from_edges", "cell_adjacency", "off_diagonal_pattern", "bfs_depths", "distance_sums"]


def _unique_pairs(edges: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected pairs (lo < hi) sorted by (lo, hi), from (E, 2) pairs."""
    lo = np.minimum(edges[:, 0], edges[:, 1])
    hi = np.maximum(edges[:, 0], edges[:, 1])
    keys = lo[lo != hi] * n_nodes + hi[lo != hi]
    keys.sort()
    keys = keys[np.concatenate([[True], keys[1:] != keys[:-1]])] if keys.size else keys
    return np.divmod(keys, n_nodes)


def adjacency_from_edges(edges: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """Symmetric 0/1 CSR adjacency (n_nodes, n_nodes) from undirected pairs.

    edges: (E, 2) int node pairs in any order and direction; duplicates and self-pairs are
    dropped. The result has sorted indices and no diagonal. Row r lists its smaller
    neighbours (pairs with hi = r, ordered by lo) and then its larger ones (pairs with
    lo = r, ordered by hi), so two sorts of the unique pairs place every entry directly;
    this is several times faster than scipy's COO conversion or np.unique at 1M edges.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    lo, hi = _unique_pairs(edges, n_nodes)
    smaller_row, smaller = np.divmod(np.sort(hi * n_nodes + lo), n_nodes)  # pairs by (hi, lo)
    n_smaller = np.bincount(hi, minlength=n_nodes)
    n_larger = np.bincount(lo, minlength=n_nodes)
    indptr = np.zeros(n_nodes + 1, dtype=np.int64)
    np.cumsum(n_smaller + n_larger, out=indptr[1:])
    rank = np.arange(lo.size)
    indices = np.empty(2 * lo.size, dtype=np.int32 if n_nodes < 2**31 else np.int64)
    indices[indptr[smaller_row] + rank - (np.cumsum(n_smaller) - n_smaller)[smaller_row]] = smaller
    indices[indptr[lo] + n_smaller[lo] + rank - (np.cumsum(n_larger) - n_larger)[lo]] = hi
    return sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(n_nodes, n_nodes))


def cell_adjacency(cells: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """Adjacency through shared simplices: cells (C, k) node indices -> (N, N) 0/1 CSR."""
    k = cells.shape[1]
    pairs = np.concatenate([cells[:, [a, b]] for a in range(k) for b in range(a + 1, k)])
    return adjacency_from_edges(pairs, n_nodes)


def off_diagonal_pattern(matrix: sp.spmatrix) -> sp.csr_matrix:
    """0/1 CSR pattern of a symmetric square ``matrix`` without its diagonal, sorted indices.

    ``matrix`` must hold no duplicate entries (scipy sums and products do not). Sorting is
    one transposition, a counting sort, instead of scipy's per-row sort: for a symmetric
    matrix the column-major arrays are the row-major ones.
    """
    by_column = matrix.tocsc()
    n = matrix.shape[0]
    row_of = np.repeat(np.arange(n), np.diff(by_column.indptr))
    keep = (by_column.indices != row_of) & (by_column.data != 0)
    indices = by_column.indices[keep]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(row_of[keep], minlength=n))])
    return sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(n, n))


def _with_super_source(adjacency: sp.csr_matrix, sources: np.ndarray) -> sp.csr_matrix:
    """(N+1, N+1) directed pattern: the graph plus a node N with an arc to every source."""
    n = adjacency.shape[0]
    indptr = np.concatenate([adjacency.indptr, [adjacency.indptr[-1] + sources.size]])
    indices = np.concatenate([adjacency.indices, sources.astype(adjacency.indices.dtype)])
    return sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(n + 1, n + 1))


def bfs_depths(adjacency: sp.csr_matrix, sources) -> np.ndarray:
    """Hop distance of every node to the nearest of ``sources`` (multi-source BFS).

    adjacency: (N, N) symmetric CSR; sources: int or (S,) node indices -> (N,) int64, -1 for
    nodes no source reaches. One csgraph traversal (a virtual node linked to all sources);
    the frontier boundaries are read off the BFS order, in which parent positions never
    decrease, so depths need no Python loop over nodes.
    """
    sources = np.unique(np.atleast_1d(np.asarray(sources, dtype=np.int64)))
    n = adjacency.shape[0]
    if sources.size == 1:
        graph, start = adjacency, int(sources[0])
    else:
        graph, start = _with_super_source(adjacency, sources), n
    order, parent = csgraph.breadth_first_order(graph, start, directed=True, return_predecessors=True)
    position = np.empty(graph.shape[0], dtype=np.int64)
    position[order] = np.arange(order.size)
    parent_position = position[parent[order[1:]]]  # non-decreasing along the BFS order
    ends = [1]  # frontier k occupies order[ends[k-1]:ends[k]]
    while ends[-1] < order.size:
        ends.append(1 + int(np.searchsorted(parent_position, ends[-1], side="left")))
    depth = np.full(graph.shape[0], -1, dtype=np.int64)
    depth[order] = np.repeat(np.arange(len(ends)), np.diff([0, *ends]))
    if graph is adjacency:
        return depth
    depth = depth[:n]
    depth[depth > 0] -= 1
    return depth


def distance_sums(adjacency: sp.csr_matrix) -> np.ndarray:
    """Exact sum of hop distances from each node to all nodes of its component.

    adjacency: (N, N) symmetric CSR in which every node has at least one neighbour
    -> (N,) int64. All-sources BFS with bitsets: row v holds the set of nodes within k hops
    of v; one step ORs the rows of v's neighbours into it, and
    sum_j d(v, j) = sum_k (|component| - |ball_k(v)|). Time O(diameter * nnz * N / 64),
    memory O(nnz * N / 64) bytes: meant for components of a few thousand nodes.
    """
    n = adjacency.shape[0]
    words = (n + 63) // 64
    node = np.arange(n)
    balls = np.zeros((n, words), dtype=np.uint64)
    balls[node, node // 64] = np.left_shift(np.uint64(1), (node % 64).astype(np.uint64))
    starts = adjacency.indptr[:-1]
    sizes = [np.ones(n, dtype=np.int64)]
    while True:
        balls = balls | np.bitwise_or.reduceat(balls[adjacency.indices], starts, axis=0)
        size = np.bitwise_count(balls).sum(axis=1, dtype=np.int64)
        if np.array_equal(size, sizes[-1]):
            break
        sizes.append(size)
    final = sizes[-1]
    return len(sizes) * final - np.sum(sizes, axis=0)
