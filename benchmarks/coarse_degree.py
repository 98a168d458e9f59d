"""The coarse-degree cap of bi-stride (``graph.max_coarse_degree``, ``bsms.graph.capping``) on the
3D plates of ``scaling.py``: what it does to the levels and to BSMS-GNN's step.

Per plate size (``--sizes``, the cached gmsh plates of ``scaling.py``) and per cap (``--caps``,
``none`` = the thesis' levels), the hierarchy ``scaling.py`` builds (pooled until a level has
fewer than 32 nodes, MinAve seeds): per level its nodes, directed edges, largest degree and
diameter (exact, in hops), and the total edges over the mesh's. With ``--rules``, the same for
two other ways of keeping k pairs per node, for comparison: ``union`` (each node's k pairs with
the most two-paths, an edge where either end keeps it) and ``mutual`` (where both do), both
reconnected like the library's rule. Then, in fresh processes as ``scaling.py`` times them,
BSMS-GNN's training and inference steps (``--infer-only``: inference) per cap (``--steps`` timed after ``--warmup``, the
median; with ``--rounds R``, R interleaved rounds over the caps and the median of theirs; CPU
time of the process by default, which a neighbour's load changes least on one thread), unless
``--no-timing``.

    python benchmarks/coarse_degree.py [--sizes 5000 15000] [--caps none 12 16 24] [--rules]
        [--latent 64 --hidden-layers 1 --no-layer-norm] [--threads 1] [--steps 5] [--rounds 1]

Writes ``--out`` (JSON) and prints markdown tables; ends with one line per size:

    coarse degree N nodes: cap k edges/mesh a, inference x ms; ... (none: edges/mesh b, inference y ms)
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import scipy.sparse as sp

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from scaling import cached_plate, run_worker  # noqa: E402

MIN_NODES = 32  # scaling.py's hierarchies (model_costs.MIN_NODES)


@functools.cache
def _diameter(n: int, indptr: bytes, indices: bytes, chunk: int = 4096) -> int:
    """Bitset BFS from ``chunk`` sources at a time: row v holds the sources within k hops of v; the
    hops until no row grows are the largest eccentricity of those sources."""
    indptr, indices = np.frombuffer(indptr, np.int64), np.frombuffer(indices, np.int32)
    if not indices.size:
        return 0
    best, starts = 0, indptr[:-1]
    for first in range(0, n, chunk):
        sources = np.arange(first, min(first + chunk, n))
        balls = np.zeros((n, (chunk + 63) // 64), dtype=np.uint64)
        offset = sources - first
        balls[sources, offset // 64] = np.left_shift(np.uint64(1), (offset % 64).astype(np.uint64))
        hops = 0
        while True:
            grown = balls | np.bitwise_or.reduceat(balls[indices], starts, axis=0)
            if np.array_equal(grown, balls):
                break
            balls, hops = grown, hops + 1
        best = max(best, hops)
    return best


def diameter(adjacency: sp.csr_matrix) -> int:
    """Exact hop diameter (the largest finite distance; graphs without isolated nodes): BFS from every
    node (remembered per graph: every cap shares the mesh)."""
    return _diameter(adjacency.shape[0], adjacency.indptr.astype(np.int64).tobytes(),
                     adjacency.indices.astype(np.int32).tobytes())


def top_k_rule(mutual: bool):
    """A coarse rule for ``bsms.graph.hierarchy._coarse_level``: each node's ``cap`` pairs with the most
    two-paths (ties: the smaller index), an edge where either end (``mutual``: both ends) keeps it,
    split components rejoined as the library's rule rejoins them."""
    from bsms.graph.capping import path_counts, reconnecting_pairs

    def coarse(adjacency, closed, seeds, kept, cap):
        counts = path_counts(closed).tocoo()
        row, col, count = counts.row.astype(np.int64), counts.col.astype(np.int64), counts.data
        order = np.lexsort((col, -count, row))
        rank = np.empty(row.size, dtype=np.int64)
        rank[order] = np.arange(row.size) - np.searchsorted(row[order], row[order])
        lo, hi = np.minimum(row, col), np.maximum(row, col)
        by_pair = np.argsort(lo * kept.size + hi, kind="stable")  # a pair's two directions, side by side
        keeps = (rank[by_pair] < cap).reshape(-1, 2)
        lo, hi, count = lo[by_pair[0::2]], hi[by_pair[0::2]], count[by_pair[0::2]]
        ranking = np.lexsort((hi, lo, -count))
        lo, hi = lo[ranking], hi[ranking]
        accepted = (keeps.all(axis=1) if mutual else keeps.any(axis=1))[ranking]
        accepted[reconnecting_pairs(lo, hi, accepted, kept.size)] = True
        pattern = sp.csr_matrix((np.ones(2 * int(accepted.sum())), (np.concatenate([lo[accepted], hi[accepted]]),
                                np.concatenate([hi[accepted], lo[accepted]]))), shape=(kept.size, kept.size))
        pattern.sort_indices()
        return pattern

    return coarse


