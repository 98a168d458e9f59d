"""Gas and MPM solids in one solve (:mod:`datagen.csmpm.coupled`), run by :func:`datagen.simulate`.

``lifting_cylinder`` (Arienti et al. 2003; the thesis' Fig. 3.7): a channel of ``size`` =
[length, height] with ``cells`` cells per unit length, walls at the bottom and top, an inlet on
the left and an outlet on the right. A shock of Mach ``mach`` moving right through still gas
``ahead`` = [rho, p] starts at x = ``shock_at``; behind it the gas holds the Rankine–Hugoniot
state, which the inlet keeps feeding. A cylinder of ``radius`` lies at ``centre`` (on the floor
by default), a solid of the package's MPM materials (``material``: ``neo_hookean``,
``linear`` or ``fixed_corotated``; ``E``, ``nu``, ``density``) meshed at ``mesh_size``
(default: half a cell), one particle per mesh node. Swept over by the shock, it is lifted off
the floor and carried towards the top wall.

The Trajectory's mesh is the cylinder's and its positions and velocities the cylinder's nodes;
its ``fields`` hold the gas on every cell: ``x`` (N, 2) cell centres (row-major over x then y),
``density``, ``pressure`` (frames + 1, N) and ``velocity`` (frames + 1, N, 2) (inside the solid:
the gas it encloses), and ``solid`` (frames + 1, N) the cells the solve took as solid; its
diagnostics per frame: gas ``mass``, the solid's ``momentum`` and ``centre``, and ``cg_iterations``
(the most of any step reaching the frame).
"""

from __future__ import annotations

import math
import time

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mpm.materials import MATERIALS
from ..trajectory import NodeType, Trajectory
from . import coupled, euler, gas

__all__ = ["COUPLED_DEFAULTS", "COUPLED_OUTPUT", "check", "simulate", "shock_state"]

COUPLED_DEFAULTS = {
    "lifting_cylinder": {"size": [1.0, 0.2], "cells": 100, "mach": 3.0, "ahead": [1.4, 1.0], "shock_at": 0.08,
                         "radius": 0.05, "centre": [0.15, 0.05], "material": "neo_hookean", "E": 2.0e4, "nu": 0.3,
                         "density": 10.77, "mesh_size": None, "gamma": gas.GAMMA},
}
COUPLED_OUTPUT = {"lifting_cylinder": {"frames": 10, "frame_interval": 0.03}}
ELASTIC = ("neo_hookean", "linear", "fixed_corotated")


def shock_state(mach: float, rho: float, p: float, gamma: float = gas.GAMMA) -> tuple[float, float, float]:
    """[rho, u, p] behind a shock of Mach ``mach`` moving into still gas (rho, p): the
    Rankine–Hugoniot jump conditions."""
    c = math.sqrt(gamma * p / rho)
    m2 = mach * mach
    return (rho * (gamma + 1.0) * m2 / ((gamma - 1.0) * m2 + 2.0), 2.0 * c * (m2 - 1.0) / ((gamma + 1.0) * mach),
            p * (1.0 + 2.0 * gamma / (gamma + 1.0) * (m2 - 1.0)))


def _pair(value, key: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in value):
        raise ConfigError(f"config key 'params.{key}' must be two positive numbers, got {value!r}")
    return [float(v) for v in value]


def check(name: str, p: dict, number) -> dict:
    """Scene ``name``'s params checked (``number``: the scenes' number check)."""
    p["cells"] = number(p["cells"], "params.cells", low=1, integer=True)
    p["gamma"] = float(number(p["gamma"], "params.gamma", low=1))
    for key in ("size", "ahead", "centre"):
        p[key] = _pair(p[key], key)
    for key in ("mach", "radius", "E", "density"):
        p[key] = float(number(p[key], f"params.{key}", low=0))
    if p["mach"] <= 1:
        raise ConfigError(f"config key 'params.mach' must be > 1 (a shock), got {p['mach']!r}")
    p["nu"] = float(number(p["nu"], "params.nu"))
    if not -1 < p["nu"] < 0.5:
        raise ConfigError(f"config key 'params.nu' must lie in (-1, 0.5), got {p['nu']!r}")
    if p["material"] not in ELASTIC:
        raise ConfigError(f"config key 'params.material' must be one of {', '.join(ELASTIC)}, got {p['material']!r}")
    (length, height), (cx, cy), r = p["size"], p["centre"], p["radius"]
    p["shock_at"] = float(number(p["shock_at"], "params.shock_at", low=0))
    if not (r <= cx - p["shock_at"] and cx + r < length and r <= cy and cy + r < height):
        raise ConfigError(f"config keys 'params.centre' {p['centre']} and 'params.radius' {r:g} must put the "
                          f"cylinder inside the channel {p['size']}, ahead of the shock at x = {p['shock_at']:g}")
    dx = 1.0 / p["cells"]
    if r < 2 * dx:
        raise ConfigError(f"config key 'params.cells' ({p['cells']} per unit length) leaves the cylinder (radius "
                          f"{r:g}) under 2 cells across its radius; raise it")
    p["mesh_size"] = 0.5 * dx if p["mesh_size"] is None else float(number(p["mesh_size"], "params.mesh_size", low=0))
    return p


