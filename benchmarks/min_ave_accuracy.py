"""Accuracy of the sampled MinAve search (bsms.graph.seeding) against the exact graph median.

For every connected component of levels 0-2 of some gmsh meshes, the exact sum of hop
distances from each node is computed with all-sources BFS (csgraph, in chunks); the sampled
search then runs with three random seeds and its pick is compared with the exact minimum.
Reports, per graph, the relative excess in mean distance and the number of BFS it took.

Run: python benchmarks/min_ave_accuracy.py   (a few minutes)
"""

from __future__ import annotations

import time

import numpy as np
from scipy.sparse import csgraph

from bsms.graph import bfs, bistride_levels
from bsms.graph import seeding as seeding_module
from datagen import shapes


def exact_sums(adjacency) -> np.ndarray:
    """(N,) sum of hop distances from every node of a connected graph."""
    n, out = adjacency.shape[0], np.zeros(adjacency.shape[0])
    for start in range(0, n, 512):
        rows = np.arange(start, min(n, start + 512))
        distances = csgraph.shortest_path(adjacency, unweighted=True, directed=False, indices=rows)
        out[rows] = distances.sum(axis=1)
    return out


def components(adjacency):
    count, labels = csgraph.connected_components(adjacency, directed=False)
    for c in range(count):
        members = np.flatnonzero(labels == c)
        if members.size > 500:
            yield adjacency[members][:, members].tocsr()


def counted_search(component, rng) -> tuple[int, int]:
    """(picked node, BFS count) of one sampled search."""
    calls = 0
    original = seeding_module.bfs_depths

    def counting(graph, sources):
        nonlocal calls
        calls += 1
        return original(graph, sources)

    seeding_module.bfs_depths = counting
    try:
        return seeding_module._sampled_median(component, rng), calls
    finally:
        seeding_module.bfs_depths = original


def main() -> None:
    meshes = {
        "disk": shapes.disk(1.0, 0.02),
        "annulus": shapes.annulus(0.3, 1.0, 0.018),
        "L-shape": shapes.polygon([(0, 0), (3, 0), (3, 1), (1, 1), (1, 3), (0, 3)], size=0.035),
        "glyph BSMS": shapes.glyph("BSMS", 0.012),
        "box": shapes.box((1.0, 1.0, 1.0), 0.06),
        "sphere": shapes.sphere(1.0, 0.1),
    }
    excess, counts = [], []
    print(f"{'graph':22s} {'nodes':>6s} {'excess % (3 runs)':>24s} {'BFS':>12s} {'time [s]':>9s}")
    for name, mesh in meshes.items():
        hierarchy = bistride_levels(mesh, levels=3, seeding="close_center")
        for l, level in enumerate(hierarchy.levels):
            for component in components(level.adjacency):
                sums = exact_sums(component)
                runs = []
                start = time.perf_counter()
                for seed in range(3):
                    node, calls = counted_search(component, np.random.default_rng(seed))
                    runs.append((sums[node] / sums.min() - 1.0, calls))
                elapsed = (time.perf_counter() - start) / 3
                excess += [r[0] for r in runs]
                counts += [r[1] for r in runs]
                shown = " ".join(f"{100 * r[0]:7.3f}" for r in runs)
                print(f"{name + f' level {l}':22s} {component.shape[0]:6d} {shown:>24s} "
                      f"{'/'.join(str(r[1]) for r in runs):>12s} {elapsed:9.3f}")
    excess = np.array(excess)
    print(f"\n{excess.size} searches: exact median found {np.sum(excess == 0)}, mean excess "
          f"{100 * excess.mean():.3f}%, worst {100 * excess.max():.3f}%; BFS per search mean "
          f"{np.mean(counts):.0f}, max {np.max(counts)}")
    assert bfs.bfs_depths is seeding_module.bfs_depths


if __name__ == "__main__":
    main()
