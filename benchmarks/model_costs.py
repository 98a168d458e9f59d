"""The thesis' cost comparison (§4.4.3, Tables 4.5-4.7): train step, inference step and peak
training memory of BSMS-GNN, MeshGraphNets, MS-GNN-Grid and GraphUNets, and of BSMS-GNN's
five transitions, on the same batches of 2D graphs of about 1k, 5k, 15k and 45k nodes.

Graphs: cylinder-flow-like channels (a 1.6 x 0.41 rectangle around a disk whose centre and
radius vary per mesh, seeded), meshed by gmsh to the target node count and cached in
``--data/model_costs/``. Each graph of a batch is a different mesh; each frame displaces its
nodes by a smooth field and gives them smooth velocities and targets (seeded), so every model
sees exactly the same numbers. The hierarchy is bi-stride with MinAve seeding, pooled until a
level has fewer than 32 nodes (the thesis' 7 levels at 1.9k nodes, 9 at 5.2k); GraphUNets uses
as many levels, MeshGraphNets 15 passes, MS-GNN-Grid the thesis' [4, 2, 2, 4] passes with an
automatic cell size. Meshes only (no contact edges: the thesis' flow cases have none). MLPs:
two hidden layers of ``--latent`` (128) units, as the thesis.

Every (model, size, batch) runs in fresh processes, one for time and one for memory, and the
models are interleaved (A B C ... A B C ...) over ``--rounds`` so that load drift on a shared
machine hits all alike; a time is the median over rounds of each process' median step
(``--clock cpu``: CPU seconds of the process instead of wall seconds, steadier where other
processes share the cores).
Memory is measured as in ``benchmarks/train_step.py`` (CPU: the resident-set high-water mark
over the training steps, freed blocks returned to the OS; CUDA: max_memory_allocated). A
process that runs out of the ``--memory-cap`` (address space on CPU) reports ``-`` as the
thesis' tables do for configurations that did not fit.

Prints one table per graph size and batch size (absolute values, then ratios to BSMS-GNN),
writes everything to ``--out`` (JSON), and ends with exactly

    model costs @5k: MGN/BSMS train T1 mem M1, GRID/BSMS train T2 mem M2, GUNETS/BSMS train T3 mem M3

(the 5k graphs at the smallest batch size).

    python benchmarks/model_costs.py --quick          # the four models, 5k nodes, batch 2: minutes
    python benchmarks/model_costs.py                  # 1k-45k nodes, batches 2-16: hours
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from train_step import MemoryMeter, release_freed_memory  # noqa: E402

# (label, model.name, model.transition)
VARIANTS = (
    ("BSMS", "bsms_gnn", "bistride"),
    ("MGN", "meshgraphnets", "bistride"),
    ("GRID", "ms_gnn_grid", "bistride"),
    ("GUNETS", "graph_unets", "bistride"),
    ("T-none", "bsms_gnn", "none"),
    ("T-graph_conv", "bsms_gnn", "graph_conv"),
    ("T-pos_kernel", "bsms_gnn", "pos_kernel"),
    ("T-learnable", "bsms_gnn", "learnable"),
)
SIZES = (1000, 5000, 15000, 45000)
BATCHES = (2, 4, 8, 16)
CUDA_BATCHES = (2, 4, 8, 16, 32, 64)
MIN_NODES = 32
# the thesis' ratios to BSMS-GNN at its scales (Table 4.5 train time per step, Table 4.6 training
# RAM at batch 2), per case: cylinder (1.9k nodes), airfoil (5.2k), plate (1.3k, 3D), font (13k)
THESIS = {
    "MGN": {"train": "1.90 / 1.95 / 3.15 / 2.56", "mem": "1.35 / 1.51 / 1.31 / 1.99"},
    "GRID": {"train": "1.51 / 1.34 / 3.19 / 2.33", "mem": "1.16 / 1.14 / 1.44 / 1.73"},
    "GUNETS": {"train": "1.60 / 2.93 / 2.05 / 39.9", "mem": "9.68 / - / - / -"},
}


# ----------------------------------------------------------------------------- meshes
def channel(nodes: int, variant: int):
    """A meshed channel with a disk hole of about ``nodes`` nodes (gmsh; sizes refined twice)."""
    from datagen.shapes import polygon

    rng = np.random.default_rng(1000 + variant)
    cx, cy, r = 0.2 + 0.1 * rng.random(), 0.18 + 0.05 * rng.random(), 0.04 + 0.02 * rng.random()
    outer = np.array([[0.0, 0.0], [1.6, 0.0], [1.6, 0.41], [0.0, 0.41]])
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    hole = np.stack([cx + r * np.cos(angles), cy + r * np.sin(angles)], axis=1)
    area = 1.6 * 0.41 - np.pi * r * r
    size = math.sqrt(2 * area / (math.sqrt(3) * nodes))  # equilateral triangles: N ~ 2A / (sqrt(3) h^2)
    for _ in range(3):
        mesh = polygon(outer, [hole], size=size)
        size *= math.sqrt(mesh.nodes.shape[0] / nodes)
    return mesh


def cached_mesh(folder: Path, nodes: int, variant: int) -> tuple[np.ndarray, np.ndarray]:
    return cached(folder / f"channel_{nodes}_{variant}.npz", lambda: channel(nodes, variant))


def cached(path: Path, make) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, cells) of the mesh ``make()`` returns, meshed once and kept at ``path`` (.npz)."""
    if not path.is_file():
        mesh = make()
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, nodes=mesh.nodes, cells=mesh.cells)
        tmp.replace(path)
    data = np.load(path)
    return data["nodes"], data["cells"]


