"""Compiled loops of the bi-stride hierarchy (``csrc/graph.c``), built on first use.

Two loops dominate a 3D hierarchy once its coarse levels densify (a million-tetrahedron box:
mean degree ~1,000 on level 4): the pooled adjacency R R^T of every coarse level and the
breadth-first searches of MinAve seeding. Here

- :func:`pooled_adjacency` builds each row of R R^T from the kept nodes its neighbours touch:
  on sparse levels one by one (a bitset drops repeats, a short sort orders them), on dense
  levels (where a row's K/64 words cost less than a neighbour's kept nodes one by one) as
  bitsets OR-ed a cache line at a time over column blocks of 512 kept nodes, read out in order.
  Both count first and then write, so nothing of the size of the dense matrix is allocated
  (first-touch page faults of large transient arrays cost more than the loops on some VMs);
- :func:`multi_source_sums` runs breadth-first search from 64 sources at once, a bit per
  source in a word per node (one sweep over the adjacency per hop), and returns the distance
  sums that MinAve needs: per node over the sources, and per source over the nodes.

A third loop serves every frame rather than the hierarchy: :func:`coarse_images` carries
contact edges one level down (eq. 4.1), five times per press frame, at less than half numpy's
cost (numpy sorts every candidate pair; here the pairs of one node share their images first).

All return exactly what the scipy/csgraph/numpy code returns (tests compare them on meshes with
several components); the callers use that code where no compiler is found or ``BSMS_NATIVE=0``.
Built by :func:`datagen.compiled.build`.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from datagen import compiled

__all__ = ["library", "pooled_adjacency", "multi_source_sums", "coarse_images"]

SOURCE = Path(__file__).with_name("csrc") / "graph.c"
_DENSE_RATIO = 8  # dense when a row's words are fewer than 8x the kept nodes a neighbour touches


@functools.cache
def library() -> ctypes.CDLL | None:
    """The compiled library, or None where it cannot be built (the scipy code runs instead)."""
    lib = compiled.build(SOURCE, "compiled bi-stride loops", "the hierarchy is built by scipy, several times slower")
    if lib is None:
        return None
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    lib.bsms_pooled_sparse.argtypes = [i64] + [ptr] * 7
    lib.bsms_pooled_sparse.restype = ctypes.c_int
    lib.bsms_pooled_dense.argtypes = [i64, i64] + [ptr] * 7
    lib.bsms_pooled_dense.restype = ctypes.c_int
    lib.bsms_multi_bfs.argtypes = [i64, ptr, ptr, i64, ptr, ptr, ptr]
    lib.bsms_multi_bfs.restype = ctypes.c_int
    lib.bsms_coarse_images.argtypes = [i64, ptr, ptr, ptr, ptr, i64, i64, ptr, ptr]
    lib.bsms_coarse_images.restype = i64
    return lib


def _int64(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array, dtype=np.int64)


def _address(array: np.ndarray | None) -> int | None:
    return None if array is None else array.ctypes.data


def pooled_adjacency(closed: sp.csr_matrix, dense: bool | None = None) -> sp.csr_matrix | None:
    """(K, K) 0/1 CSR of kept pairs within two hops, sorted int32 indices, no diagonal; None
    without the library. closed: (K, N) rows of A + I at the kept nodes, sorted indices
    (:func:`bsms.graph.pooling.closed_rows`). dense: force the dense or the sparse rows
    (default: the cheaper one by the count of bits each costs)."""
    lib = library()
    if lib is None:
        return None
    n_kept, n_nodes = closed.shape
    reach = closed.T.tocsr()
    reach.sort_indices()
    if dense is None:
        words = -(-n_kept // 64)
        touched = reach.nnz / max(n_nodes, 1)  # kept nodes per closed neighbourhood: bits set one by one
        dense = words < _DENSE_RATIO * touched
    c_ptr, c_idx, r_ptr, r_idx = (_int64(a) for a in (closed.indptr, closed.indices, reach.indptr, reach.indices))
    build = lib.bsms_pooled_dense if dense else lib.bsms_pooled_sparse
    head = (n_kept, n_nodes) if dense else (n_kept,)
    arrays = tuple(_address(a) for a in (c_ptr, c_idx, r_ptr, r_idx))
    counts = np.empty(n_kept, dtype=np.int64)
    if build(*head, *arrays, counts.ctypes.data, None, None):
        raise MemoryError(f"pooled adjacency of {n_kept} kept nodes: out of memory")
    indptr = np.zeros(n_kept + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    if indptr[-1] >= 2**31:
        return None  # int32 indices would overflow: scipy's product
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    if build(*head, *arrays, None, indptr.ctypes.data, indices.ctypes.data):
        raise MemoryError(f"pooled adjacency of {n_kept} kept nodes: out of memory")
    return sp.csr_matrix((np.ones(indices.size), indices, indptr.astype(np.int32)), shape=(n_kept, n_kept))


def multi_source_sums(adjacency: sp.csr_matrix, sources) -> tuple[np.ndarray, np.ndarray] | None:
    """Hop distance sums of a connected graph from ``sources``; None without the library.

    adjacency: (N, N) symmetric CSR, connected; sources: (S,) distinct node indices ->
    (node_sums (N,) int64: sum over the sources of d(s, v); source_sums (S,) int64: sum over
    the nodes of d(s, v)), equal to summing :func:`bsms.graph.bfs.bfs_depths` one source at a
    time. 64 sources per sweep.
    """
    lib = library()
    if lib is None:
        return None
    sources = _int64(np.atleast_1d(sources))
    ptr, idx = _int64(adjacency.indptr), _int64(adjacency.indices)
    n = adjacency.shape[0]
    node_sums = np.zeros(n, dtype=np.int64)
    source_sums = np.zeros(sources.size, dtype=np.int64)
    for start in range(0, sources.size, 64):
        chunk = _int64(sources[start:start + 64])
        sums = np.zeros(chunk.size, dtype=np.int64)
        if lib.bsms_multi_bfs(n, ptr.ctypes.data, idx.ctypes.data, chunk.size, chunk.ctypes.data,
                              node_sums.ctypes.data, sums.ctypes.data):
            raise MemoryError(f"breadth-first search on {n} nodes: out of memory")
        source_sums[start:start + chunk.size] = sums
    return node_sums, source_sums


def coarse_images(pairs: np.ndarray, reach: sp.csr_matrix) -> np.ndarray | None:
    """:func:`bsms.graph.contact.coarse_images` (one step of eq. 4.1 on contact pairs), the same
    array, in one compiled pass; None without the library. pairs: (2, C) int64 node pairs of a
    level, both directions; reach: (n, n') 0/1 CSR -> (2, C') int64, sorted by (row, col)."""
    lib = library()
    if lib is None:
        return None
    indptr, indices = _int64(reach.indptr), _int64(reach.indices)
    rows, cols = _int64(pairs[0]), _int64(pairs[1])
    while True:
        out = _OUT[0]
        written = lib.bsms_coarse_images(rows.size, rows.ctypes.data, cols.ctypes.data, indptr.ctypes.data,
                                         indices.ctypes.data, reach.shape[1], out.shape[1], out[0].ctypes.data,
                                         out[1].ctypes.data)
        if written >= 0:
            return out[:, :written].copy()
        if written == -1:
            raise MemoryError(f"contact edges of {rows.size} pairs on the next level: out of memory")
        _OUT[0] = np.empty((2, max(-2 - written, 2 * out.shape[1])), dtype=np.int64)  # room, reused by later calls


_OUT = [np.empty((2, 4096), dtype=np.int64)]  # the output buffer of coarse_images, grown when a call needs more
