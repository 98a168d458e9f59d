"""Wall time of ``bistride_levels`` next to a straightforward reference implementation.

Meshes: gmsh disks (2D, triangles) and boxes (3D, tetrahedra) of about 1k, 10k, 50k and 200k
nodes, and a box of 180k nodes and about a million tetrahedra (``1Mtet``, 3D only; gmsh takes
about 5 minutes to mesh it), meshed once and cached under ``.cache/benchmarks/``. For each mesh
and seeding it times ``bistride_levels(mesh, levels=7, seeding=...)`` -- the mesh and 6 coarse
levels, with transitions -- as the best of ``--repeats`` runs, each on a fresh Mesh object, on
one thread. The ``scipy [s]`` column times the same call without the compiled loops
(``BSMS_NATIVE=0``: scipy's sparse product and csgraph's searches, :mod:`bsms.graph.native`),
once, and says whether it gives the same levels and transitions. In the same process it runs
the reference below (once) where it can: plain Python BFS with a list as
queue, two-hop sets for coarse edges, loops for the transition weights, and for MinAve a
dense all-pairs BFS table. Both must give the same levels (kept nodes and edges) and the same
down and up transition weights (to 1e-12).

Run: python benchmarks/bistride_preprocess.py [--sizes 1k 10k 50k 200k 1Mtet] [--dims 2 3]
The table is printed and written to ``runs/benchmarks/bistride_preprocess.md``.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from pathlib import Path

os.environ["OMP_NUM_THREADS"] = "1"  # one core: the compiled loops' OpenMP included

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

from bsms.graph import SEEDINGS, bistride_levels, native  # noqa: E402
from datagen import shapes  # noqa: E402
from datagen.mesh import Mesh  # noqa: E402

LEVELS = 7  # the mesh and 6 coarse levels
SIZES = {"1k": 1_000, "10k": 10_000, "50k": 50_000, "200k": 200_000, "1Mtet": 180_000}
ONLY_3D = {"1Mtet"}
TARGETS = {(2, "50k", "close_center"): 0.2, (2, "50k", "min_ave"): 2.0, (2, "200k", "close_center"): 1.0,
           (3, "1Mtet", "min_ave"): 5.0}
WEIGHT_TOLERANCE = 1e-12
REFERENCE_MIN_AVE_NODES = 2_000  # its dense all-pairs table is O(N^2) in time and memory
REFERENCE_3D_NODES = 12_000  # 3D coarse levels get dense (mean degree ~1000): two-hop sets explode
CACHE = Path(".cache/benchmarks")
RESULTS = Path("runs/benchmarks/bistride_preprocess.md")


# --------------------------------------------------------------------------- meshes
def benchmark_mesh(dim: int, nodes: int) -> Mesh:
    """A gmsh disk (2D) or unit box (3D) within 20% of ``nodes`` nodes, cached as npz."""
    path = CACHE / f"{'disk' if dim == 2 else 'box'}_{nodes}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            return Mesh(data["nodes"], data["cells"])
    size = 0.0137 * math.sqrt(19_657 / nodes) if dim == 2 else 0.03 * (30_932 / nodes) ** (1 / 3)
    for _ in range(4):  # gmsh's node count is not smooth in the size: rescale until close
        mesh = shapes.disk(1.0, size) if dim == 2 else shapes.box((1.0, 1.0, 1.0), size)
        if abs(mesh.n_nodes / nodes - 1) < 0.2:
            break
        size *= (mesh.n_nodes / nodes) ** (1 / dim)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, nodes=mesh.nodes, cells=mesh.cells)
    return mesh


# --------------------------------------------------------------------------- reference
def python_bfs(neighbours: list[list[int]], seed: int) -> dict[int, int]:
    """Hop depth of every node reachable from ``seed``; the queue is a plain list."""
    depth, queue, head = {seed: 0}, [seed], 0
    while head < len(queue):
        node = queue[head]
        head += 1
        for other in neighbours[node]:
            if other not in depth:
                depth[other] = depth[node] + 1
                queue.append(other)
    return depth


def reference_components(neighbours: list[list[int]]) -> list[list[int]]:
    seen, components = set(), []
    for start in range(len(neighbours)):
        if start not in seen:
            members = sorted(python_bfs(neighbours, start))
            seen.update(members)
            components.append(members)
    return components


def reference_seed(members, positions, seeding, keys, distances) -> int:
    """The seed of one component, ties to the lowest index (as bsms.graph.seeding)."""
    if seeding == "close_center":
        centroid = positions[members].mean(axis=0)
        score = [float(np.linalg.norm(positions[m] - centroid)) for m in members]
    elif seeding == "random":
        score = [keys[m] for m in members]
    else:
        score = [int(distances[m, members].sum()) for m in members]
    return members[min(range(len(members)), key=lambda k: (score[k], members[k]))]


def reference_level(neighbours, positions, weights, seeding, keys, distances):
    """One bi-stride level: kept nodes, coarse neighbour lists, down weights, coarse weights."""
    kept = []
    for members in reference_components(neighbours):
        depth = python_bfs(neighbours, reference_seed(members, positions, seeding, keys, distances))
        odd = [m for m in members if depth[m] % 2 == 1]
        even = [m for m in members if depth[m] % 2 == 0]
        kept += odd if 0 < len(odd) < len(even) else even
    kept.sort()
    index = {node: k for k, node in enumerate(kept)}
    coarse = []
    for node in kept:
        reach = {node, *neighbours[node]}
        for middle in neighbours[node]:
            reach.update(neighbours[middle])
        coarse.append(sorted(index[other] for other in reach if other in index and other != node))
    down, coarse_weights = [], []
    for node in kept:
        senders = [node, *neighbours[node]]
        shares = [weights[s] / (len(neighbours[s]) + 1) for s in senders]
        coarse_weights.append(sum(shares))
        down.append({s: share / coarse_weights[-1] for s, share in zip(senders, shares, strict=True)})
    return kept, coarse, down, coarse_weights


def reference_up(down: list[dict[int, float]], n_fine: int) -> list[dict[int, float]]:
    """Up weights: the down table transposed, renormalised per fine node."""
    up = [{} for _ in range(n_fine)]
    for coarse, row in enumerate(down):
        for fine, weight in row.items():
            up[fine][coarse] = weight
    return [{coarse: w / sum(row.values()) for coarse, w in row.items()} for row in up]


def reference_levels(mesh: Mesh, seeding: str, seed: int = 0) -> list[tuple]:
    """All levels by the reference: (kept, coarse neighbour lists, down rows, up rows) per coarse level."""
    neighbours = [[] for _ in range(mesh.n_nodes)]
    for i, j in mesh.edges.tolist():
        neighbours[i].append(j)
        neighbours[j].append(i)
    positions, weights, out = mesh.nodes, [1.0] * mesh.n_nodes, []
    for depth in range(1, LEVELS):
        n = len(neighbours)
        keys = np.random.default_rng([seed, depth]).random(n).tolist() if seeding == "random" else None
        distances = None
        if seeding == "min_ave":  # dense all-pairs BFS table
            distances = np.zeros((n, n), dtype=np.int32)
            for source in range(n):
                for node, hops in python_bfs(neighbours, source).items():
                    distances[source, node] = hops
        kept, coarse, down, weights = reference_level(neighbours, positions, weights, seeding, keys, distances)
        out.append((kept, coarse, down, reference_up(down, n)))
        positions, neighbours = positions[kept], coarse
    return out


def same_levels(hierarchy, reference) -> bool:
    for level, (kept, neighbours, _, _) in zip(hierarchy.levels[1:], reference, strict=True):
        rows = np.repeat(np.arange(len(neighbours)), [len(n) for n in neighbours])
        edges = np.stack([rows, np.concatenate([np.asarray(n, dtype=np.int64) for n in neighbours])])
        if level.kept.tolist() != kept or not np.array_equal(level.edge_index, edges):
            return False
    return True


def as_matrix(rows: list[dict[int, float]], n_cols: int) -> sp.csr_matrix:
    indices = [(r, c, w) for r, row in enumerate(rows) for c, w in row.items()]
    r, c, w = (np.array(v) for v in zip(*indices, strict=True))
    return sp.csr_matrix((w, (r, c)), shape=(len(rows), n_cols))


def weight_difference(hierarchy, reference) -> float:
    """Largest difference between bsms' down/up weights and the reference's, over all levels."""
    worst = 0.0
    for level, (_, _, down, up) in zip(hierarchy.levels[1:], reference, strict=True):
        for transition, rows in ((level.down, down), (level.up, up)):
            difference = transition.matrix() - as_matrix(rows, transition.shape[1])
            worst = max(worst, float(abs(difference).max()) if difference.nnz else 0.0)
    return worst


# --------------------------------------------------------------------------- timing
def best_time(mesh: Mesh, seeding: str, repeats: int, compiled: bool = True):
    """Best wall time of ``repeats`` builds and the last hierarchy; ``compiled=False`` switches
    the compiled loops off (BSMS_NATIVE=0) for the duration."""
    saved = os.environ.get("BSMS_NATIVE")
    os.environ["BSMS_NATIVE"] = "1" if compiled else "0"
    native.library.cache_clear()
    try:
        return _best_time(mesh, seeding, repeats)
    finally:
        os.environ.pop("BSMS_NATIVE") if saved is None else os.environ.update(BSMS_NATIVE=saved)
        native.library.cache_clear()


def _best_time(mesh: Mesh, seeding: str, repeats: int):
    times, hierarchy = [], None
    for _ in range(repeats):
        fresh = Mesh(mesh.nodes, mesh.cells)
        start = time.perf_counter()
        hierarchy = bistride_levels(fresh, levels=LEVELS, seeding=seeding)
        times.append(time.perf_counter() - start)
    return min(times), hierarchy


def reference_fits(dim: int, n_nodes: int, seeding: str, limit: int) -> bool:
    if seeding == "min_ave":
        limit = min(limit, REFERENCE_MIN_AVE_NODES)
    elif dim == 3:
        limit = min(limit, REFERENCE_3D_NODES)
    return n_nodes <= limit


def run_case(dim, name, mesh, seeding, args) -> str:
    fast, hierarchy = best_time(mesh, seeding, args.repeats)
    target = TARGETS.get((dim, name, seeding))
    verdict = "" if target is None else f"{'met' if fast < target else 'MISSED'} (< {target:g} s)"
    plain, without = best_time(mesh, seeding, 1, compiled=False)
    same_plain = "yes" if same_hierarchy(hierarchy, without) else "NO"
    reference = speedup = match = weights = "-"
    if reference_fits(dim, mesh.n_nodes, seeding, args.reference_max_nodes):
        start = time.perf_counter()
        levels = reference_levels(mesh, seeding)
        elapsed = time.perf_counter() - start
        reference, speedup = f"{elapsed:.3f}", f"{elapsed / fast:.0f}x"
        match = "yes" if same_levels(hierarchy, levels) else "NO"
        if match == "yes":
            difference = weight_difference(hierarchy, levels)
            weights = f"{'yes' if difference <= WEIGHT_TOLERANCE else 'NO'} ({difference:.1e})"
    counts = "/".join(str(c) for c in hierarchy.node_counts)
    return (f"| {dim}D | {name} | {mesh.n_nodes} | {mesh.cells.shape[0]} | {seeding} | {fast:.3f} | "
            f"{plain:.3f} ({same_plain}) | {reference} | {speedup} | {match} | {weights} | {verdict} | {counts} |")


def same_hierarchy(a, b) -> bool:
    """Every level's kept nodes, edges, seeds, weights and transitions identical."""
    for x, y in zip(a.levels, b.levels, strict=True):
        arrays = [(getattr(x, k), getattr(y, k)) for k in ("kept", "edge_index", "node_weights", "seeds")]
        for kind in ("down", "up") if x.down is not None else ():
            u, v = getattr(x, kind), getattr(y, kind)
            arrays += [(getattr(u, k), getattr(v, k)) for k in ("rows", "cols", "weights")]
        if not all(np.array_equal(u, v) for u, v in arrays):
            return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES),
                        help="1Mtet: 3D only, 5 minutes of meshing the first time")
    parser.add_argument("--dims", nargs="+", type=int, default=[2, 3], choices=[2, 3])
    parser.add_argument("--seedings", nargs="+", default=list(SEEDINGS), choices=list(SEEDINGS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reference-max-nodes", type=int, default=50_000,
                        help="largest mesh the reference runs on (also at most 2k for MinAve, 12k in 3D)")
    args = parser.parse_args()
    machine = platform.processor() or platform.machine()
    lines = [f"bistride_levels, levels={LEVELS}, best of {args.repeats}, one thread; {machine}", "",
             "| dim | size | nodes | cells | seeding | bsms [s] | scipy [s] (same) | reference [s] | speed-up | "
             "same levels | same weights (max difference) | target | nodes per level |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for dim in args.dims:
        for name in args.sizes:
            if name in ONLY_3D and dim != 3:
                continue
            mesh = benchmark_mesh(dim, SIZES[name])
            for seeding in args.seedings:
                lines.append(run_case(dim, name, mesh, seeding, args))
                print(lines[-1], flush=True)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text("\n".join(lines) + "\n")
    print(f"\nwritten to {RESULTS}")


if __name__ == "__main__":
    main()
