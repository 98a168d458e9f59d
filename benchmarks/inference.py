"""Inference speed of the learned simulators, against the machine's matmul rate and against the solver.

Sweep: BSMS-GNN (``--levels`` 6 levels) and MeshGraphNets (15 passes) at latent 64 and 128 on
2D disks of 1k-50k nodes and 3D balls of 1k-20k nodes (default graph options; one body, so
the contact edge sets are empty), in float32 and in bfloat16 where the hardware has it
(``--precisions f32 bf16`` forces bf16, emulated on CPUs without bfloat16 instructions).
The models are untrained (random weights; normalisers fed the graph once): speed does not
depend on the weights.

* ms/step: the network's forward on a prebuilt graph (``LearnedSimulator.velocity_change``),
  the median of ``--repeats`` calls after one warm-up call.
* GFLOP/step: 2 M K N summed over every matrix product the forward ran (their shapes are
  recorded by ``torch.profiler``), i.e. counted from the layer shapes as they ran.
* GFLOP/s achieved: those FLOPs over ms/step.
* attainable: the same products as plain dense matmuls (``torch.addmm`` of the same shapes
  and dtype on fresh operands), each timed in the same run (median); attainable GFLOP/s =
  FLOPs over their summed time, fraction = that time over ms/step.

The case of issue 14: glyph "B" of height 0.4 m in the 1 m glyph box, ``body_size`` 0.006,
``mesh_size`` 0.012, E = 2e6 Pa, frames of 0.01 s: the solver (``datagen.simulate``, one
thread) runs ``--case-frames`` frames, its frame time is their median; BSMS-GNN (latent 128,
``--levels`` levels, default ``GraphOptions``) rolls out ``--case-steps`` steps from frame 0
with ``bsms.rollouts.rollout.rollout`` at the default precision (``auto``), its step time is the
median of the rollout's step times (graph building, contacts and the network). Graph
building and the network alone are also timed (median of ``--repeats``).

Everything runs on ``--threads`` (1) torch threads in this one process. Prints a table, then
the case, writes everything to ``--out`` as JSON, and ends with the line
``inference: graph/body nodes R, BSMS step vs solver frame S x faster, fraction of attainable F``
where R is graph nodes over body nodes in the case's first frame, S the solver's frame time
over the BSMS-GNN step time, and F the lowest fraction of attainable of BSMS-GNN at latent 128
at the default precision over the meshes of 10k nodes or more.

    python benchmarks/inference.py [--quick] [--threads 1] [--out runs/inference]
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

SIZES = {2: [1000, 10000, 50000], 3: [1000, 10000, 20000]}
QUICK_SIZES = {2: [1000, 10000], 3: [1000]}
MODELS = ("bsms_gnn", "meshgraphnets")
LATENTS = (64, 128)
CASE = {"chars": ["B"], "height": 0.4, "body_size": 0.006, "mesh_size": 0.012, "E": 2e6}
LARGE = 10_000  # mesh size (nodes asked for) from which the fraction of attainable counts


# ----------------------------------------------------------------------------- timing
CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}
clock = CLOCKS["wall"]


def median_seconds(call, repeats: int) -> float:
    """Median time of ``call()`` over ``repeats`` calls after one warm-up call (on ``clock``)."""
    call()
    times = []
    for _ in range(repeats):
        start = clock()
        call()
        times.append(clock() - start)
    return float(np.median(times))


def matmul_shapes(call) -> Counter:
    """(M, K, N) -> count of the matrix products one ``call()`` runs (addmm, addmm_, mm)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU], record_shapes=True) as prof:
        call()
    shapes = Counter()
    for event in prof.events():
        if event.name in ("aten::addmm", "aten::addmm_"):
            (m, k), (_, n) = event.input_shapes[1], event.input_shapes[2]
        elif event.name == "aten::mm":
            (m, k), (_, n) = event.input_shapes[0], event.input_shapes[1]
        else:
            continue
        if m * k * n:
            shapes[m, k, n] += 1
    return shapes


def attainable_seconds(shapes: Counter, dtype: torch.dtype, repeats: int) -> float:
    """Summed median time of the products ``shapes`` as plain dense ``addmm`` in ``dtype``."""
    total = 0.0
    for (m, k, n), count in shapes.items():
        a, w, b = torch.randn(m, k, dtype=dtype), torch.randn(n, k, dtype=dtype), torch.randn(n, dtype=dtype)
        total += count * median_seconds(lambda a=a, w=w, b=b: torch.addmm(b, a, w.T), repeats)
    return total


