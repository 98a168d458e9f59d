"""Contact edges: world-space proximity between nodes, and their coarse levels (thesis §4.2.2).

Mesh edges carry the elastic mechanics and come from topology alone; contact edges join nodes
that are close in space but not mesh neighbours -- nodes of different bodies (or a body and
an obstacle), and, for self-contact, nodes of one body that are not joined by a mesh edge.
They change every frame, so :func:`contact_edges` is a KD-tree query, O(N log N).

:func:`coarsen_contacts` carries them through a :class:`~bsms.graph.hierarchy.Hierarchy` with
eq. 4.1, C_{l+1} = ((A_l + I) C_l (A_l + I))[K, K] without the diagonal: a coarse contact
(i', j') exists when i' is i or its neighbour and j' is j or its neighbour for a finer contact
(i, j). Because every dropped node has a kept neighbour, every contact keeps a coarse image
on every level (the thesis' proof); only a self-contact whose two ends share a kept
neighbour collapses onto that node.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bsms.graph import native
from bsms.graph.bfs import off_diagonal_pattern
from bsms.graph.hierarchy import Hierarchy, edge_index_of

__all__ = ["contact_edges", "coarsen_contacts", "coarse_images"]


def _pair_keys(pairs: np.ndarray, n: int) -> np.ndarray:
    """Order-independent int64 key of each (i, j) pair: min * n + max."""
    return np.minimum(pairs[:, 0], pairs[:, 1]) * n + np.maximum(pairs[:, 0], pairs[:, 1])


def _contains(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """(len(keys),) bool: which keys occur in the sorted array (binary search, no hashing)."""
    where = np.minimum(np.searchsorted(sorted_keys, keys), max(sorted_keys.size - 1, 0))
    return (sorted_keys[where] == keys) if sorted_keys.size else np.zeros(keys.size, dtype=bool)


def _checked_contact_inputs(positions, body_id, radius, exclude) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or not np.isfinite(positions).all():
        raise ValueError(f"positions must be a finite (N, d) array; got shape {positions.shape}")
    body_id = np.asarray(body_id)
    if body_id.shape != positions.shape[:1] or not np.issubdtype(body_id.dtype, np.integer):
        raise ValueError(f"body_id must be an integer array of shape (N,) = ({positions.shape[0]},), "
                         f"one body or obstacle index per node; got {body_id.dtype} {body_id.shape}")
    if not (np.isscalar(radius) and np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be a positive finite distance; got {radius!r}")
    exclude = np.zeros((0, 2), np.int64) if exclude is None else np.asarray(exclude)
    if exclude.ndim != 2 or exclude.shape[1] != 2 or not np.issubdtype(exclude.dtype, np.integer):
        raise ValueError("exclude must be an integer (E, 2) array of node pairs such as mesh.edges "
                         f"(for a (2, E) edge_index pass edge_index.T); got {exclude.dtype} {exclude.shape}")
    return positions, body_id, exclude.astype(np.int64)


def contact_edges(positions, body_id, radius: float, exclude=None, *,
                  self_contact: bool = True) -> np.ndarray:
    """Proximity edges between nodes within ``radius`` (distance <= radius), not mesh neighbours.

    positions: (N, d) world positions of this frame; body_id: (N,) int body/obstacle of each
    node; exclude: (E, 2) node pairs never joined (normally ``mesh.edges``); self_contact:
    also join close nodes of the same body that ``exclude`` does not list. With self-contact,
    pick ``radius`` below the rest length of the mesh edges, or exclude more pairs, or nodes
    two hops apart along a surface count as touching.
    -> (2, C) int64 edge index, both directions, sorted by (row, col), no self-pairs.
    """
    positions, body_id, exclude = _checked_contact_inputs(positions, body_id, radius, exclude)
    n = positions.shape[0]
    pairs = cKDTree(positions).query_pairs(float(radius), output_type="ndarray").astype(np.int64)
    same_body = body_id[pairs[:, 0]] == body_id[pairs[:, 1]]
    if self_contact:
        excluded = _contains(np.sort(_pair_keys(exclude, n)), _pair_keys(pairs, n))
        keep = ~(same_body & excluded)
    else:
        keep = ~same_body
    pairs = pairs[keep]
    both = np.concatenate([pairs, pairs[:, ::-1]]).T
    return both[:, np.lexsort((both[1], both[0]))]


def _contact_matrix(contacts, n: int) -> sp.csr_matrix:
    contacts = np.asarray(contacts)
    if contacts.ndim != 2 or contacts.shape[0] != 2 or not np.issubdtype(contacts.dtype, np.integer):
        raise ValueError(f"contacts must be an integer (2, C) edge index (as contact_edges returns); "
                         f"got {contacts.dtype} {contacts.shape}")
    if contacts.size and (contacts.min() < 0 or contacts.max() >= n):
        raise ValueError(f"contact node indices must lie in [0, {n}), the hierarchy's level-0 nodes")
    values = np.ones(contacts.shape[1])
    matrix = sp.csr_matrix((values, (contacts[0], contacts[1])), shape=(n, n))
    return off_diagonal_pattern(matrix + matrix.T)


def coarse_images(pairs: np.ndarray, reach: sp.csr_matrix) -> np.ndarray:
    """One step of eq. 4.1 on contact pairs: every (a, b) with a in reach[i], b in reach[j] for a
    pair (i, j), a != b.

    pairs: (2, C) int64 node pairs of a level, both directions; reach: (n, n') 0/1 CSR with
    sorted indices (:attr:`Hierarchy.reach`) -> (2, C') int64 unique pairs of the next level,
    both directions, sorted by (row, col). A pair whose ends reach r_i and r_j nodes gives
    r_i * r_j candidates, built without a loop from the pairs with i < j (the rest are mirrors).
    """
    compiled = native.coarse_images(pairs, reach)
    if compiled is not None:  # the same array from one compiled pass (bsms.graph.native)
        return compiled
    indptr, indices, n = reach.indptr.astype(np.int64), reach.indices.astype(np.int64), reach.shape[1]
    i, j = pairs[:, pairs[0] < pairs[1]]
    start_i, start_j = indptr[i], indptr[j]
    count_j = indptr[j + 1] - start_j
    count = (indptr[i + 1] - start_i) * count_j
    owner = np.repeat(np.arange(count.size), count)
    offset = np.arange(owner.size) - np.repeat(np.cumsum(count) - count, count)
    a = indices[start_i[owner] + offset // count_j[owner]]
    b = indices[start_j[owner] + offset % count_j[owner]]
    apart = a != b
    a, b = a[apart], b[apart]
    keys = np.minimum(a, b) * n + np.maximum(a, b)
    keys.sort()
    low, high = np.divmod(keys[np.concatenate([keys[:1] == keys[:1], keys[1:] != keys[:-1]])], n)
    both = np.concatenate([low * n + high, high * n + low])
    both.sort()
    return np.stack(np.divmod(both, n))


def coarsen_contacts(hierarchy: Hierarchy, contacts) -> tuple[np.ndarray, ...]:
    """Contact edges on every level (thesis eq. 4.1).

    contacts: (2, C) int64 level-0 contact edge index (either or both directions)
    -> one (2, C_l) edge index per level, both directions, sorted; entry 0 is the input
    made symmetric.
    """
    out = [edge_index_of(_contact_matrix(contacts, hierarchy.levels[0].n_nodes))]
    for reach in hierarchy.reach:
        out.append(coarse_images(out[-1], reach))
    return tuple(out)
