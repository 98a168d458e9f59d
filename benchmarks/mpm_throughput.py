"""Solver throughput: particle-steps per second of UMLS-MPM (2D, 3D) and the structured B-spline solver.

An elastic block, spinning and drifting so that particles cross cells, sits in a box meshed
with element size about twice the particle spacing (the grid of the structured B-spline solver has
that spacing too). Every step recomputes the kernel (cell search included). If ``taichi`` is
importable, a structured MLS-MPM written in taichi runs on the same particle counts and the
ratio ours / taichi is printed (taichi is never a dependency).

By default glibc's malloc is told to keep freed memory (large mmap and trim thresholds, the
same as exporting MALLOC_MMAP_THRESHOLD_ / MALLOC_TRIM_THRESHOLD_): torch on CPU allocates
and frees megabyte temporaries every operation, and returning them to the kernel each time
costs page faults that can double the step time. --default-malloc measures without it.

    python benchmarks/mpm_throughput.py [--sizes 5000 20000 100000] [--threads 2] [--steps 10]
"""

from __future__ import annotations

import argparse
import ctypes
import importlib.util
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mpm import Model, State, cfl_time_step, step
from datagen.mpm.kernels import Grid, MeshTables
from datagen.mpm.materials import NeoHookean
from datagen.scenes.base import lattice

MATERIAL = NeoHookean(1e4, 0.3, 1.0)


def _block(n_particles: int, dim: int):
    """Particles filling the centre of a unit box: positions, velocities, volumes, spacing."""
    side = 0.6
    spacing = side / n_particles ** (1.0 / dim)
    x, _, step_ = lattice(np.full(dim, 0.2), np.full(dim, 0.8), spacing)
    centred = x - 0.5
    v = np.zeros_like(x)
    v[:, 0], v[:, 1] = -2.0 * centred[:, 1] + 0.3, 2.0 * centred[:, 0]  # spin + drift: cells are crossed
    return x, v, np.full(len(x), float(np.prod(step_))), float(step_.mean())


def umls_model(dim: int, spacing: float, device) -> Model:
    h = 2.0 * spacing
    domain = shapes.rectangle(1.0, 1.0, h) if dim == 2 else shapes.box((1.0, 1.0, 1.0), h)
    tables = MeshTables.build(with_extra_layer(domain), device=device)
    gravity = torch.zeros(dim, dtype=torch.float64, device=device)
    h_cfl = domain.edge_length_stats.min
    return Model(tables, "umls", "flip", ((MATERIAL, None),), (), gravity, tables.nodes, h_cfl)


def bspline_model(dim: int, spacing: float, device) -> Model:
    grid = Grid.covering(np.zeros(dim), np.ones(dim), 2.0 * spacing)
    nodes = torch.tensor(grid.nodes(), device=device)
    gravity = torch.zeros(dim, dtype=torch.float64, device=device)
    return Model(grid, "bspline", "flip", ((MATERIAL, None),), (), gravity, nodes, grid.spacing)


def time_steps(model: Model, state: State, steps: int, repeats: int = 3) -> float:
    """Best mean seconds per step over ``repeats`` runs of ``steps`` steps (after a warm-up)."""
    dt = cfl_time_step(model, state, 0.3)
    for _ in range(3):
        state = step(model, state, dt)
    best = math.inf
    for _ in range(repeats):
        if state.x.is_cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(steps):
            state = step(model, state, dt)
        if state.x.is_cuda:
            torch.cuda.synchronize()
        best = min(best, (time.perf_counter() - start) / steps)
    return best


def measure(kind: str, dim: int, n: int, steps: int, device) -> dict:
    x, v, vol, spacing = _block(n, dim)
    start = time.perf_counter()
    model = (umls_model if kind == "umls" else bspline_model)(dim, spacing, device)
    setup = time.perf_counter() - start
    state = State.at_rest_shape(x, v, vol, MATERIAL.density, device=device)
    per_step = time_steps(model, state, steps)
    return {"kind": kind, "dim": dim, "particles": len(x), "nodes": model.n_nodes,
            "setup_s": setup, "ms_per_step": 1e3 * per_step, "particle_steps_per_s": len(x) / per_step}


