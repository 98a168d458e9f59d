"""Bi-stride pooling and the adjacency of the pooled level (thesis §4.2.2, eq. 4.1).

From a seed per connected component, BFS splits each component into frontiers of equal hop
depth. Every mesh edge joins two nodes whose depths differ by at most one, so keeping every
other frontier leaves each dropped node with a kept neighbour (its BFS parent, or any
neighbour of a dropped seed): the pooling is 2-connection-conservative by construction. Kept
nodes within two hops, A_{l+1} = (A_l + I)^2 [K, K] without the diagonal, are joined on the
coarse level; every kept node at depth k >= 2 is then joined to its BFS grandparent, and the
depth-1 nodes (when the odd frontiers are kept) to each other through the seed, so each
component stays connected and no edge ever joins two components.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bsms.graph import native
from bsms.graph.bfs import bfs_depths, off_diagonal_pattern

__all__ = ["bistride_pool", "coarse_adjacency", "closed_rows"]


def bistride_pool(adjacency: sp.csr_matrix, labels: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Kept nodes: per component, the even or the odd BFS frontiers from its seed.

    adjacency: (N, N) symmetric CSR; labels: (N,) component of each node, in [0, C);
    seeds: (C,) one node of each component -> (K,) int64 sorted kept node indices.
    Per component the parity with fewer nodes is kept; ties, and one-node components,
    keep the even frontiers (which hold the seed).
    """
    n_components = seeds.size
    odd = bfs_depths(adjacency, seeds) % 2 == 1
    n_odd = np.bincount(labels, weights=odd, minlength=n_components)
    n_even = np.bincount(labels, minlength=n_components) - n_odd
    keep_odd = (n_odd > 0) & (n_odd < n_even)
    return np.flatnonzero(odd == keep_odd[labels]).astype(np.int64)


def closed_rows(adjacency: sp.csr_matrix, kept: np.ndarray) -> sp.csr_matrix:
    """Rows ``kept`` of the closed neighbourhood matrix A + I: (K, N) boolean CSR, sorted indices.

    Boolean so that products of it are pattern-only (scipy adds booleans with OR), which
    moves an eighth of the bytes of float64 through the sparse products.
    """
    shape = (kept.size, adjacency.shape[0])
    loops = sp.csr_matrix((np.ones(kept.size), (np.arange(kept.size), kept)), shape=shape)
    rows = (adjacency[kept] + loops).tocsr()
    rows.sort_indices()
    return sp.csr_matrix((np.ones(rows.nnz, dtype=bool), rows.indices, rows.indptr), shape=shape)


def coarse_adjacency(closed: sp.csr_matrix) -> sp.csr_matrix:
    """Adjacency of the pooled level: kept pairs within two hops, (K, K) 0/1 CSR, no diagonal.

    closed: (K, N) rows of A + I at the kept nodes (:func:`closed_rows`). The product
    R R^T = (A + I)^2 [K, K] never forms the square on all nodes. Compiled bitset rows
    (:func:`bsms.graph.native.pooled_adjacency`) where a compiler is found, else scipy's product;
    the same matrix either way.
    """
    pooled = native.pooled_adjacency(closed)
    return off_diagonal_pattern(closed @ closed.T) if pooled is None else pooled
