"""The taichi side of ``mpm_throughput.py``: a structured quadratic MLS-MPM (APIC, Neo-Hookean,
float64) in taichi on the benchmark's spinning block, timed on taichi's CPU backend.

It needs only numpy and taichi, so that it runs in the benchmark's own environment (taichi is
never a dependency of the package): ``mpm_throughput.py`` starts it as

    PYTHON benchmarks/taichi_mpm.py --particles 20000 --dim 3 --steps 10 --threads 2

with PYTHON an interpreter that has taichi, and reads the one JSON line it prints last.
"""

import argparse
import json
import time

import numpy as np

# the block's material (mpm_throughput.MATERIAL): E 1e4 Pa, nu 0.3, density 1
E, NU, DENSITY = 1e4, 0.3, 1.0
MU, LAM = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
WAVE_SPEED = float(np.sqrt((LAM + 2 * MU) / DENSITY))


def block(n_particles: int, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Cell-centred particles filling [0.2, 0.8]^dim of a unit box, spinning about the centre and
    drifting along x so that they cross cells: positions, velocities, volumes, mean spacing."""
    lower, upper = np.full(dim, 0.2), np.full(dim, 0.8)
    counts = np.maximum(np.round((upper - lower) / (0.6 / n_particles ** (1.0 / dim))).astype(int), 1)
    step = (upper - lower) / counts
    axes = [lower[k] + (np.arange(c) + 0.5) * step[k] for k, c in enumerate(counts)]
    x = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    centred = x - 0.5
    v = np.zeros_like(x)
    v[:, 0], v[:, 1] = -2.0 * centred[:, 1] + 0.3, 2.0 * centred[:, 0]
    return x, v, np.full(len(x), float(np.prod(step))), float(step.mean())


def _program(ti, x0: np.ndarray, v0: np.ndarray, volume: float, h: float):
    """Fields and one substep of structured quadratic MLS-MPM (APIC, Neo-Hookean) in taichi."""
    p, dim = x0.shape
    res = int(round(1.0 / h)) + 1
    mass = DENSITY * volume
    x, v = ti.Vector.field(dim, float, p), ti.Vector.field(dim, float, p)
    C, F = ti.Matrix.field(dim, dim, float, p), ti.Matrix.field(dim, dim, float, p)
    grid_v, grid_m = ti.Vector.field(dim, float, (res,) * dim), ti.field(float, (res,) * dim)
    real = np.float64 if ti.lang.impl.get_runtime().default_fp == ti.f64 else np.float32
    x.from_numpy(x0.astype(real))
    v.from_numpy(v0.astype(real))
    F.from_numpy(np.tile(np.eye(dim, dtype=real), (p, 1, 1)))

    @ti.kernel
    def substep(dt: float):  # taichi reads this annotation: no "from __future__ import annotations" here
        for I in ti.grouped(grid_m):
            grid_v[I], grid_m[I] = ti.Vector.zero(float, dim), 0.0
        for q in x:  # P2G
            base = (x[q] / h - 0.5).cast(int)
            fx = x[q] / h - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            eye = ti.Matrix.identity(float, dim)
            tau = MU * (F[q] @ F[q].transpose() - eye) + LAM * ti.log(F[q].determinant()) * eye
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


def rate(n: int, dim: int, steps: int, threads: int, precision: str = "float64") -> dict:
    """Particle-steps per second of the taichi MLS-MPM on ``threads`` CPU threads in ``precision``
    (``float64`` or ``float32``: taichi's default float type; compiled first; the best of three timed
    runs of ``steps`` substeps)."""
    import taichi as ti

    ti.init(arch=ti.cpu, default_fp=ti.f64 if precision == "float64" else ti.f32, cpu_max_num_threads=threads,
            log_level=ti.WARN)
    x0, v0, vol, spacing = block(n, dim)
    h = 2.0 * spacing
    substep = _program(ti, x0, v0, float(vol[0]), h)
    dt = 0.3 * h / (WAVE_SPEED + 2.0)
    substep(dt)  # compile
    ti.sync()
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(steps):
            substep(dt)
        ti.sync()
        best = min(best, (time.perf_counter() - start) / steps)
    return {"particles": len(x0), "dim": dim, "threads": threads, "taichi": ".".join(str(k) for k in ti.__version__),
            "precision": precision, "ms_per_step": 1e3 * best, "particle_steps_per_s": len(x0) / best}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, required=True)
    parser.add_argument("--dim", type=int, choices=(2, 3), required=True)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--precision", choices=("float64", "float32"), default="float64")
    args = parser.parse_args()
    print(json.dumps(rate(args.particles, args.dim, args.steps, args.threads, args.precision)))


if __name__ == "__main__":
    main()
