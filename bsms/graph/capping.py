"""A cap on the degree of the coarse bi-stride levels (``max_coarse_degree``), from topology alone.

Bi-stride joins the kept nodes within two hops, A_{l+1} = (A_l + I)^2 [K, K]. On a tetrahedral
mesh two-hop neighbourhoods are large and the degree compounds level after level (a 15k-node
plate: 180 edges per node on its fourth level, docs/scaling.md). With a cap k, level l+1 keeps
a subset of those pairs, chosen from the mesh's topology only (no spatial search):

- strength: each candidate pair (i, j) counts its two-paths, |N[i] ∩ N[j]| over closed
  neighbourhoods of level l (the entries of the integer product R R^T): pairs that share many
  neighbours are the mesh's nearest; a pair joined through a single node is the weakest;
- anchors first: every kept node at BFS depth d >= 2 has kept nodes at depth d - 2 within two
  hops (its BFS grandparent among them); its strongest such pair is its anchor, the link toward
  its component's seed that keeps the component connected and lets a coarse hop cover two
  BFS frontiers (the thesis' bi-stride argument);
- greedy under the cap: pairs ranked (anchor first, then more two-paths, then the smaller
  node indices) are accepted in that order while both ends have fewer than k coarse edges;
- reconnection: where the cap splits a connected component (on the tetrahedral plates of
  docs/scaling.md never for k >= 12, one or two pairs on a few levels for k = 6 and 8), the
  strongest dropped pairs that join its pieces are added back (a spanning forest over the
  pieces, the best-ranked pairs first).

So every node has at most k coarse edges, plus the reconnecting edges at it (a component split
into p pieces gets p - 1 of them), every level keeps the components of the mesh, and a cap at or
above a level's uncapped degree keeps all its pairs (the hierarchy of ``max_coarse_degree=None``).
The greedy runs in vectorised rounds that give exactly the sequential result
(:func:`greedy_degree_cap`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

__all__ = ["path_counts", "ranked_pairs", "greedy_degree_cap", "reconnecting_pairs", "capped_coarse_adjacency"]


def path_counts(closed: sp.csr_matrix) -> sp.csr_matrix:
    """(K, K) CSR, sorted indices, no diagonal: two-path counts between kept pairs within two hops.

    closed: (K, N) rows of A + I at the kept nodes (:func:`bsms.graph.pooling.closed_rows`).
    Entry (i, j) = |N[i] ∩ N[j]| (closed neighbourhoods): the pattern of
    :func:`bsms.graph.pooling.coarse_adjacency`, with counts.
    """
    rows = sp.csr_matrix((np.ones(closed.nnz, dtype=np.int32), closed.indices, closed.indptr), shape=closed.shape)
    counts = (rows @ rows.T).tocoo()
    off = counts.row != counts.col
    result = sp.csr_matrix((counts.data[off], (counts.row[off], counts.col[off])), shape=counts.shape)
    result.sort_indices()
    return result


def _anchors(row: np.ndarray, col: np.ndarray, count: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Bool per directed entry: (row, col) is row's anchor, its strongest pair with a node two
    BFS frontiers nearer the seed (ties: the smaller col)."""
    toward = depth[col] == depth[row] - 2
    order = np.lexsort((col, -count, ~toward, row))  # per row: toward-seed pairs first, strongest first
    first = np.ones(order.size, dtype=bool)
    first[1:] = row[order][1:] != row[order][:-1]
    anchor = np.zeros(row.size, dtype=bool)
    anchor[order] = first & toward[order]
    return anchor