def _extent(nodes: np.ndarray) -> float:
    """The mesh's largest side over the channel's 1.6 m, so that fields vary as much over any mesh."""
    return float(np.ptp(nodes, axis=0).max()) / 1.6


def frame(nodes: np.ndarray, cells: np.ndarray, seed: int, cache: Path, max_coarse_degree: int | None = None):
    """One LevelGraph on the mesh (2D or 3D): smooth displacement, velocity and target fields (seeded);
    max_coarse_degree: the hierarchy's coarse-degree cap (``bistride_levels``; None: none)."""
    from bsms.graph import bistride_levels
    from bsms.level_graph import frame_graph, hierarchy_levels
    from datagen.mesh import Mesh

    mesh = Mesh(nodes, cells)
    hierarchy = bistride_levels(mesh, levels="auto", min_nodes=MIN_NODES, max_coarse_degree=max_coarse_degree,
                                cache_dir=cache)
    rng = np.random.default_rng(seed)
    dim = nodes.shape[1]
    k = rng.normal(size=(3, dim, dim)) * 4 / _extent(nodes)

    def smooth(j: int) -> np.ndarray:
        return np.sin(nodes @ k[j]) * 0.01

    return frame_graph(hierarchy_levels(hierarchy), rest_pos=nodes, pos=nodes + smooth(0), velocity=smooth(1),
                       node_type=np.zeros(len(nodes), np.int64), target=smooth(2)), hierarchy.n_levels


# ----------------------------------------------------------------------------- worker (child)
def _cap_memory(cap_bytes: int) -> None:
    """Limit the address space to what the process maps now plus ``cap_bytes`` (CPU)."""
    with open("/proc/self/status") as fh:
        vm_size = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmSize:"))
    resource.setrlimit(resource.RLIMIT_AS, (vm_size + cap_bytes, resource.RLIM_INFINITY))


def _measure(model, batches, optimizer, device, warmup: int, phase: str, clock_name: str) -> dict:
    import torch

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def train_step(batch, accumulate: bool) -> None:
        model.train()
        count = batch.loss_mask.sum().clamp(min=1).float()
        loss = model.loss(batch, accumulate=accumulate, reduction="sum") / count
        optimizer.zero_grad(set_to_none=False)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()

    clock = time.process_time if clock_name == "cpu" else time.perf_counter

    def timed(run) -> float:
        sync()
        start = clock()
        run()
        sync()
        return clock() - start

    if phase == "infer":  # inference alone (too slow to train here): the warm-up batches feed the normalisers
        with torch.no_grad():
            for batch in batches[:max(warmup, 1)]:
                model.loss(batch, accumulate=True, reduction="sum")
        model.eval()
        with torch.no_grad():
            return {"infer_s": float(np.median([timed(lambda b=b: model(b)) for b in batches][warmup:]))}
    meter = MemoryMeter(device)
    meter.start()
    train = [timed(lambda b=b, k=k: train_step(b, k < warmup)) for k, b in enumerate(batches)][warmup:]
    peak = meter.peak()
    model.eval()
    optimizer.zero_grad(set_to_none=True)
    with torch.no_grad():
        infer = [timed(lambda b=b: model(b)) for b in batches][warmup:]
    if phase == "memory":
        return {"train_peak_bytes": int(peak)}
    return {"train_s": float(np.median(train)), "infer_s": float(np.median(infer))}


def worker(spec: dict) -> dict:
    """One phase (``time`` or ``memory``) of one variant on one size and batch size."""
    if spec["phase"] == "memory" and spec["device"] == "cpu":
        release_freed_memory()
    import torch

    torch.set_num_threads(spec["threads"])
    folder = Path(spec["data"])
    graphs = []
    for i in range(spec["batch"] * (spec["warmup"] + spec["steps"])):
        nodes, cells = cached_mesh(folder, spec["size"], i % spec["batch"])
        graphs.append(frame(nodes, cells, seed=i, cache=folder / "hierarchies")[0])
    return measure_model(spec, graphs, 2)