def _taichi_program(ti, x0: np.ndarray, v0: np.ndarray, volume: float, h: float):
    """Fields and one substep of structured quadratic MLS-MPM (APIC, Neo-Hookean) in taichi."""
    p, dim = x0.shape
    res = int(round(1.0 / h)) + 1
    mu, lam, mass = MATERIAL.mu, MATERIAL.lam, MATERIAL.density * volume
    x, v = ti.Vector.field(dim, float, p), ti.Vector.field(dim, float, p)
    C, F = ti.Matrix.field(dim, dim, float, p), ti.Matrix.field(dim, dim, float, p)
    grid_v, grid_m = ti.Vector.field(dim, float, (res,) * dim), ti.field(float, (res,) * dim)
    x.from_numpy(x0)
    v.from_numpy(v0)
    F.from_numpy(np.tile(np.eye(dim), (p, 1, 1)))

    @ti.kernel
    def substep(dt: float):
        for I in ti.grouped(grid_m):
            grid_v[I], grid_m[I] = ti.Vector.zero(float, dim), 0.0
        for q in x:  # P2G
            base = (x[q] / h - 0.5).cast(int)
            fx = x[q] / h - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            eye = ti.Matrix.identity(float, dim)
            tau = mu * (F[q] @ F[q].transpose() - eye) + lam * ti.log(F[q].determinant()) * eye
            affine = -dt * volume * 4.0 / h**2 * tau + mass * C[q]
            for off in ti.static(ti.grouped(ti.ndrange(*((3,) * dim)))):
                weight = 1.0
                for a in ti.static(range(dim)):
                    weight *= w[off[a]][a]
                grid_v[base + off] += weight * (mass * v[q] + affine @ ((off - fx) * h))
                grid_m[base + off] += weight * mass
        for I in ti.grouped(grid_m):
            if grid_m[I] > 0:
                grid_v[I] /= grid_m[I]
        for q in x:  # G2P
            base = (x[q] / h - 0.5).cast(int)
            fx = x[q] / h - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v, new_C = ti.Vector.zero(float, dim), ti.Matrix.zero(float, dim, dim)
            for off in ti.static(ti.grouped(ti.ndrange(*((3,) * dim)))):
                weight = 1.0
                for a in ti.static(range(dim)):
                    weight *= w[off[a]][a]
                new_v += weight * grid_v[base + off]
                new_C += 4.0 / h**2 * weight * grid_v[base + off].outer_product((off - fx) * h)
            v[q], C[q] = new_v, new_C
            x[q] += dt * new_v
            F[q] = (ti.Matrix.identity(float, dim) + dt * new_C) @ F[q]

    return substep


def taichi_rate(n: int, dim: int, steps: int) -> float | None:
    """Particle-steps/s of a structured quadratic MLS-MPM in taichi, or None without taichi."""
    try:
        import taichi as ti
    except ImportError:
        return None
    ti.init(arch=ti.cpu, default_fp=ti.f64)
    x0, v0, vol, spacing = _block(n, dim)
    h = 2.0 * spacing
    substep = _taichi_program(ti, x0, v0, float(vol[0]), h)
    dt = 0.3 * h / (MATERIAL.wave_speed + 2.0)
    substep(dt)  # compile
    ti.sync()
    start = time.perf_counter()
    for _ in range(steps):
        substep(dt)
    ti.sync()
    return len(x0) * steps / (time.perf_counter() - start)


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process (mallopt); False if unavailable."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(libc.mallopt(m_mmap_threshold, 1 << 28)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 100000])
    parser.add_argument("--dims", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=Path("runs/mpm_throughput"))
    parser.add_argument("--default-malloc", action="store_true", help="leave glibc malloc settings alone")
    args = parser.parse_args()
    tuned = False if args.default_malloc else keep_freed_memory()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    rows = []
    print(f"torch threads: {torch.get_num_threads()}, device: {device}, malloc keeps freed memory: {tuned}")
    has_taichi = importlib.util.find_spec("taichi") is not None
    if not has_taichi:
        print("taichi is not installed: the taichi comparison is skipped (pip install taichi to run it)")
    elif device.type != "cpu":
        print("the taichi comparison runs on the CPU only: skipped on", device)
    print(f"{'kernel':8s} {'dim':>3s} {'particles':>9s} {'nodes':>7s} {'ms/step':>8s} {'M p-steps/s':>11s} "
          f"{'vs bspline':>10s}")
    for dim in args.dims:
        for n in args.sizes:
            pair = {kind: measure(kind, dim, n, args.steps, device) for kind in ("bspline", "umls")}
            umls, bspline = pair["umls"]["particle_steps_per_s"], pair["bspline"]["particle_steps_per_s"]
            pair["umls"]["ratio_umls_over_bspline"] = umls / bspline
            rate = taichi_rate(n, dim, args.steps) if has_taichi and device.type == "cpu" else None
            if rate is not None:
                pair["umls"]["ratio_umls_over_taichi"] = pair["umls"]["particle_steps_per_s"] / rate
                pair["bspline"]["taichi_particle_steps_per_s"] = rate
            for kind, row in pair.items():
                ratio = row.get("ratio_umls_over_bspline", 1.0)
                print(f"{kind:8s} {dim:3d} {row['particles']:9d} {row['nodes']:7d} {row['ms_per_step']:8.1f} "
                      f"{row['particle_steps_per_s'] / 1e6:11.3f} {ratio:10.2f}", flush=True)
                rows.append(row)
            if rate is not None:
                print(f"{'taichi':8s} {dim:3d} {n:9d} {'':7s} {'':8s} {rate / 1e6:11.3f}   ours/taichi "
                      f"{pair['umls']['ratio_umls_over_taichi']:.3f}")
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {"threads": args.threads, "malloc_keeps_freed_memory": tuned, "taichi_installed": has_taichi,
               "rows": rows}
    (args.out / "results.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