def ranked_pairs(counts: sp.csr_matrix, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs (lo < hi) of ``counts`` in acceptance order: anchors first, then more
    two-paths, then (lo, hi). depth: (K,) BFS depth of each kept node from its component's seed
    on the finer level -> (lo (P,), hi (P,)) int64."""
    entries = counts.tocoo()
    row, col, count = entries.row.astype(np.int64), entries.col.astype(np.int64), entries.data
    anchor = _anchors(row, col, count, depth)
    # counts is symmetric: each pair is two entries, adjacent once sorted by pair; it is an
    # anchor pair when either direction is an anchor
    lo, hi = np.minimum(row, col), np.maximum(row, col)
    by_pair = np.argsort(lo * counts.shape[0] + hi, kind="stable")
    pair_anchor = anchor[by_pair].reshape(-1, 2).any(axis=1)
    lo, hi, count = lo[by_pair[0::2]], hi[by_pair[0::2]], count[by_pair[0::2]]
    ranking = np.lexsort((hi, lo, -count, ~pair_anchor))
    return lo[ranking], hi[ranking]


def greedy_degree_cap(lo: np.ndarray, hi: np.ndarray, n: int, cap: int) -> np.ndarray:
    """Bool per pair: accepted by the greedy that takes pairs in the given order while both ends
    have fewer than ``cap`` accepted pairs.

    lo, hi: (P,) distinct undirected pairs in rank order. Vectorised in rounds: a pair is accepted
    in a round when it is among the first ``room`` remaining pairs of both its ends (the sequential
    greedy accepts it too: fewer than ``room`` pairs still undecided come before it at either end);
    pairs at an end with no room left are dropped (the greedy filled that end with better pairs).
    The first remaining pair is accepted every round, so the rounds end, with exactly the
    sequential result (tests compare them).
    """
    room = np.full(n, cap, dtype=np.int64)
    accepted = np.zeros(lo.size, dtype=bool)
    alive = np.arange(lo.size)
    while alive.size:
        ends = np.concatenate([lo[alive], hi[alive]])
        order = np.lexsort((np.concatenate([alive, alive]), ends))  # per end, its remaining pairs in rank order
        sorted_ends = ends[order]
        starts = np.searchsorted(sorted_ends, sorted_ends, side="left")
        position = np.empty(ends.size, dtype=np.int64)
        position[order] = np.arange(ends.size) - starts
        half = alive.size
        take = (position[:half] < room[lo[alive]]) & (position[half:] < room[hi[alive]])
        taken = alive[take]
        accepted[taken] = True
        room -= np.bincount(lo[taken], minlength=n) + np.bincount(hi[taken], minlength=n)
        rest = alive[~take]
        alive = rest[(room[lo[rest]] > 0) & (room[hi[rest]] > 0)]
    return accepted


def reconnecting_pairs(lo: np.ndarray, hi: np.ndarray, accepted: np.ndarray, n: int) -> np.ndarray:
    """Indices of the dropped pairs that rejoin the pieces the cap split: per pair of pieces its
    first dropped pair in rank order, then a spanning forest of the pieces minimising rank (the
    strongest). Empty where the accepted pairs connect every component of the candidate graph."""
    graph = sp.csr_matrix((np.ones(int(accepted.sum())), (lo[accepted], hi[accepted])), shape=(n, n))
    _, pieces = csgraph.connected_components(graph, directed=False)
    candidates = np.flatnonzero(~accepted & (pieces[lo] != pieces[hi]))
    if not candidates.size:
        return candidates
    a, b = pieces[lo[candidates]], pieces[hi[candidates]]
    key = np.minimum(a, b) * n + np.maximum(a, b)
    _, first = np.unique(key, return_index=True)  # the first (best-ranked) pair per pair of pieces
    best = candidates[np.sort(first)]
    a, b = pieces[lo[best]], pieces[hi[best]]
    weights = np.arange(1, best.size + 1, dtype=np.float64)  # distinct: the forest is unique
    quotient = sp.csr_matrix((weights, (np.minimum(a, b), np.maximum(a, b))), shape=(n, n))
    forest = csgraph.minimum_spanning_tree(quotient).tocoo()
    return best[np.sort(forest.data.astype(np.int64) - 1)]


def capped_coarse_adjacency(closed: sp.csr_matrix, depth: np.ndarray, cap: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """The coarse level's adjacency under a degree cap, and the pairs added to reconnect it.

    closed: (K, N) rows of A + I at the kept nodes; depth: (K,) their BFS depths from their
    components' seeds on the finer level; cap: >= 1 -> ((K, K) symmetric 0/1 CSR, sorted indices,
    no diagonal; (2, R) int64 reconnecting pairs, lo < hi).
    """
    n = closed.shape[0]
    lo, hi = ranked_pairs(path_counts(closed), depth)
    accepted = greedy_degree_cap(lo, hi, n, cap)
    extra = reconnecting_pairs(lo, hi, accepted, n)
    accepted[extra] = True
    rows, cols = np.concatenate([lo[accepted], hi[accepted]]), np.concatenate([hi[accepted], lo[accepted]])
    adjacency = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    adjacency.sort_indices()
    return adjacency, np.stack([lo[extra], hi[extra]])