def measure_model(spec: dict, graphs: list, dim: int) -> dict:
    """Build ``spec``'s model for ``dim`` and measure it on ``graphs`` (``spec["batch"]`` per step):
    the ``phase``'s figures, the levels run and the mean nodes per batch."""
    import torch
    from torch_geometric.data import Batch

    from bsms.run import build_model, load_config

    device = torch.device(spec["device"])
    # every graph needs the same level count to batch: cut to the shallowest mesh's depth
    depth = min(g.n_levels for g in graphs)
    batches = [Batch.from_data_list(graphs[k:k + spec["batch"]]).to(device)
               for k in range(0, len(graphs), spec["batch"])]
    config = load_config({
        "name": "model_costs", "dataset": {"config": "unused"},
        "graph": {"levels": depth, "contact": False, "obstacles": False},
        "model": {"name": spec["model"], "transition": spec["transition"], "latent": spec["latent"],
                  "hidden_layers": spec.get("hidden_layers", 2),
                  "layer_norm": spec.get("layer_norm", True) or spec["model"] != "bsms_gnn"},  # bsms_gnn's option
        "train": {"normalizer_steps": max(spec["warmup"], 1)},
    })
    torch.manual_seed(0)
    model = build_model(config, dim).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    if spec["device"] == "cpu" and spec["memory_cap"] > 0:
        _cap_memory(int(spec["memory_cap"] * 2**30))
    try:
        result = _measure(model, batches, optimizer, device, spec["warmup"], spec["phase"], spec["clock"])
    except (RuntimeError, MemoryError) as exc:
        if "memory" not in str(exc).lower() and not isinstance(exc, MemoryError):
            raise
        result = {"oom": True}
    return {**result, "levels": depth, "nodes": float(np.mean([b.num_nodes for b in batches]))}


def run_worker(spec: dict) -> dict:
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        sys.stderr.write(done.stderr[-4000:])
        raise SystemExit(f"the {spec['model']} ({spec['transition']}) worker failed (exit {done.returncode})")
    return json.loads(done.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- parent
def measure_cell(spec: dict, variants, rounds: int) -> dict:
    """Every variant on one (size, batch): interleaved rounds of fresh time and memory processes."""
    runs = {label: [] for label, _, _ in variants}
    for _ in range(rounds):
        for label, name, transition in variants:
            timing = run_worker({**spec, "model": name, "transition": transition, "phase": "time"})
            memory = run_worker({**spec, "model": name, "transition": transition, "phase": "memory"})
            runs[label].append({**timing, **memory})
    cell = {}
    for label, results in runs.items():
        ok = [r for r in results if not r.get("oom")]
        cell[label] = {"oom": True} if len(ok) < len(results) else {
            "train_s": float(np.median([r["train_s"] for r in ok])),
            "infer_s": float(np.median([r["infer_s"] for r in ok])),
            "train_peak_bytes": int(np.median([r["train_peak_bytes"] for r in ok])),
            "nodes": ok[0]["nodes"], "levels": ok[0]["levels"], "rounds": results,
        }
    return cell


def ratio(cell: dict, label: str, key: str) -> float | None:
    a, b = cell.get(label, {}), cell.get("BSMS", {})
    if a.get("oom") or b.get("oom") or key not in a or key not in b:
        return None
    return a[key] / b[key]


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def print_cell(size: int, batch: int, cell: dict) -> None:
    base = cell["BSMS"]
    nodes = f"{base['nodes']:.0f} nodes per batch, {base['levels']} levels" if not base.get("oom") else ""
    print(f"\n~{size} nodes per graph, batch {batch} ({nodes})")
    print(f"  {'model':<14}{'train ms':>10}{'infer ms':>10}{'train MB':>10}{'train/B':>9}{'infer/B':>9}{'mem/B':>8}")
    for label, result in cell.items():
        if result.get("oom"):
            print(f"  {label:<14}{'-':>10}{'-':>10}{'-':>10}{'-':>9}{'-':>9}{'-':>8}")
            continue
        print(f"  {label:<14}{result['train_s'] * 1e3:>10.1f}{result['infer_s'] * 1e3:>10.1f}"
              f"{result['train_peak_bytes'] / 2**20:>10.1f}{_fmt(ratio(cell, label, 'train_s')):>9}"
              f"{_fmt(ratio(cell, label, 'infer_s')):>9}{_fmt(ratio(cell, label, 'train_peak_bytes')):>8}", flush=True)


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="the four models (no transition variants) at 5k nodes, batch 2, 1 round (minutes)")
    parser.add_argument("--sizes", type=int, nargs="+", help=f"nodes per graph (default {list(SIZES)})")
    parser.add_argument("--batches", type=int, nargs="+", help="batch sizes (default 2 4 8 16; CUDA up to 64)")
    parser.add_argument("--models", nargs="+", help="labels to run (default all: "
                        + " ".join(label for label, _, _ in VARIANTS) + ")")
    parser.add_argument("--steps", type=int, help="timed steps per process (default 5; quick 2)")
    parser.add_argument("--warmup", type=int, help="untimed steps first (default 2; quick 1)")
    parser.add_argument("--rounds", type=int, help="interleaved rounds (default 2; quick 1)")
    parser.add_argument("--latent", type=int, default=128, help="latent and hidden width (default 128)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads per process (default 2)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                        help="wall seconds, or the process' CPU seconds (all its threads: steadier on a busy "
                             "machine, where other processes take turns on the cores; CPU only)")
    parser.add_argument("--memory-cap", type=float, default=12.0,
                        help="GiB a CPU process may map beyond its start before it counts as out of memory "
                             "(default 12; 0: no cap)")
    parser.add_argument("--data", type=Path, default=Path("data/model_costs"), help="mesh cache folder")
    parser.add_argument("--out", type=Path, default=Path("runs/benchmarks/model_costs.json"))
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    cuda = args.device.startswith("cuda")
    args.sizes = args.sizes or ([5000] if args.quick else list(SIZES))
    args.batches = args.batches or ([2] if args.quick else list(CUDA_BATCHES if cuda else BATCHES))
    args.steps = args.steps or (2 if args.quick else 5)
    args.warmup = (1 if args.quick else 2) if args.warmup is None else args.warmup
    args.rounds = args.rounds or (1 if args.quick else 2)
    labels = [label for label, _, _ in VARIANTS]
    args.models = args.models or (labels[:4] if args.quick else labels)  # quick: the four models
    unknown = [m for m in args.models if m not in labels]
    if unknown:
        parser.error(f"unknown --models {' '.join(unknown)}; choose from {' '.join(labels)}")
    if "BSMS" not in args.models:
        args.models.insert(0, "BSMS")  # the baseline of every ratio
    for key in ("steps", "rounds", "latent", "threads"):
        if getattr(args, key) < 1:
            parser.error(f"--{key} must be >= 1")
    if args.warmup < 0:
        parser.error("--warmup must be >= 0")
    if min(args.sizes) < 100 or min(args.batches) < 1:
        parser.error("--sizes must be >= 100 nodes and --batches >= 1")
    if 5000 not in args.sizes:
        parser.error("--sizes must include 5000: the last line reports the ratios at 5k nodes")
    return args