def level_stats(mesh, cap: int | None, rule: str = "greedy") -> dict:
    """The levels of ``mesh`` under ``cap`` with ``rule`` (``greedy``: the library's)."""
    from bsms.graph import bistride_levels
    from bsms.graph import hierarchy as hierarchy_module

    if rule == "greedy":
        hierarchy = bistride_levels(mesh, levels="auto", min_nodes=MIN_NODES, max_coarse_degree=cap)
    else:
        with mock.patch.object(hierarchy_module, "_coarse_level", top_k_rule(rule == "mutual")):
            hierarchy = bistride_levels(mesh, levels="auto", min_nodes=MIN_NODES, max_coarse_degree=cap)
    levels = hierarchy.levels
    return {"nodes": [level.n_nodes for level in levels], "edges": [level.n_edges for level in levels],
            "max_degree": [int(np.diff(level.adjacency.indptr).max(initial=0)) for level in levels],
            "diameter": [diameter(level.adjacency) for level in levels],
            "edges_over_mesh": sum(level.n_edges for level in levels) / levels[0].n_edges}


def one_timing(size: int, cap: int | None, args) -> dict:
    spec = {"data": str(args.data), "steps": args.steps, "warmup": args.warmup, "threads": args.threads,
            "device": "cpu", "latent": args.latent, "memory_cap": 16.0, "clock": args.clock,
            "hidden_layers": args.hidden_layers, "layer_norm": not args.no_layer_norm, "size": size,
            "model": "bsms_gnn", "transition": "bistride", "batch": 1, "kind": "model",
            "phase": "infer" if args.infer_only else "time"}
    if cap is not None:
        spec["max_coarse_degree"] = cap
    return run_worker(spec)


def timings(size: int, caps: list, args) -> dict:
    """Per cap, the median over ``--rounds`` of each process's median steps; rounds interleave the caps,
    so that a neighbour's load falls on all of them alike."""
    runs = {cap: [] for cap in caps}
    for _ in range(args.rounds):
        for cap in caps:
            runs[cap].append(one_timing(size, cap, args))
    return {cap: {key: float(np.median([r[key] for r in results])) for key in ("train_s", "infer_s")
                  if key in results[0]}
            | {"rounds": results} for cap, results in runs.items()}


def _ms(time: dict, key: str) -> str:
    return "-" if key not in time else f"{1e3 * time[key]:.4g}"


