"""Solver throughput: particle-steps per second of UMLS-MPM (2D, 3D) and the structured B-spline solver.

An elastic block, spinning and drifting so that particles cross cells, sits in a box meshed
with element size about twice the particle spacing (the grid of the structured B-spline solver has
that spacing too). Steps run as a simulation runs them: ``--steps`` substeps per call of
:func:`datagen.mpm.advance`, which runs eulerian UMLS substeps in one compiled call
(:mod:`datagen.mpm.fused`) and every other solver one Python step at a time. ``umls`` recomputes
the kernel every step (cell search included); ``umls python`` is the same solver one Python
step at a time (the compiled kernels between torch operators: how it ran before the compiled
substeps); in 3D the A-ULMPM ``total`` and ``adaptive`` reference configurations, which keep the
kernel, are timed too, and ``umls float32``: the compiled substeps with ``precision="float32"``
(the kernel, stress coefficients, node sums and G2P in single precision over a float64 state;
:mod:`datagen.mpm.fused`). A structured quadratic MLS-MPM written in taichi (``taichi_mpm.py``, its
CPU backend, the same threads) runs on the same particle counts in the benchmark's own
environment: this interpreter if it has taichi, else a venv made at ``--taichi-env`` on first use
(taichi is never a dependency of the package), in float64 and, in 3D, in float32 as well. Ends with
exactly ``throughput 2D: UMLS U M/s, taichi T M/s, ratio R``,
``throughput 3D: UMLS U M/s, taichi T M/s, ratio R`` (particle-steps per second, kernel rebuilt
every step, the largest size of each dimension, same run; float64) and
``throughput 3D float32: UMLS U M/s, taichi T M/s, ratio R`` (both in float32). The solver's per-particle loops
are the compiled ones of :mod:`datagen.mpm.native` where a C compiler is available
(``BSMS_NATIVE=0`` times the torch code).

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
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from taichi_mpm import DENSITY, NU, E, block

from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mpm import Model, State, advance, cfl_time_step, native, step
from datagen.mpm.kernels import Grid, MeshTables
from datagen.mpm.materials import NeoHookean

MATERIAL = NeoHookean(E, NU, DENSITY)  # the block taichi_mpm.py runs too


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


def time_steps(model: Model, state: State, steps: int, repeats: int = 3, python: bool = False) -> float:
    """Best mean seconds per step over ``repeats`` runs of ``steps`` steps (after a warm-up), each run
    one call of :func:`advance` (``python``: one Python :func:`step` per step)."""
    dt = cfl_time_step(model, state, 0.3)

    def run(state: State, n: int) -> State:
        if python:
            for _ in range(n):
                state = step(model, state, dt)
            return state
        return advance(model, state, dt, n)

    state = run(state, 3)
    best = math.inf
    for _ in range(repeats):
        if state.x.is_cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        state = run(state, steps)
        if state.x.is_cuda:
            torch.cuda.synchronize()
        best = min(best, (time.perf_counter() - start) / steps)
    return best


def measure(kind: str, dim: int, n: int, steps: int, device) -> dict:
    """kind: ``bspline``, ``umls`` (kernel rebuilt every step), ``umls python`` (the same, one Python
    step at a time), ``umls total`` or ``umls adaptive`` (A-ULMPM reference configurations: the
    kernel kept while the reference holds), ``umls float32`` (``umls`` with the float32 substeps)."""
    x, v, vol, spacing = block(n, dim)
    start = time.perf_counter()
    model = bspline_model(dim, spacing, device) if kind == "bspline" else umls_model(dim, spacing, device)
    if kind in ("umls total", "umls adaptive"):
        model = replace(model, reference=kind.split()[1])
    if kind == "umls float32":
        model = replace(model, precision="float32")
    setup = time.perf_counter() - start
    state = State.at_rest_shape(x, v, vol, MATERIAL.density, device=device)
    per_step = time_steps(model, state, steps, python=kind == "umls python")
    return {"kind": kind, "dim": dim, "particles": len(x), "nodes": model.n_nodes,
            "setup_s": setup, "ms_per_step": 1e3 * per_step, "particle_steps_per_s": len(x) / per_step}


def taichi_python(env: Path) -> Path:
    """An interpreter that has taichi: this one if it imports taichi, else the benchmark's own
    environment ``env`` (a venv made there and ``pip install taichi`` into it on first use)."""
    if importlib.util.find_spec("taichi") is not None:
        return Path(sys.executable)
    python = env / "bin" / "python"
    if not python.is_file():
        print(f"making the taichi environment {env} (python -m venv; pip install taichi numpy)", flush=True)
        subprocess.run([sys.executable, "-m", "venv", str(env)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "--quiet", "taichi", "numpy"], check=True)
    return python


def taichi_rate(python: Path, n: int, dim: int, steps: int, threads: int, precision: str = "float64") -> dict:
    """taichi_mpm.py's measurement (structured quadratic MLS-MPM on the same block) in ``python``."""
    out = subprocess.run([str(python), str(Path(__file__).with_name("taichi_mpm.py")), "--particles", str(n),
                          "--dim", str(dim), "--steps", str(steps), "--threads", str(threads),
                          "--precision", precision], capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"the taichi measurement failed in {python} (exit {out.returncode}):\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


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
    parser.add_argument("--taichi-env", type=Path, default=Path("runs/taichi-env"),
                        help="the benchmark's own environment for taichi (made on first use)")
    parser.add_argument("--no-taichi", action="store_true", help="skip the taichi comparison")
    parser.add_argument("--default-malloc", action="store_true", help="leave glibc malloc settings alone")
    args = parser.parse_args()
    if 3 not in args.dims:
        parser.error("--dims must include 3: the last line reports the 3D throughput")
    tuned = False if args.default_malloc else keep_freed_memory()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(f"torch threads: {torch.get_num_threads()}, device: {device}, malloc keeps freed memory: {tuned}, "
          f"compiled loops: {native.available()}")
    python = None if args.no_taichi or device.type != "cpu" else taichi_python(args.taichi_env)
    if python is None and not args.no_taichi:
        print(f"the taichi comparison runs on the CPU only: skipped on {device}")
    print(f"{'kernel':18s} {'dim':>3s} {'particles':>9s} {'nodes':>7s} {'ms/step':>8s} {'M p-steps/s':>11s} "
          f"{'vs bspline':>10s}")
    rows, taichi = [], []
    for dim in args.dims:
        for n in args.sizes:
            kinds = ("bspline", "umls", "umls python",
                     *(("umls total", "umls adaptive", "umls float32") if dim == 3 else ()))
            measured = {kind: measure(kind, dim, n, args.steps, device) for kind in kinds}
            for kind, row in measured.items():
                row["ratio_over_bspline"] = row["particle_steps_per_s"] / measured["bspline"]["particle_steps_per_s"]
                print(f"{kind:18s} {dim:3d} {row['particles']:9d} {row['nodes']:7d} {row['ms_per_step']:8.1f} "
                      f"{row['particle_steps_per_s'] / 1e6:11.3f} {row['ratio_over_bspline']:10.2f}", flush=True)
                rows.append(row)
            for precision in ("float64", "float32") if dim == 3 else ("float64",):
                if python is None:
                    break
                t = taichi_rate(python, n, dim, args.steps, args.threads, precision)
                taichi.append(t)
                ours = measured["umls" if precision == "float64" else "umls float32"]
                name = f"taichi {t['taichi']}" + (" f32" if precision == "float32" else "")
                print(f"{name:18s} {dim:3d} {t['particles']:9d} {'':7s} {t['ms_per_step']:8.1f} "
                      f"{t['particle_steps_per_s'] / 1e6:11.3f}   umls/taichi "
                      f"{ours['particle_steps_per_s'] / t['particle_steps_per_s']:.3f}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {"threads": args.threads, "device": str(device), "malloc_keeps_freed_memory": tuned, "rows": rows,
               "taichi": taichi}
    (args.out / "results.json").write_text(json.dumps(summary, indent=1))
    for dim in (2, 3):
        print(_summary(rows, taichi, dim))
    print(_summary(rows, taichi, 3, "float32"))


def _summary(rows: list[dict], taichi: list[dict], dim: int, precision: str = "float64") -> str:
    """``throughput {dim}D: UMLS U M/s, taichi T M/s, ratio R`` at the largest size of ``dim`` ("n/a"
    where taichi did not run or the dimension was not measured); with precision float32,
    ``throughput {dim}D float32: ...`` from the float32 substeps and taichi's float32 run."""
    kind, label = ("umls", f"{dim}D") if precision == "float64" else ("umls float32", f"{dim}D float32")
    umls = [r for r in rows if r["dim"] == dim and r["kind"] == kind]
    if not umls:
        return f"throughput {label}: UMLS n/a M/s, taichi n/a M/s, ratio n/a"
    row = max(umls, key=lambda r: r["particles"])
    ti = next((t for t in taichi if t["dim"] == dim and t["particles"] == row["particles"]
               and t.get("precision", "float64") == precision), None)
    rate = row["particle_steps_per_s"]
    ti_text = "n/a" if ti is None else f"{ti['particle_steps_per_s'] / 1e6:#.3g}"
    ratio = "n/a" if ti is None else f"{rate / ti['particle_steps_per_s']:.3f}"
    return f"throughput {label}: UMLS {rate / 1e6:#.3g} M/s, taichi {ti_text} M/s, ratio {ratio}"

if __name__ == "__main__":
    main()
