"""Gas scenes of CSMPM run by :func:`datagen.simulate`: ``shock_tube`` so far.

``shock_tube``: any 1D Riemann problem on a tube of ``cells`` cells over ``length``:
``left`` = [rho, u, p] for x < ``interface``, ``right`` for x > it, ideal gas ``gamma``,
``boundaries`` ``open`` (the tube's ends let waves out) or ``wall``. Solver: ``cfl`` on the
speed |u| + ``acoustic`` c (``acoustic`` 1: the explicit acoustic limit, the default for
validation against the exact solution; 0: the flow speed alone, which the semi-implicit pressure
allows, each step then capped by the frame interval). The Trajectory's ``fields`` hold ``x``
(N,) cell centres and ``density``, ``velocity``, ``pressure`` (frames + 1, N); its positions
are the cell centres (a fixed 1D mesh), its velocities the gas velocity; diagnostics per frame:
``mass``, ``momentum``, ``energy`` (per unit cross-section) and ``cg_iterations`` (the most of
any step reaching the frame).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..config import ConfigError, reject_unknown
from ..mesh import Mesh
from ..trajectory import NodeType, Trajectory
from . import euler, gas

__all__ = ["GAS_SCENES", "resolve", "simulate"]

GAS_SCENES = ("shock_tube",)
DEFAULTS = {"left": [1.0, 0.0, 1.0], "right": [0.125, 0.0, 0.1], "cells": 400, "length": 1.0, "interface": 0.5,
            "gamma": gas.GAMMA, "boundaries": "open"}
SOLVER = {"cfl": 0.5, "acoustic": 1.0, "max_substeps": 100_000}
OUTPUT = {"frames": 20, "frame_interval": 0.01}


def _number(value, key: str, *, low=None, integer=False) -> float:
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not math.isfinite(value) or (
            low is not None and not value > low):
        what = "an integer" if integer else "a number"
        raise ConfigError(f"config key '{key}' must be {what}" + ("" if low is None else f" > {low:g}") +
                          f", got {value!r}")
    return value


def _state(value, key: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ConfigError(f"config key '{key}' must be [density, velocity, pressure], got {value!r}")
    rho, u, p = (float(_number(v, f"{key}[{i}]")) for i, v in enumerate(value))
    if not (rho > 0 and p > 0):
        raise ConfigError(f"config key '{key}' needs positive density and pressure, got {value!r}")
    return [rho, u, p]


def _section(config: dict, name: str, defaults: dict) -> dict:
    given = config.get(name) or {}
    if not isinstance(given, dict):
        raise ConfigError(f"config key '{name}' must be a mapping, got {given!r}")
    reject_unknown(given, defaults, prefix=name, where=f"scene {config['scene']!r}")
    return {**defaults, **given}


def resolve(config: dict) -> dict:
    """The full config of a gas scene (defaults filled in, every value checked)."""
    reject_unknown(config, {"scene", "params", "solver", "output", "seed"})
    p, s, o = (_section(config, n, d) for n, d in (("params", DEFAULTS), ("solver", SOLVER), ("output", OUTPUT)))
    p["left"], p["right"] = _state(p["left"], "params.left"), _state(p["right"], "params.right")
    p["cells"] = _number(p["cells"], "params.cells", low=7, integer=True)
    p["length"] = float(_number(p["length"], "params.length", low=0))
    p["interface"] = float(_number(p["interface"], "params.interface"))
    if not 0 < p["interface"] < p["length"]:
        raise ConfigError(f"config key 'params.interface' must lie inside the tube (0, {p['length']:g}), "
                          f"got {p['interface']!r}")
    p["gamma"] = float(_number(p["gamma"], "params.gamma", low=1))
    if p["boundaries"] not in euler.BOUNDARIES:
        raise ConfigError(f"config key 'params.boundaries' must be one of {', '.join(euler.BOUNDARIES)}, "
                          f"got {p['boundaries']!r}")
    s["cfl"] = float(_number(s["cfl"], "solver.cfl", low=0))
    s["acoustic"] = float(_number(s["acoustic"], "solver.acoustic"))
    if s["acoustic"] < 0:
        raise ConfigError(f"config key 'solver.acoustic' must be >= 0, got {s['acoustic']!r}")
    s["max_substeps"] = _number(s["max_substeps"], "solver.max_substeps", low=0, integer=True)
    o["frames"] = _number(o["frames"], "output.frames", low=0, integer=True)
    o["frame_interval"] = float(_number(o["frame_interval"], "output.frame_interval", low=0))
    seed = config.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"config key 'seed' must be an integer, got {seed!r}")
    return {"scene": config["scene"], "params": p, "solver": s, "output": o, "seed": seed}


def simulate(config: dict) -> Trajectory:
    """Run a gas scene (a config dict whose ``scene`` is in :data:`GAS_SCENES`)."""
    config = resolve(config)
    p, s, o = config["params"], config["solver"], config["output"]
    n, length = p["cells"], p["length"]
    dx = length / n
    x = (np.arange(n) + 0.5) * dx
    grid = euler.Grid((n,), dx, ((p["boundaries"],) * 2,))
    left = x < p["interface"]
    primitive = [np.where(left, a, b) for a, b in zip(p["left"], p["right"], strict=True)]
    state = gas.conserved(primitive[0], primitive[1][None], primitive[2], p["gamma"])
    frames, wall, substeps, times = [state], [0.0], 0, [0.0]
    t, iterations = 0.0, [0]
    for k in range(1, o["frames"] + 1):
        end, start, most = k * o["frame_interval"], time.perf_counter(), 0
        steps = 0
        while t < end - 1e-12 * end:
            dt = min(euler.time_step(state, grid, s["cfl"], s["acoustic"], p["gamma"]), end - t)
            state, info = euler.step(state, grid, dt, p["gamma"])
            t, steps, most = (end if dt == end - t else t + dt), steps + 1, max(most, info.cg_iterations)
            if steps > s["max_substeps"]:
                raise ConfigError(f"frame {k} took more than solver.max_substeps ({s['max_substeps']:,}) steps; "
                                  "raise it, or coarsen the tube (params.cells)")
            if not np.all(np.isfinite(state)) or np.any(state[0] <= 0) or np.any(gas.pressure(state, p["gamma"]) <= 0):
                raise RuntimeError(f"shock_tube: the gas state became non-physical (density or pressure <= 0) "
                                   f"at t = {t:.6g} s, step {substeps + steps}; lower solver.cfl")
        wall.append(time.perf_counter() - start)
        substeps += steps
        iterations.append(most)
        frames.append(state)
        times.append(t)
    stacked = np.stack(frames)  # (T, 3, N)
    rho, velocity, pressure = stacked[:, 0], stacked[:, 1] / stacked[:, 0], gas.pressure(
        np.moveaxis(stacked, 1, 0), p["gamma"])
    mesh = Mesh(x[:, None], np.stack([np.arange(n - 1), np.arange(1, n)], 1))
    diagnostics = {"mass": stacked[:, 0].sum(1) * dx, "momentum": stacked[:, 1].sum(1) * dx,
                   "energy": stacked[:, 2].sum(1) * dx, "cg_iterations": np.array(iterations)}
    return Trajectory(
        mesh=mesh, positions=np.broadcast_to(x[None, :, None], (len(frames), n, 1)).copy(),
        velocities=velocity[:, :, None].copy(), times=np.array(times), diagnostics=diagnostics,
        wall_time=float(sum(wall)), config=config, dt=t / max(substeps, 1), substeps=substeps, n_particles=0,
        frame_wall_times=np.array(wall), node_type=np.full(n, NodeType.FREE, np.int64),
        fields={"x": x, "density": rho, "velocity": velocity, "pressure": pressure},
    )