def tables(size: int, rows: dict) -> list[str]:
    lines = [f"\n{size} nodes: per level nodes / directed edges / largest degree / diameter",
             "| rule | levels | nodes | edges | largest degree | diameter | edges / mesh | train, infer (ms) |",
             "|---|---|---|---|---|---|---|---|"]
    for name, row in rows.items():
        time = row.get("time", {})
        ms = "-" if "infer_s" not in time else \
            f"{_ms(time, 'train_s')}, {_ms(time, 'infer_s')}"
        lines.append(f"| {name} | {len(row['nodes'])} | " + " | ".join(
            ", ".join(f"{v:,}" for v in row[key]) for key in ("nodes", "edges", "max_degree", "diameter"))
            + f" | {row['edges_over_mesh']:.2f} | {ms} |")
    return lines


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 15000], help="plate nodes (scaling.py's)")
    parser.add_argument("--caps", nargs="+", default=["none", "12", "16", "24"], help="caps; none: no cap")
    parser.add_argument("--rules", action="store_true", help="also the union and mutual top-k rules (levels only)")
    parser.add_argument("--no-timing", action="store_true", help="the levels only")
    parser.add_argument("--infer-only", action="store_true",
                        help="time the inference step alone (no training steps; more --steps for as long a run)")
    parser.add_argument("--steps", type=int, default=5, help="timed steps per process (default 5)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed steps first (default 1)")
    parser.add_argument("--rounds", type=int, default=1, help="timing rounds over the caps, interleaved (default 1)")
    parser.add_argument("--latent", type=int, default=128, help="latent and hidden width (default 128)")
    parser.add_argument("--hidden-layers", type=int, default=2, help="hidden layers of every MLP (default 2)")
    parser.add_argument("--no-layer-norm", action="store_true", help="BSMS-GNN without LayerNorm (the lean blocks)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per process (default 1)")
    parser.add_argument("--clock", choices=("cpu", "wall"), default="cpu",
                        help="cpu: the process's CPU time (one thread: what a neighbour's load changes least; "
                             "default), wall: elapsed time")
    parser.add_argument("--data", type=Path, default=Path("data/scaling"), help="scaling.py's mesh and hierarchy cache")
    parser.add_argument("--out", type=Path, default=Path("runs/benchmarks/coarse_degree.json"))
    args = parser.parse_args(argv)
    try:
        args.caps = [None if c == "none" else int(c) for c in args.caps]
    except ValueError:
        parser.error("--caps takes integers >= 1 or none")
    if any(c is not None and c < 1 for c in args.caps) or min(args.steps, args.rounds) < 1 or args.warmup < 0:
        parser.error("--caps must be >= 1 (or none), --steps and --rounds >= 1, --warmup >= 0")
    return args


def main(argv=None) -> int:
    args = parse(argv)
    from datagen.compiled import cpu_summary
    from datagen.mesh import Mesh

    print(f"coarse degree: {cpu_summary()}", flush=True)
    results, summary = {}, []
    for size in args.sizes:
        mesh = Mesh(*cached_plate(args.data, size))
        rows = {}
        times = {} if args.no_timing else timings(size, args.caps, args)
        for cap in args.caps:
            name = "none" if cap is None else f"cap {cap}"
            rows[name] = level_stats(mesh, cap)
            if cap in times:
                rows[name]["time"] = times[cap]
            for rule in ("union", "mutual") if args.rules and cap is not None else ():
                rows[f"{rule} {cap}"] = level_stats(mesh, cap, rule)
        results[str(size)] = rows
        print("\n".join(tables(size, rows)), flush=True)
        base = rows.get("none", {})
        parts = [f"{name} edges/mesh {row['edges_over_mesh']:.2f}"
                 + ("" if "time" not in row else f", inference {1e3 * row['time']['infer_s']:.4g} ms")
                 for name, row in rows.items() if name.startswith("cap")]
        summary.append(f"coarse degree {mesh.n_nodes} nodes: " + "; ".join(parts) + (
            "" if not base else f" (none: edges/mesh {base['edges_over_mesh']:.2f}"
            + ("" if "time" not in base else f", inference {1e3 * base['time']['infer_s']:.4g} ms") + ")"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"cpu": cpu_summary(), "args": {k: str(v) for k, v in vars(args).items()},
                                    "results": results}, indent=1))
    print("\n".join(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