# ----------------------------------------------------------------------------- the sweep
def mesh_of(dim: int, nodes: int):
    """A disk (2D) or ball (3D) of radius 1 meshed to about ``nodes`` nodes."""
    from datagen import shapes

    make = shapes.disk if dim == 2 else shapes.sphere
    size = 0.2
    for _ in range(3):  # node count ~ size^-dim: two corrections land within a few percent
        mesh = make(1.0, size)
        size *= (len(mesh.nodes) / nodes) ** (1.0 / dim)
    return mesh


def sweep_graph(mesh, levels: int):
    """The graph of ``mesh`` at rest with a smooth velocity field (default graph options)."""
    from bsms.data import GraphOptions, Scenario

    scenario = Scenario.build(mesh, GraphOptions(levels=levels), frame_dt=0.01)
    x = scenario.rest_pos
    return scenario.graph(x, 0.1 * np.sin(3.0 * x[:, ::-1]))


def untrained(core: str, dim: int, latent: int, levels: int, graph):
    """A LearnedSimulator whose normalisers have seen ``graph`` once."""
    from bsms.models.simulator import LearnedSimulator

    torch.manual_seed(0)
    model = LearnedSimulator(core, dim, n_levels=levels, contact=True, latent=latent)
    model(graph, accumulate=True)
    return model.eval()


def measure(model, graph, precision: str, repeats: int) -> dict:
    """Time, FLOPs and the attainable rate of one forward of ``model`` on ``graph``."""
    from bsms.models.precision import network_dtype

    def step():
        return model.velocity_change(graph, precision=precision)

    with torch.no_grad():
        seconds = median_seconds(step, repeats)
        shapes = matmul_shapes(step)
    flops = sum(2 * m * k * n * count for (m, k, n), count in shapes.items())
    attainable = attainable_seconds(shapes, network_dtype(precision, "cpu"), repeats)
    return {"ms_per_step": 1e3 * seconds, "gflop_per_step": flops / 1e9, "gflops": flops / seconds / 1e9,
            "attainable_gflops": flops / attainable / 1e9, "fraction": attainable / seconds}


def sweep(sizes: dict, precisions: list[str], levels: int, repeats: int) -> list[dict]:
    rows = []
    print(f"{'model':13s} {'latent':>6s} {'dim':>3s} {'nodes':>6s} {'edges':>7s} {'precision':>9s} {'ms/step':>8s} "
          f"{'GFLOP/step':>10s} {'GFLOP/s':>8s} {'attainable':>10s} {'fraction':>8s}")
    for dim, targets in sizes.items():
        for target in targets:
            mesh = mesh_of(dim, target)
            graph = sweep_graph(mesh, levels)
            for core in MODELS:
                for latent in LATENTS:
                    model = untrained(core, dim, latent, levels, graph)
                    for precision in precisions:
                        row = {"model": core, "latent": latent, "dim": dim, "size": target, "nodes": len(mesh.nodes),
                               "edges": int(graph.edge_index_0.shape[1]), "precision": precision,
                               **measure(model, graph, precision, repeats)}
                        rows.append(row)
                        print(f"{core:13s} {latent:6d} {dim:3d} {row['nodes']:6d} {row['edges']:7d} {precision:>9s} "
                              f"{row['ms_per_step']:8.1f} {row['gflop_per_step']:10.2f} {row['gflops']:8.1f} "
                              f"{row['attainable_gflops']:10.1f} {row['fraction']:8.2f}", flush=True)
    return rows


# ----------------------------------------------------------------------------- the case of issue 14
def solver_frames(frames: int):
    """The case's trajectory and the solver's time per frame on ``clock``: the median of the frame
    wall times, or the CPU time of a run of 1 + ``frames`` frames minus that of a run of one frame
    (the same meshing and set-up; a first run warms the process up)."""
    import datagen

    def run(count: int):
        return datagen.simulate({"scene": "glyphs", "params": CASE, "solver": {"threads": torch.get_num_threads()},
                                 "output": {"frames": count, "frame_interval": 0.01}})

    if clock is CLOCKS["wall"]:
        trajectory = run(frames)
        return trajectory, float(np.median(trajectory.frame_wall_times[1:]))
    seconds = []
    for count in (1, 1, 1 + frames):
        start = clock()
        trajectory = run(count)
        seconds.append(clock() - start)
    return trajectory, (seconds[2] - seconds[1]) / frames


