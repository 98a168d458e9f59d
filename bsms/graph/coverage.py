"""How well a pooling covers the level it pools from: the fraction of nodes with no kept node
within k hops (thesis Fig. 4.5, "unfair pooling" of learnable top-k).

Bi-stride pooling keeps every other BFS frontier, so every dropped node has a kept neighbour
(2-connection-conservative): at k = 1 nothing is left uncovered on any level. A learned top-k
pooling gives no such guarantee; the nodes it leaves uncovered get coarse information only
through longer chains of fine message passes.

The measure on a pooling step l -> l + 1 is taken on level l's own graph (its nodes and
edges): the "fine" nodes are level l's, the kept ones level l + 1's.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["uncovered_fraction", "level_coverage"]


def uncovered_fraction(edge_index: np.ndarray, n_nodes: int, kept: np.ndarray, hops: int) -> float:
    """Fraction of the ``n_nodes`` nodes of a graph with no node of ``kept`` within ``hops`` edges.

    edge_index: (2, E) int node pairs (either or both directions); kept: indices of the kept
    nodes (a kept node covers itself, at 0 hops); hops >= 0.
    """
    if hops < 0:
        raise ValueError(f"hops must be >= 0, got {hops}")
    if n_nodes == 0:
        return 0.0
    edge_index = np.asarray(edge_index, dtype=np.int64).reshape(2, -1)
    ones = np.ones(edge_index.shape[1], dtype=bool)
    adjacency = sp.csr_matrix((ones, (edge_index[0], edge_index[1])), shape=(n_nodes, n_nodes))
    adjacency = (adjacency + adjacency.T).tocsr()
    reached = np.zeros(n_nodes, dtype=bool)
    reached[np.asarray(kept, dtype=np.int64)] = True
    for _ in range(hops):
        reached = reached | (adjacency @ reached.astype(np.int8) > 0)
    return float(1.0 - reached.mean())


def level_coverage(level_nodes: list[np.ndarray], level_edges: list[np.ndarray], hops: int) -> list[float]:
    """Uncovered fraction of every pooling step of a multi-level graph.

    level_nodes: per level, the level-0 indices of its nodes (each level's a subset of the
    previous level's); level_edges: per level, its (2, E) edges in that level's own numbering
    (position in ``level_nodes[l]``). Returns one fraction per step l -> l + 1 (len - 1 values).
    """
    fractions = []
    for l in range(len(level_nodes) - 1):
        fine, coarse = np.asarray(level_nodes[l]), np.asarray(level_nodes[l + 1])
        position = np.full(int(max(fine.max(initial=-1), coarse.max(initial=-1))) + 1, -1, dtype=np.int64)
        position[fine] = np.arange(len(fine))
        kept = position[coarse]
        if (kept < 0).any():
            raise ValueError(f"level {l + 1} holds nodes that level {l} lacks: {coarse[kept < 0][:5].tolist()}")
        fractions.append(uncovered_fraction(level_edges[l], len(fine), kept, hops))
    return fractions