def main(argv=None) -> None:
    args = parse(argv)
    if args.worker is not None:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    variants = [v for v in VARIANTS if v[0] in args.models]
    for size in args.sizes:  # mesh the graphs once, outside the timed processes
        for variant in range(max(args.batches)):
            cached_mesh(args.data, size, variant)
    print(f"model costs: sizes {args.sizes}, batches {args.batches}, {args.warmup} warm-up + {args.steps} timed "
          f"steps, {args.rounds} round(s), {args.threads} threads, {args.device}, latent {args.latent}, "
          f"{args.clock} clock", flush=True)
    if args.clock == "cpu" and args.device != "cpu":
        raise SystemExit("--clock cpu times CPU processes; use the wall clock with --device cuda")
    spec = {"data": str(args.data), "steps": args.steps, "warmup": args.warmup, "threads": args.threads,
            "device": args.device, "latent": args.latent, "memory_cap": args.memory_cap, "clock": args.clock}
    cells = {}
    for size in args.sizes:
        for batch in args.batches:
            cell = measure_cell({**spec, "size": size, "batch": batch}, variants, args.rounds)
            cells[f"{size}x{batch}"] = cell
            print_cell(size, batch, cell)
    at5k = cells[f"5000x{min(args.batches)}"]
    print("\nthe thesis' ratios to BSMS-GNN (cylinder / airfoil / plate / font; Tables 4.5, 4.6 batch 2):")
    for label, values in THESIS.items():
        print(f"  {label}/BSMS: train {values['train']}, memory {values['mem']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    report = {"args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
              "machine": platform.processor() or platform.machine(), "cells": cells}
    args.out.write_text(json.dumps(report, indent=1))
    parts = [f"{label}/BSMS train {_fmt(ratio(at5k, label, 'train_s'))} "
             f"mem {_fmt(ratio(at5k, label, 'train_peak_bytes'))}" for label in ("MGN", "GRID", "GUNETS")]
    print(f"model costs @5k: {', '.join(parts)}")


if __name__ == "__main__":
    main()