def case(frames: int, steps: int, levels: int, repeats: int) -> dict:
    """The solver's frame and the BSMS-GNN step on the glyph "B" case, in this process."""
    from bsms.data import GraphOptions, Scenario
    from bsms.rollouts.rollout import rollout

    trajectory, solver_seconds = solver_frames(frames)
    scenario = Scenario.from_trajectory(trajectory, GraphOptions(levels=levels))
    x0 = scenario.positions(trajectory.positions, trajectory.obstacle_positions)[0]
    v0 = scenario.full(trajectory.velocities[:1], 0.0)[0]
    graph = scenario.graph(x0, v0)
    model = untrained("bsms_gnn", x0.shape[1], 128, levels, graph)
    start = clock()
    result = rollout(model, scenario, x0, v0, steps)  # warm-up: one untimed step
    step_seconds = float(np.median(result.step_seconds)) if clock is CLOCKS["wall"] else \
        (clock() - start) / (steps + 1)
    with torch.no_grad():
        network = median_seconds(lambda: model.velocity_change(graph, precision="auto"), repeats)
    building = median_seconds(lambda: scenario.graph(x0, v0), repeats)
    out = {"body_nodes": int(scenario.n_body), "graph_nodes": int(graph.num_nodes),
           "graph_nodes_max": int(np.max(result.graph_nodes, initial=graph.num_nodes)),
           "solver_frame_ms": 1e3 * solver_seconds, "substeps": int(trajectory.substeps),
           "step_ms": 1e3 * step_seconds, "network_ms": 1e3 * network, "graph_ms": 1e3 * building}
    print(f"case: body nodes {out['body_nodes']}, graph nodes {out['graph_nodes']} (at most "
          f"{out['graph_nodes_max']} over the rollout), solver frame {out['solver_frame_ms']:.0f} ms "
          f"({out['substeps']} substeps), BSMS-GNN step {out['step_ms']:.1f} ms (network {out['network_ms']:.1f} ms, "
          f"graph building {out['graph_ms']:.1f} ms)")
    return out


def main() -> None:
    from bsms.models.precision import bf16_supported

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="2D meshes of 1k and 10k nodes, 3D of 1k; shorter case")
    parser.add_argument("--precisions", nargs="+", choices=("f32", "bf16"),
                        help="default: f32, and bf16 where the hardware has it")
    parser.add_argument("--levels", type=int, default=6, help="BSMS-GNN levels (the mesh included)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--case-frames", type=int, default=3)
    parser.add_argument("--case-steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--clock", choices=tuple(CLOCKS), default="wall",
                        help="wall time, or this process's CPU time (steadier on a busy machine)")
    parser.add_argument("--out", type=Path, default=Path("runs/inference"))
    args = parser.parse_args()
    global clock
    clock = CLOCKS[args.clock]
    torch.set_num_threads(args.threads)
    precisions = args.precisions or (["f32", "bf16"] if bf16_supported("cpu") else ["f32"])
    auto = "bf16" if bf16_supported("cpu") else "f32"
    print(f"torch threads: {torch.get_num_threads()}, clock: {args.clock}, bfloat16 instructions: "
          f"{bf16_supported('cpu')}, precision auto = {auto}")
    rows = sweep(QUICK_SIZES if args.quick else SIZES, precisions, args.levels, args.repeats)
    found = case(2 if args.quick else args.case_frames, 5 if args.quick else args.case_steps, args.levels,
                 args.repeats)
    large = [r["fraction"] for r in rows if r["model"] == "bsms_gnn" and r["latent"] == 128
             and r["precision"] == auto and r["size"] >= LARGE]
    ratio = found["graph_nodes"] / found["body_nodes"]
    speedup = found["solver_frame_ms"] / found["step_ms"]
    fraction = min(large) if large else float("nan")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(
        {"threads": args.threads, "clock": args.clock, "bf16_instructions": bf16_supported("cpu"), "rows": rows,
         "case": found, "graph_body_ratio": ratio, "speedup": speedup, "fraction_of_attainable": fraction}, indent=1))
    print(f"inference: graph/body nodes {ratio:.2f}, BSMS step vs solver frame {speedup:.1f} x faster, "
          f"fraction of attainable {fraction:.2f}")


if __name__ == "__main__":
    main()