def _setup(p: dict):
    (length, height), n = p["size"], p["cells"]
    dx = 1.0 / n
    nx, ny = round(length * n), round(height * n)
    rho1, p1 = p["ahead"]
    behind = shock_state(p["mach"], rho1, p1, p["gamma"])
    inflow = gas.conserved(np.array(behind[0]), np.array([behind[1], 0.0]), np.array(behind[2]), p["gamma"])
    grid = euler.Grid((nx, ny), dx, (("inlet", "open"), ("wall", "wall")), inflow=inflow)
    x, y = np.meshgrid((np.arange(nx) + 0.5) * dx, (np.arange(ny) + 0.5) * dx, indexing="ij")
    shocked = x < p["shock_at"]
    state = gas.conserved(np.where(shocked, behind[0], rho1), np.stack([np.where(shocked, behind[1], 0.0),
                                                                        np.zeros_like(x)]),
                          np.where(shocked, behind[2], p1), p["gamma"])
    # a cylinder resting on the floor is meshed a hair above it, so no particle sits on the wall's nodes
    cx, cy = p["centre"]
    mesh = shapes.disk(p["radius"], p["mesh_size"], center=(cx, max(cy, p["radius"] + 1e-3 * dx)))
    material = MATERIALS[p["material"]](E=p["E"], nu=p["nu"], density=p["density"])
    solid = coupled.Solid.from_mesh(mesh, material, p0=p1)
    return grid, state, solid, mesh, np.stack([x.ravel(), y.ravel()], 1)


def simulate(config: dict) -> Trajectory:
    """Run a resolved coupled scene (:func:`datagen.csmpm.scenes.resolve`)."""
    p, s, o = config["params"], config["solver"], config["output"]
    grid, state, solid, mesh, centres = _setup(p)
    frames, solids, cells, wall, times, iterations = [state], [solid], [np.zeros(len(centres), bool)], [0.0], [0.0], [0]
    t, substeps = 0.0, 0
    for k in range(1, o["frames"] + 1):
        end, start, most, steps = k * o["frame_interval"], time.perf_counter(), 0, 0
        while t < end - 1e-12 * end:
            dt = min(coupled.time_step(state, solid, grid, s["cfl"]), end - t)
            state, solid, info = coupled.step(state, solid, grid, dt, gamma=p["gamma"])
            t, steps, most = (end if dt == end - t else t + dt), steps + 1, max(most, info.cg_iterations)
            if steps > s["max_substeps"]:
                raise ConfigError(f"frame {k} took more than solver.max_substeps ({s['max_substeps']:,}) steps; "
                                  "raise it, or coarsen the grid (params.cells)")
            if not (np.all(np.isfinite(state)) and np.all(state[0] > 0) and np.all(gas.pressure(state, p["gamma"]) > 0)
                    and np.all(np.isfinite(solid.x))):
                raise RuntimeError(f"{config['scene']}: the state became non-physical at t = {t:.6g} s, step "
                                   f"{substeps + steps}; lower solver.cfl or refine params.cells")
        wall.append(time.perf_counter() - start)
        substeps += steps
        iterations.append(most)
        frames.append(state)
        solids.append(solid)
        cells.append(info.solid_cells.ravel())
        times.append(t)
    stacked = np.stack(frames).reshape(len(frames), 4, -1)
    rho = stacked[:, 0]
    velocity = np.moveaxis(stacked[:, 1:-1] / rho[:, None], 1, -1)
    positions = np.stack([b.x for b in solids])
    node_type = np.full(mesh.n_nodes, NodeType.FREE, np.int64)
    return Trajectory(
        mesh=mesh, positions=positions, velocities=np.stack([b.v for b in solids]), times=np.array(times),
        diagnostics={"mass": rho.sum(1) * grid.dx ** 2, "momentum": np.stack([b.momentum for b in solids]),
                     "centre": positions.mean(1), "cg_iterations": np.array(iterations)},
        wall_time=float(sum(wall)), config=config, dt=t / max(substeps, 1), substeps=substeps,
        n_particles=len(solid.x), frame_wall_times=np.array(wall), node_type=node_type,
        fields={"x": centres, "density": rho, "velocity": velocity,
                "pressure": gas.pressure(np.moveaxis(stacked, 1, 0), p["gamma"]), "solid": np.stack(cells)},
    )
