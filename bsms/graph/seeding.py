"""Seeds for bi-stride pooling: one BFS start node per connected component (thesis §4.2.2).

- ``close_center`` (Algorithm 2): the node nearest the component's centroid.
- ``random``: a uniformly random node of each component, from a seeded generator.
- ``min_ave`` (Algorithm 3): the node with the minimum mean hop distance to the rest of its
  component (the graph median). The thesis evaluates it from all-pairs BFS, O(N^2) in time
  and memory. Here:

  * small components are solved exactly: packed into batches and swept by one bitset
    all-sources BFS per batch (:func:`distance_sums`), as long as a sweep step touches at most
    ``EXACT_MIN_AVE_WORK`` = 2^19 words (adjacency entries x nodes / 64): about 2,300 nodes
    of a triangle mesh, 1,500 of a tetrahedral one, fewer on the denser coarse levels;
    70 ms for 2,000 triangle-mesh nodes;
  * larger components use a sampled search, O(N) memory: the mean distance of every node is
    estimated from BFS out of ``_SAMPLED_SOURCES`` = 48 random nodes; the 12 best estimates
    are evaluated exactly (one BFS each); then a descent moves to the best neighbour while
    that lowers the exact mean (at most 32 steps; of a node's neighbours only the 16 with
    the best estimates are tried, which bounds the cost on the dense coarse levels). The
    searches of each stage run together, 64 sources per bit-parallel search, where the
    compiled loops are available (:func:`bsms.graph.native.multi_source_sums`): the same
    integer sums, so the same seeds.
    ``benchmarks/min_ave_accuracy.py`` compares it with the exact median on every component
    of 0.5k-10k nodes of levels 0-2 of gmsh disk, annulus, L-shape, glyph, box and sphere
    meshes (72 searches, 72 BFS each on average): the exact median in 61, mean excess in
    mean distance 0.14%, worst 3.4% (the glyph 'B' with its holes, where the descent can
    settle in a neighbouring basin).

Ties are broken towards the lowest node index, so every seeding is deterministic.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bsms.graph import native
from bsms.graph.bfs import bfs_depths, distance_sums

__all__ = ["SEEDINGS", "EXACT_MIN_AVE_WORK", "component_seeds", "close_center_seeds",
           "random_seeds", "min_ave_seeds"]

SEEDINGS = ("min_ave", "close_center", "random")
EXACT_MIN_AVE_WORK = 2**19
_SAMPLED_SOURCES = 48
_CANDIDATES = 12
_MAX_DESCENT_STEPS = 32
_DESCENT_WIDTH = 16


def argmin_per_component(values: np.ndarray, labels: np.ndarray, n_components: int) -> np.ndarray:
    """Index of the smallest value in each component, ties to the lowest index.

    values: (N,), labels: (N,) in [0, n_components), every component non-empty
    -> (n_components,) int64 node indices. O(N), no sort.
    """
    smallest = np.full(n_components, np.inf)
    np.minimum.at(smallest, labels, values)
    ties = np.flatnonzero(values == smallest[labels])
    first = np.full(n_components, values.size, dtype=np.int64)
    np.minimum.at(first, labels[ties], ties)
    return first


def close_center_seeds(positions: np.ndarray, labels: np.ndarray, n_components: int) -> np.ndarray:
    """Node nearest its component's centroid (Algorithm 2). positions: (N, d) -> (C,)."""
    counts = np.bincount(labels, minlength=n_components)
    centroids = np.stack(
        [np.bincount(labels, weights=positions[:, axis], minlength=n_components) / counts
         for axis in range(positions.shape[1])], axis=1)
    distance = np.linalg.norm(positions - centroids[labels], axis=1)
    return argmin_per_component(distance, labels, n_components)


def random_seeds(labels: np.ndarray, n_components: int, rng: np.random.Generator) -> np.ndarray:
    """A uniformly random node of each component. labels: (N,) -> (C,)."""
    return argmin_per_component(rng.random(labels.size), labels, n_components)


