"""The thesis' scaling analysis in 3D (§4.4.5, Fig. 4.10): the train step, the inference step and
the peak training memory of BSMS-GNN, MeshGraphNets and MS-GNN-Grid against node count on
tetrahedral meshes, beside the MPM solver's frame on as many particles.

Meshes: a 10 x 10 x 2 cm plate (DEFORMINGPLATE's shape) tetrahedralised by gmsh to about each
``--sizes`` node count (calibrated, cached in ``--data``). Each graph is one mesh, its nodes
displaced by smooth seeded fields (the same numbers for every model; ``model_costs.frame``). The
models are ``model_costs.py``'s: MLPs of ``--hidden-layers`` (2) hidden layers of ``--latent`` (128) units
(``--latent 64 --hidden-layers 1 --no-layer-norm``: the lean blocks of the published 2D models),
MeshGraphNets 15 passes, MS-GNN-Grid the thesis' [4, 2, 2, 4] passes, BSMS-GNN one pass per
level of a bi-stride hierarchy pooled until a level has fewer than 32 nodes (MinAve seeds; with
``--max-coarse-degree k``, at most k edges per node on its coarse levels: ``bsms.graph.capping``).
Every (model, size) runs in fresh processes, one for time and one for memory, measured as
``model_costs.py`` measures them (``--warmup`` then ``--steps`` training steps, then the same
graphs as inference passes; the median step; memory: the resident-set high-water mark over the
training steps). The inference step is the network on a built graph, as the thesis times it.
A model whose training step would take more than ``--max-step`` seconds at a size (the power law
through its two largest sizes so far) is only timed in inference there and above, and one whose
inference step would take more than ``--max-infer`` is not run (``-`` in the table); a
process that maps more than ``--memory-cap`` GiB counts as
out of memory (``-``), as the thesis' tables mark configurations that did not fit.

The solver: UMLS-MPM (``mpm_throughput.measure``, the kernel rebuilt every substep, float64) on a
block of the same number of particles, timed per substep; its frame is that times the substeps a
frame needs for the reference part the plate stands for: 10 cm across, E = 50 MPa, nu = 0.3,
rho = 1,000 kg/m^3 (the middle of the planned 3D press family), frames of 0.01 s, CFL 1 (the
data's): ``ceil(frame c / h)`` with ``c`` the dilatational wave speed and ``h`` the background
mesh's shortest edge at the part's scale. A frame costs particles x substeps, so its slope is
about 4/3; one learned step per frame has the network's slope.

Prints a table per size and one of fitted slopes (least squares of log time against log nodes
over the sizes each method ran), writes everything to ``--out`` (JSON) and, with ``--docs``, the
log-log figure ``docs/images/scaling.png`` and the table ``docs/scaling_table.md``; ends with exactly

    scaling: BSMS-GNN slope a, MeshGraphNets slope b, MS-GNN-Grid slope c, solver slope d, largest N nodes

(slopes of the inference step; the solver's of its frame; N the largest mesh BSMS-GNN ran).

    python benchmarks/scaling.py [--sizes 5000 15000 45000 150000 500000] [--threads 2] [--docs] [--resume]
        [--latent 128] [--hidden-layers 2] [--no-layer-norm] [--max-coarse-degree K]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from model_costs import VARIANTS, cached, frame, measure_model  # noqa: E402

MODELS = ("BSMS", "MGN", "GRID")
NAMES = {"BSMS": "BSMS-GNN", "MGN": "MeshGraphNets", "GRID": "MS-GNN-Grid", "solver": "solver"}
SIZES = (5000, 15000, 45000, 150000, 500000)
PLATE = (0.1, 0.1, 0.02)  # m
# the reference part the solver's frame is counted for
PART_WIDTH, E, NU, DENSITY, FRAME_DT, CFL = 0.1, 50e6, 0.3, 1000.0, 0.01, 1.0


# ----------------------------------------------------------------------------- meshes
def plate(nodes: int):
    """The plate meshed to about ``nodes`` nodes (gmsh; the element size corrected twice)."""
    from datagen.shapes import box

    size = (1.9 * math.prod(PLATE) / nodes) ** (1 / 3)  # tetrahedra: N ~ 1.9 V / h^3
    for _ in range(3):
        mesh = box(PLATE, size)
        if abs(mesh.n_nodes / nodes - 1) < 0.1:
            break
        size *= (mesh.n_nodes / nodes) ** (1 / 3)
    return mesh


def cached_plate(folder: Path, nodes: int) -> tuple[np.ndarray, np.ndarray]:
    return cached(folder / f"plate_{nodes}.npz", lambda: plate(nodes))


# ----------------------------------------------------------------------------- workers (children)
def model_worker(spec: dict) -> dict:
    """One phase (``time`` or ``memory``) of one model on one size."""
    if spec["phase"] == "memory":
        from train_step import release_freed_memory

        release_freed_memory()
    import torch

    torch.set_num_threads(spec["threads"])
    folder = Path(spec["data"])
    nodes, cells = cached_plate(folder, spec["size"])
    count = spec["warmup"] + (1 if spec["phase"] == "memory" else spec["steps"])  # memory: one step peaks
    cap = spec.get("max_coarse_degree")
    graphs = [frame(nodes, cells, seed=i, cache=folder / "hierarchies", max_coarse_degree=cap)[0] for i in range(count)]
    return measure_model(spec, graphs, 3)  # under --memory-cap once the model is built


def solver_worker(spec: dict) -> dict:
    """UMLS-MPM's substep on ``spec["size"]`` particles, and the substeps a frame of the reference part needs."""
    import torch
    from mpm_throughput import keep_freed_memory, measure, umls_model
    from taichi_mpm import block

    from datagen.mpm.materials import NeoHookean

    keep_freed_memory()
    torch.set_num_threads(spec["threads"])
    row = measure("umls", 3, spec["size"], spec["steps"], torch.device("cpu"))
    _, _, _, spacing = block(spec["size"], 3)
    block_width = 0.6  # mpm_throughput's block spans [0.2, 0.8]^3 of a unit box
    h = umls_model(3, spacing, torch.device("cpu")).h_cfl * PART_WIDTH / block_width
    c = NeoHookean(E, NU, DENSITY).wave_speed
    substeps = math.ceil(FRAME_DT * c / (CFL * h))
    return {"substep_s": row["ms_per_step"] / 1e3, "substeps": substeps,
            "frame_s": substeps * row["ms_per_step"] / 1e3, "nodes": float(row["particles"])}


