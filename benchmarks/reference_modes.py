"""A-ULMPM reference configurations: rebuilds, cost, numerical fracture and accuracy per mode.

For each scene (rotating_plate, stretched_bar, droplet — their defaults are the test settings)
and each mode (eulerian, total, adaptive) prints: kernel rebuilds per 10^4 steps, wall time
per step, the fracture measure (largest fraction of body-mesh edges longer than twice the
background cell size over the run), and the error against the eulerian run (largest distance
between the centres of mass over the run, divided by how far the eulerian one travels, or by
the background cell size when it travels less: the plate and the bar hardly move).
Then the cost of the contact trigger (colliding_disks, adaptive with and without it) and the
throughput of a 20k-particle 2D plate in total and eulerian mode per kernel. Writes a chart.

    python benchmarks/reference_modes.py [--out docs/images/reference_modes.png] [--threads 2] [--quick]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

import datagen
from datagen.mpm.solver import step
from datagen.simulation import build_simulation

SCENES = ("rotating_plate", "stretched_bar", "droplet")
MODES = ("eulerian", "total", "adaptive")


def fracture(traj) -> float:
    edges = traj.mesh.edges
    lengths = np.linalg.norm(traj.positions[:, edges[:, 0]] - traj.positions[:, edges[:, 1]], axis=-1)
    return float((lengths > 2 * traj.config["params"]["mesh_size"]).mean(axis=1).max())


def com_error(traj, reference) -> float:
    a, b = traj.diagnostics["center_of_mass"], reference.diagnostics["center_of_mass"]
    scale = max(np.linalg.norm(b - b[0], axis=1).max(), traj.config["params"]["mesh_size"])
    return float(np.linalg.norm(a - b, axis=1).max() / scale)


def modes_table(threads: int) -> dict:
    rows = {}
    print(f"{'scene':<16}{'mode':<10}{'rebuilds/1e4 steps':>20}{'ms/step':>10}{'fracture':>10}{'COM err':>10}"
          f"{'contact':>9}")
    for scene in SCENES:
        runs = {m: datagen.simulate({"scene": scene, "solver": {"reference": m, "threads": threads}}) for m in MODES}
        for mode, traj in runs.items():
            steps = traj.substeps * (len(traj.times) - 1)
            row = {"rebuilds": 1e4 * traj.kernel_rebuilds / steps, "ms_per_step": 1e3 * traj.wall_time / steps,
                   "fracture": fracture(traj), "error": com_error(traj, runs["eulerian"]),
                   "contact": int(traj.diagnostics["contact_rebuilds"][-1])}
            rows[(scene, mode)] = row
            print(f"{scene:<16}{mode:<10}{row['rebuilds']:>20.1f}{row['ms_per_step']:>10.2f}{row['fracture']:>10.3f}"
                  f"{row['error']:>10.4f}{row['contact']:>9d}")
    return rows


def contact_cost(threads: int) -> None:
    """Two disks colliding: the contact trigger's extra rebuilds and time (adaptive)."""
    print("\ncontact trigger on colliding_disks (adaptive, epsilon 0.5, fraction 0.1):")
    base = {"scene": "colliding_disks", "output": {"frames": 20, "frame_interval": 0.1}}
    for margin in (1.0, None):
        solver = {"reference": "adaptive", "epsilon": 0.5, "fraction": 0.1, "contact_margin": margin,
                  "threads": threads, "cfl": 0.6}
        traj = datagen.simulate({**base, "solver": solver})
        steps = traj.substeps * (len(traj.times) - 1)
        half = traj.velocities.shape[1] // 2  # colliding_disks: the first disk's vertices come first
        v = traj.velocities[-1, :half, 0].mean()
        print(f"  contact_margin={margin!s:<5} rebuilds {traj.kernel_rebuilds:4d} (contact "
              f"{int(traj.diagnostics['contact_rebuilds'][-1])}) in {steps} steps, "
              f"{1e3 * traj.wall_time / steps:.2f} ms/step, disk 0 mean x-velocity {v:+.3f} m/s (starts +0.1)")


def throughput(threads: int, steps: int = 10) -> dict:
    """Particle-steps per second of a ~20k-particle plate, per kernel, mode and dtype."""
    print(f"\nthroughput, ~20k particles in 2D, {threads} threads:")
    out = {}
    torch.set_num_threads(threads)
    for kernel in ("umls", "linear", "bspline"):
        for dtype in ("float64", "float32"):
            for mode in ("total", "eulerian"):
                transfer = "flip"
                config = {"scene": "rotating_plate", "params": {"side": 0.7, "mesh_size": 0.01, "omega": 5.0},
                          "solver": {"reference": mode, "kernel": kernel, "transfer": transfer, "dtype": dtype}}
                sim = build_simulation(config)
                state = step(sim.model, step(sim.model, sim.state, sim.dt), sim.dt)  # warm-up; builds the kernel
                start = time.perf_counter()
                for _ in range(steps):
                    state = step(sim.model, state, sim.dt)
                rate = len(state.x) * steps / (time.perf_counter() - start)
                out[(kernel, dtype, mode)] = rate
                print(f"  {kernel:<8}{dtype:<9}{mode:<9}{len(state.x):>7d} particles {rate / 1e6:6.2f} M/s")
    return out


def chart(rows: dict, rates: dict | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("rebuilds", "kernel rebuilds per 10^4 steps", True), ("ms_per_step", "wall time per step (ms)", False),
              ("fracture", "fracture: edges > 2 cells (max fraction)", False),
              ("error", "centre-of-mass error vs eulerian", False)]
    fig, axes = plt.subplots(1, len(panels) + (rates is not None), figsize=(4.2 * (len(panels) + 1), 3.8))
    width = 0.25
    x = np.arange(len(SCENES))
    for ax, (key, title, log) in zip(axes, panels, strict=False):
        for j, mode in enumerate(MODES):
            ax.bar(x + (j - 1) * width, [max(rows[(s, mode)][key], 1e-6 if log else 0) for s in SCENES], width,
                   label=mode)
        ax.set_xticks(x, SCENES, rotation=15)
        ax.set_title(title, fontsize=10)
        if log:
            ax.set_yscale("log")
    axes[0].legend()
    if rates is not None:
        ax = axes[-1]
        labels = [f"{k}\n{d[5:]}" for k in ("umls", "linear", "bspline") for d in ("float64", "float32")]
        xs = np.arange(len(labels))
        for j, mode in enumerate(("total", "eulerian")):
            vals = [rates[(k, d, mode)] / 1e6 for k in ("umls", "linear", "bspline") for d in ("float64", "float32")]
            ax.bar(xs + (j - 0.5) * 0.4, vals, 0.4, label=mode)
        ax.axhline(3.0, color="k", ls="--", lw=0.8, label="target 3 M/s")
        ax.set_xticks(xs, labels, fontsize=8)
        ax.set_title("M particle-steps/s, 20k particles", fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"\nchart written to {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/images/reference_modes.png"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="skip the contact-trigger and throughput runs")
    args = parser.parse_args()
    rows = modes_table(args.threads)
    rates = None
    if not args.quick:
        contact_cost(args.threads)
        rates = throughput(args.threads)
    chart(rows, rates, args.out)


if __name__ == "__main__":
    main()