def source_distance_sums(component: sp.csr_matrix, sources: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sum over ``sources`` of each node's hop distance (N,), sum over the nodes of each source's
    (S,)) on a connected graph: compiled, 64 sources per search (:mod:`bsms.graph.native`),
    else one csgraph search per source; the same integers either way."""
    sums = native.multi_source_sums(component, sources)
    if sums is not None:
        return sums
    node_sums = np.zeros(component.shape[0], dtype=np.int64)
    source_sums = np.zeros(len(sources), dtype=np.int64)
    for i, source in enumerate(sources):
        depth = bfs_depths(component, source)
        node_sums += depth
        source_sums[i] = depth.sum()
    return node_sums, source_sums


def _sampled_median(component: sp.csr_matrix, rng: np.random.Generator) -> int:
    """Approximate MinAve seed of one connected component (see the module docstring)."""
    n = component.shape[0]
    if native.library() is not None:  # the compiled searches read int64 arrays: convert once
        component = sp.csr_matrix((component.data, component.indices.astype(np.int64),
                                   component.indptr.astype(np.int64)), shape=component.shape)
    sources = rng.choice(n, size=min(_SAMPLED_SOURCES, n), replace=False)
    estimate = source_distance_sums(component, sources)[0]
    exact: dict[int, int] = {}

    def best_of(nodes) -> int:
        """The node of smallest exact distance sum, ties to the lowest index."""
        nodes = [int(node) for node in nodes]
        missing = np.array(sorted({node for node in nodes if node not in exact}), dtype=np.int64)
        if missing.size:
            exact.update(zip(missing.tolist(), source_distance_sums(component, missing)[1].tolist(), strict=True))
        return min((exact[node], node) for node in nodes)[1]

    best = best_of(np.argsort(estimate, kind="stable")[:_CANDIDATES])
    for _ in range(_MAX_DESCENT_STEPS):
        neighbours = component.indices[component.indptr[best]:component.indptr[best + 1]]
        neighbours = neighbours[np.argsort(estimate[neighbours], kind="stable")[:_DESCENT_WIDTH]]
        step = best_of([best, *neighbours])
        if step == best:
            break
        best = step
    return best


def _exact_batches(sizes: np.ndarray, nnz: np.ndarray) -> list[list[int]]:
    """Runs of consecutive components solved exactly together, each run's bitset sweep
    within EXACT_MIN_AVE_WORK words per step. sizes, nnz: (C,) nodes and adjacency entries."""
    work = nnz * -(-sizes // 64)
    batches: list[list[int]] = []
    for component in np.flatnonzero((sizes > 1) & (work <= EXACT_MIN_AVE_WORK)):
        run = batches[-1] + [component] if batches and batches[-1][-1] == component - 1 else None
        if run is None or nnz[run].sum() * -(-sizes[run].sum() // 64) > EXACT_MIN_AVE_WORK:
            batches.append([int(component)])
        else:
            batches[-1] = [int(c) for c in run]
    return batches


def min_ave_seeds(adjacency: sp.csr_matrix, labels: np.ndarray, n_components: int,
                  rng: np.random.Generator) -> np.ndarray:
    """Node of minimum mean hop distance within its component (Algorithm 3). -> (C,)."""
    order = np.argsort(labels, kind="stable")  # nodes grouped by component, contiguous
    grouped = adjacency if np.array_equal(order, np.arange(order.size)) else adjacency[order][:, order]
    sizes = np.bincount(labels, minlength=n_components)
    nnz = np.bincount(labels, weights=np.diff(adjacency.indptr), minlength=n_components).astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    seeds = order[starts[:-1]].copy()  # right for one-node components
    solved = np.zeros(n_components, dtype=bool)
    solved[sizes == 1] = True
    for batch in _exact_batches(sizes, nnz):
        lo, hi = starts[batch[0]], starts[batch[-1] + 1]
        block_labels = np.repeat(np.arange(len(batch)), sizes[batch])
        block = grouped[lo:hi, lo:hi].tocsr()
        seeds[batch] = order[lo + argmin_per_component(distance_sums(block), block_labels, len(batch))]
        solved[batch] = True
    for component in np.flatnonzero(~solved):
        lo, hi = starts[component], starts[component + 1]
        block = grouped if hi - lo == grouped.shape[0] else grouped[lo:hi, lo:hi].tocsr()
        seeds[component] = order[lo + _sampled_median(block, rng)]
    return seeds


def component_seeds(adjacency: sp.csr_matrix, labels: np.ndarray, n_components: int,
                    positions: np.ndarray, seeding: str, rng: np.random.Generator) -> np.ndarray:
    """One seed per component with the named heuristic (one of :data:`SEEDINGS`). -> (C,)."""
    if seeding == "min_ave":
        return min_ave_seeds(adjacency, labels, n_components, rng)
    if seeding == "close_center":
        return close_center_seeds(positions, labels, n_components)
    if seeding == "random":
        return random_seeds(labels, n_components, rng)
    raise ValueError(f"seeding must be one of {SEEDINGS}, got {seeding!r}")