def run_worker(spec: dict) -> dict:
    """A worker in a fresh process; {"oom": True} where it ran out of memory (or was killed for it)."""
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        if "MemoryError" in done.stderr or "out of memory" in done.stderr.lower() or done.returncode < 0:
            return {"oom": True}
        sys.stderr.write(done.stderr[-4000:])
        raise SystemExit(f"the {spec.get('model', 'solver')} worker failed (exit {done.returncode})")
    return json.loads(done.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- parent
def slope(points: list[tuple[float, float]]) -> float | None:
    """Least-squares slope of log y against log x (None under two points)."""
    if len(points) < 2:
        return None
    x, y = np.log(np.array(points, dtype=float)).T
    return float(np.polyfit(x, y, 1)[0])


def predicted(points: list[tuple[float, float]], nodes: float) -> float:
    """A step's time at ``nodes`` from the power law through the last two points (slope 1 from one)."""
    if not points:
        return 0.0
    if len(points) == 1:
        return points[-1][1] * nodes / points[-1][0]
    (n0, t0), (n1, t1) = points[-2:]
    return t1 * (nodes / n1) ** (math.log(t1 / t0) / math.log(n1 / n0))


def measure_size(size: int, spec: dict, cells: dict[int, dict], max_step: float, max_infer: float) -> dict:
    """Every model and the solver on one size. A model whose training step would take over
    ``max_step`` seconds here (the power law through its two largest sizes so far) is only timed in
    inference; one whose inference step would take over ``max_infer`` is not run."""
    cell = {}
    for label in MODELS:
        ran = [c[label] for c in cells.values() if "infer_s" in c[label]]
        train = predicted([(r["nodes"], r["train_s"]) for r in ran if "train_s" in r], size)
        infer = predicted([(r["nodes"], r["infer_s"]) for r in ran], size)
        earlier = [c[label] for c in cells.values()]
        if any("skipped" in r or r.get("inference_oom") for r in earlier):
            cell[label] = {"skipped": "skipped or out of memory in inference at a smaller size"}
            continue
        if infer > max_infer:
            cell[label] = {"skipped": f"its inference step would take {infer:.0f} s here"}
            continue
        _, name, transition = next(v for v in VARIANTS if v[0] == label)
        common = {**spec, "size": size, "model": name, "transition": transition, "batch": 1, "kind": "model"}
        if train > max_step or any("train_s" not in r for r in earlier):
            result = run_worker({**common, "phase": "infer"})
            cell[label] = {**result, "inference_oom": True} if result.get("oom") else result
            continue
        timing = run_worker({**common, "phase": "time"})
        memory = run_worker({**common, "phase": "memory"}) if not timing.get("oom") else {"oom": True}
        cell[label] = {**timing, **memory}
    cell["solver"] = run_worker({**spec, "size": size, "kind": "solver", "steps": 2})
    return cell


def _ms(result: dict, key: str) -> str:
    if result.get("oom"):
        return "OOM"
    return "-" if key not in result else f"{1e3 * result[key]:.4g}"


def table(cells: dict[int, dict]) -> list[str]:
    lines = ["| nodes | levels | " + " | ".join(f"{NAMES[m]} train / infer (ms), memory (MB)" for m in MODELS)
             + " | solver substep (ms) x substeps = frame (s) |", "|" + "---|" * (len(MODELS) + 3)]
    for size, cell in cells.items():
        base = cell["BSMS"]
        parts = [f"{base.get('nodes', size):.0f}", str(base.get("levels", "-"))]
        for label in MODELS:
            r = cell[label]
            mem = "-" if "train_peak_bytes" not in r else f"{r['train_peak_bytes'] / 2**20:.0f}"
            parts.append(f"{_ms(r, 'train_s')} / {_ms(r, 'infer_s')}, {mem}")
        s = cell["solver"]
        parts.append(f"{1e3 * s['substep_s']:.4g} x {s['substeps']} = {s['frame_s']:.3g}")
        lines.append("| " + " | ".join(parts) + " |")
    return lines


def slopes(cells: dict[int, dict]) -> dict[str, dict[str, float | None]]:
    fitted = {}
    for label in MODELS:
        ran = [(c[label]["nodes"], c[label]) for c in cells.values() if "infer_s" in c[label]]
        fitted[label] = {key: slope([(n, r[key]) for n, r in ran if key in r])
                         for key in ("infer_s", "train_s", "train_peak_bytes")}
    fitted["solver"] = {"frame_s": slope([(c["solver"]["nodes"], c["solver"]["frame_s"]) for c in cells.values()]),
                        "substep_s": slope([(c["solver"]["nodes"], c["solver"]["substep_s"])
                                            for c in cells.values()])}
    return fitted


def figure(cells: dict[int, dict], fitted: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for ax, key, title in zip(axes, ("infer_s", "train_s", "train_peak_bytes"),
                              ("inference step (s)", "training step (s)", "training memory (bytes)"), strict=True):
        for label in MODELS:
            points = sorted((c[label]["nodes"], c[label][key]) for c in cells.values() if key in c[label])
            if points:
                s = fitted[label][key]
                ax.loglog(*zip(*points, strict=True), "o-", label=f"{NAMES[label]}"
                          + ("" if s is None else f" (slope {s:.2f})"))
        if key == "infer_s":
            points = sorted((c["solver"]["nodes"], c["solver"]["frame_s"]) for c in cells.values())
            solver = fitted["solver"]["frame_s"]
            ax.loglog(*zip(*points, strict=True), "k^--",
                      label="solver frame" + ("" if solver is None else f" (slope {solver:.2f})"))
        ax.set(xlabel="nodes", title=title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="nodes per mesh")
    parser.add_argument("--steps", type=int, default=2, help="timed steps per process (default 2)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed steps first (default 1)")
    parser.add_argument("--latent", type=int, default=128, help="latent and hidden width (default 128)")
    parser.add_argument("--hidden-layers", type=int, default=2, help="hidden layers of every MLP (default 2)")
    parser.add_argument("--no-layer-norm", action="store_true",
                        help="BSMS-GNN without LayerNorm (with --latent 64 --hidden-layers 1: the lean blocks of "
                             "the published 2D models)")
    parser.add_argument("--max-coarse-degree", type=int, default=None,
                        help="BSMS-GNN's hierarchy: at most this many edges per node on the coarse levels "
                             "(graph.max_coarse_degree; default: no cap)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads per process (default 2)")
    parser.add_argument("--max-step", type=float, default=120.0,
                        help="a model whose training step would take longer (s) is timed in inference only "
                             "(default 120)")
    parser.add_argument("--max-infer", type=float, default=300.0,
                        help="a model whose inference step would take longer (s) is not run (default 300)")
    parser.add_argument("--resume", action="store_true",
                        help="keep the sizes --out already holds, measured with the same settings")
    parser.add_argument("--memory-cap", type=float, default=16.0,
                        help="GiB a process may map beyond its start before it counts as out of memory (default 16)")
    parser.add_argument("--data", type=Path, default=Path("data/scaling"), help="mesh and hierarchy cache")
    parser.add_argument("--out", type=Path, default=Path("runs/benchmarks/scaling.json"))
    parser.add_argument("--docs", action="store_true", help="write docs/images/scaling.png and docs/scaling_table.md")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    for key in ("steps", "latent", "threads", "hidden_layers"):
        if getattr(args, key) < 1:
            parser.error(f"--{key} must be >= 1")
    if args.warmup < 0 or min(args.sizes) < 500:
        parser.error("--warmup must be >= 0 and --sizes >= 500 nodes")
    if args.max_coarse_degree is not None and args.max_coarse_degree < 1:
        parser.error("--max-coarse-degree must be >= 1")
    args.sizes = sorted(set(args.sizes))
    return args


def main(argv=None) -> int:
    args = parse(argv)
    if args.worker is not None:
        spec = json.loads(args.worker)
        print(json.dumps(solver_worker(spec) if spec["kind"] == "solver" else model_worker(spec)))
        return 0
    from datagen.atomic import atomic_path
    from datagen.compiled import cpu_summary

    print(f"scaling: {args.warmup} warm-up + {args.steps} timed steps, {args.threads} threads, latent {args.latent}, "
          f"{args.hidden_layers} hidden layers, LayerNorm {not args.no_layer_norm}, coarse degree cap "
          f"{args.max_coarse_degree}; {cpu_summary()}", flush=True)
    spec = {"data": str(args.data), "steps": args.steps, "warmup": args.warmup, "threads": args.threads,
            "device": "cpu", "latent": args.latent, "memory_cap": args.memory_cap, "clock": "wall",
            "hidden_layers": args.hidden_layers, "layer_norm": not args.no_layer_norm}
    if args.max_coarse_degree is not None:  # absent when uncapped: --resume keeps files written before the option
        spec["max_coarse_degree"] = args.max_coarse_degree
    settings = {k: spec[k] for k in ("steps", "warmup", "threads", "latent", "hidden_layers", "layer_norm",
                                     "max_coarse_degree") if k in spec}
    done = {}
    if args.resume and args.out.is_file():  # sizes measured before with the same settings
        saved = json.loads(args.out.read_text())
        if saved.get("settings") == settings:
            done = {int(k): v for k, v in saved["cells"].items()}
    cells = {}
    for size in args.sizes:
        cells[size] = done.get(size) or measure_size(size, spec, cells, args.max_step, args.max_infer)
        print("\n".join(table({size: cells[size]})[-1:]), flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(args.out) as tmp:  # each size kept as it is measured (--resume)
            tmp.write_text(json.dumps({"settings": settings, "cpu": cpu_summary(),
                                       "cells": {str(k): v for k, v in cells.items()}}, indent=1))
    fitted = slopes(cells)
    lines = table(cells)
    print("\n".join(lines))
    print("\nslopes of log time (memory) against log nodes:")
    for label, values in fitted.items():
        print(f"  {NAMES[label]}: " + ", ".join(f"{k} {'-' if v is None else f'{v:.2f}'}" for k, v in values.items()))
    with atomic_path(args.out) as tmp:
        tmp.write_text(json.dumps({"settings": settings, "cpu": cpu_summary(), "args": {k: str(v) for k, v in
                                   vars(args).items()}, "cells": {str(k): v for k, v in cells.items()},
                                   "slopes": fitted}, indent=1))
    if args.docs:
        figure(cells, fitted, ROOT / "docs" / "images" / "scaling.png")
        (ROOT / "docs" / "scaling_table.md").write_text("\n".join(lines) + "\n")
    ran = [c["BSMS"]["nodes"] for c in cells.values() if "infer_s" in c["BSMS"]]

    def text(label: str, key: str = "infer_s") -> str:
        value = fitted[label][key]
        return "n/a" if value is None else f"{value:.2f}"

    print(f"scaling: BSMS-GNN slope {text('BSMS')}, MeshGraphNets slope {text('MGN')}, MS-GNN-Grid slope "
          f"{text('GRID')}, solver slope {text('solver', 'frame_s')}, largest {max(ran, default=0):.0f} nodes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
