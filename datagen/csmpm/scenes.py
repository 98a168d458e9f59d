"""Gas scenes of CSMPM run by :func:`datagen.simulate`: ``shock_tube``, ``circular_shock`` and
``stair_flow``.

``shock_tube``: any 1D Riemann problem on a tube of ``cells`` cells over ``length``:
``left`` = [rho, u, p] for x < ``interface``, ``right`` for x > it, ideal gas ``gamma``,
``boundaries`` ``open`` (the tube's ends let waves out) or ``wall``. Solver: ``cfl`` on the
speed |u| + ``acoustic`` c (``acoustic`` 1: the explicit acoustic limit, the default for
validation against the exact solution; 0: the flow speed alone, which the semi-implicit pressure
allows, each step then capped by the frame interval). The Trajectory's ``fields`` hold ``x``
(N,) cell centres and ``density``, ``velocity``, ``pressure`` (frames + 1, N); its positions
are the cell centres (a fixed 1D mesh), its velocities the gas velocity; diagnostics per frame:
``mass``, ``momentum``, ``energy`` (per unit cross-section) and ``cg_iterations`` (the most of
any step reaching the frame). ``solver.scheme``: the pressure projection's velocity/pressure
order, ``B1B0`` (:mod:`~datagen.csmpm.euler`, the default) or ``B2B1``
(:mod:`~datagen.csmpm.b2b1`: closed boxes only, so ``circular_shock`` and a walled tube).

``circular_shock`` (Kwatra et al. 2009's central circular shock): a square box of side
``length`` with ``cells`` cells per side and walls all round; gas ``inside`` = [rho, p] within
``radius`` of the centre, ``outside`` elsewhere, at rest. Its fields: ``x`` (N, 2) cell centres
(row-major over x then y), ``density`` and ``pressure`` (frames + 1, N), ``velocity`` (frames + 1,
N, 2); its mesh triangulates the cell centres (two triangles per square of four).

``stair_flow`` (Woodward and Colella's forward-facing step, the thesis' Fig. 3.6): a channel
of ``size`` = [length, height] with ``cells`` cells per unit length, walls at the bottom and
top, an inlet on the left holding ``inflow`` = [rho, u, p] (default Mach 3) and an outlet on the
right; a solid step of ``step`` = [start, height] on the floor; the channel starts filled with
the inflow. Fields as ``circular_shock``'s over the gas cells only (the step's cells are left
out: ``x`` (N, 2) their centres), and the mesh triangulates them.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import ConfigError, reject_unknown, section
from ..mesh import Mesh
from ..trajectory import NodeType, Trajectory
from . import b2b1, euler, gas
from .coupled_scenes import COUPLED_DEFAULTS, COUPLED_OUTPUT, check
from .coupled_scenes import simulate as simulate_coupled
from .flow import FLOW_DEFAULTS, FLOW_OUTPUT, cell_mesh
from .flow import check as check_flow
from .flow import simulate as simulate_flow
from .frames import gas_frames

__all__ = ["GAS_SCENES", "resolve", "simulate"]

GAS_SCENES = ("shock_tube", "circular_shock", "stair_flow", *FLOW_DEFAULTS, *COUPLED_DEFAULTS)
"""The scenes CSMPM runs: gas alone (``shock_channel``: :mod:`datagen.csmpm.flow`), and gas with
MPM solids (:mod:`datagen.csmpm.coupled_scenes`)."""
DEFAULTS = {
    "shock_tube": {"left": [1.0, 0.0, 1.0], "right": [0.125, 0.0, 0.1], "cells": 400, "length": 1.0,
                   "interface": 0.5, "gamma": gas.GAMMA, "boundaries": "open"},
    "circular_shock": {"inside": [1.0, 1.0], "outside": [0.125, 0.1], "radius": 0.4, "cells": 128, "length": 2.0,
                       "gamma": gas.GAMMA},
    "stair_flow": {"inflow": [1.4, 3.0, 1.0], "size": [3.0, 1.0], "step": [0.6, 0.2], "cells": 40, "gamma": gas.GAMMA},
    **FLOW_DEFAULTS, **COUPLED_DEFAULTS,
}
SOLVER = {"cfl": 0.5, "acoustic": 1.0, "max_substeps": 100_000, "threads": 0, "scheme": "B1B0"}
# threads: accepted like the MPM scenes' solver.threads (evaluations set it for every solver run);
# the gas solver is numpy and scipy on one thread whatever it says
OUTPUT = {"shock_tube": {"frames": 20, "frame_interval": 0.01},
          "circular_shock": {"frames": 10, "frame_interval": 0.025},
          "stair_flow": {"frames": 20, "frame_interval": 0.2}, **FLOW_OUTPUT, **COUPLED_OUTPUT}


def _number(value, key: str, *, low=None, integer=False) -> float:
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not math.isfinite(value) or (
            low is not None and not value > low):
        what = "an integer" if integer else "a number"
        raise ConfigError(f"config key '{key}' must be {what}" + ("" if low is None else f" > {low:g}") +
                          f", got {value!r}")
    return value


def _state(value, key: str, with_velocity: bool = True) -> list[float]:
    names = "[density, velocity, pressure]" if with_velocity else "[density, pressure]"
    if not isinstance(value, (list, tuple)) or len(value) != (3 if with_velocity else 2):
        raise ConfigError(f"config key '{key}' must be {names}, got {value!r}")
    values = [float(_number(v, f"{key}[{i}]")) for i, v in enumerate(value)]
    if not (values[0] > 0 and values[-1] > 0):
        raise ConfigError(f"config key '{key}' needs positive density and pressure, got {value!r}")
    return values


def _params(name: str, p: dict) -> dict:
    """Scene ``name``'s params checked (types, ranges)."""
    if name in COUPLED_DEFAULTS:
        return check(name, p, _number)
    if name in FLOW_DEFAULTS:
        return check_flow(name, p, _number, _state)
    p["cells"] = _number(p["cells"], "params.cells", low=7 if name != "stair_flow" else 1, integer=True)
    p["gamma"] = float(_number(p["gamma"], "params.gamma", low=1))
    if name == "stair_flow":
        p["inflow"] = _state(p["inflow"], "params.inflow")
        for key in ("size", "step"):
            if not isinstance(p[key], (list, tuple)) or len(p[key]) != 2:
                raise ConfigError(f"config key 'params.{key}' must be two numbers, got {p[key]!r}")
            p[key] = [float(_number(v, f"params.{key}[{i}]", low=0)) for i, v in enumerate(p[key])]
        (length, height), (start, rise) = p["size"], p["step"]
        if not (start < length and rise < height):
            raise ConfigError(f"config key 'params.step' [start, height] must lie inside the channel {p['size']}, "
                              f"got {p['step']}")
        if min(round(v * p["cells"]) for v in (length, height)) < 4:
            raise ConfigError(f"config key 'params.cells' ({p['cells']} per unit length) gives fewer than 4 cells "
                              f"across the channel {p['size']}; raise it")
        return p
    p["length"] = float(_number(p["length"], "params.length", low=0))
    if name == "circular_shock":
        p["inside"], p["outside"] = (_state(p[k], f"params.{k}", False) for k in ("inside", "outside"))
        p["radius"] = float(_number(p["radius"], "params.radius", low=0))
        if not p["radius"] < p["length"] / 2:
            raise ConfigError(f"config key 'params.radius' must be less than half the box (params.length / 2 = "
                              f"{p['length'] / 2:g}), got {p['radius']!r}")
        return p
    p["left"], p["right"] = _state(p["left"], "params.left"), _state(p["right"], "params.right")
    p["interface"] = float(_number(p["interface"], "params.interface"))
    if not 0 < p["interface"] < p["length"]:
        raise ConfigError(f"config key 'params.interface' must lie inside the tube (0, {p['length']:g}), "
                          f"got {p['interface']!r}")
    if p["boundaries"] not in euler.BOUNDARIES:
        raise ConfigError(f"config key 'params.boundaries' must be one of {', '.join(euler.BOUNDARIES)}, "
                          f"got {p['boundaries']!r}")
    return p


def _scheme(name: str, p: dict, scheme) -> None:
    """ConfigError unless ``scheme`` is one of :data:`datagen.csmpm.b2b1.SCHEMES` that ``name`` runs
    (B2B1: the gas alone in a closed box)."""
    if scheme not in b2b1.SCHEMES:
        raise ConfigError(f"config key 'solver.scheme' must be one of {', '.join(b2b1.SCHEMES)}, got {scheme!r}")
    closed = name == "circular_shock" or (name == "shock_tube" and p["boundaries"] == "wall")
    if scheme == "B2B1" and not closed:
        raise ConfigError(f"config key 'solver.scheme' B2B1 takes the gas alone in a closed box (circular_shock, or "
                          f"shock_tube with params.boundaries wall), not scene {name!r} as configured; use B1B0")


def resolve(config: dict) -> dict:
    """The full config of a gas scene (defaults filled in, every value checked)."""
    reject_unknown(config, {"scene", "params", "solver", "output", "seed", "field_spec"})  # the spec: written, not read
    name = config["scene"]
    if isinstance(config.get("output"), dict) and "step_diagnostics" in config["output"]:  # the MPM scenes' key:
        config = {**config, "output": {k: v for k, v in config["output"].items() if k != "step_diagnostics"}}  # no use
    p, s, o = (section(config, n, d, f"scene {name!r}") for n, d in (("params", DEFAULTS[name]),
                                                                     ("solver", SOLVER), ("output", OUTPUT[name])))
    p = _params(name, p)
    s["cfl"] = float(_number(s["cfl"], "solver.cfl", low=0))
    s["acoustic"] = float(_number(s["acoustic"], "solver.acoustic"))
    if s["acoustic"] < 0:
        raise ConfigError(f"config key 'solver.acoustic' must be >= 0, got {s['acoustic']!r}")
    s["max_substeps"] = _number(s["max_substeps"], "solver.max_substeps", low=0, integer=True)
    if isinstance(s["threads"], bool) or not isinstance(s["threads"], int) or s["threads"] < 0:
        raise ConfigError(f"config key 'solver.threads' must be an integer >= 0, got {s['threads']!r}")
    _scheme(name, p, s["scheme"])
    o["frames"] = _number(o["frames"], "output.frames", low=0, integer=True)
    o["frame_interval"] = float(_number(o["frame_interval"], "output.frame_interval", low=0))
    seed = config.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"config key 'seed' must be an integer, got {seed!r}")
    return {"scene": name, "params": p, "solver": s, "output": o, "seed": seed}


def _initial(name: str, p: dict):
    """(grid, conserved state, the mesh of the centres of the cells the fields hold, their flat
    indices or None for every cell) of a scene's start."""
    if name == "stair_flow":
        return _stair(p)
    n, length = p["cells"], p["length"]
    dx = length / n
    centres = (np.arange(n) + 0.5) * dx
    if name == "shock_tube":
        grid = euler.Grid((n,), dx, ((p["boundaries"],) * 2,))
        left = centres < p["interface"]
        rho, u, pres = (np.where(left, a, b) for a, b in zip(p["left"], p["right"], strict=True))
        mesh = Mesh(centres[:, None], np.stack([np.arange(n - 1), np.arange(1, n)], 1))
        return grid, gas.conserved(rho, u[None], pres, p["gamma"]), mesh, None
    grid = euler.Grid((n, n), dx, (("wall", "wall"), ("wall", "wall")))
    x, y = np.meshgrid(centres, centres, indexing="ij")
    inside = (x - length / 2) ** 2 + (y - length / 2) ** 2 < p["radius"] ** 2
    rho, pres = (np.where(inside, a, b) for a, b in zip(p["inside"], p["outside"], strict=True))
    mesh, _ = cell_mesh(x, y, np.ones((n, n), bool))
    return grid, gas.conserved(rho, np.zeros((2, n, n)), pres, p["gamma"]), mesh, None


def _stair(p: dict):
    (length, height), (start, rise), n = p["size"], p["step"], p["cells"]
    dx = 1.0 / n
    nx, ny = round(length * n), round(height * n)
    x, y = np.meshgrid((np.arange(nx) + 0.5) * dx, (np.arange(ny) + 0.5) * dx, indexing="ij")
    solid = (x > start) & (y < rise)
    rho, u, pres = p["inflow"]
    inflow = gas.conserved(np.array(rho), np.array([u, 0.0]), np.array(pres), p["gamma"])
    grid = euler.Grid((nx, ny), dx, (("inlet", "open"), ("wall", "wall")), inflow=inflow, solid=solid)
    state = np.broadcast_to(inflow[:, None, None], (4, nx, ny)).copy()
    mesh, kept = cell_mesh(x, y, ~solid)
    return grid, state, mesh, kept


def simulate(config: dict) -> Trajectory:
    """Run a gas scene (a config dict whose ``scene`` is in :data:`GAS_SCENES`)."""
    config = resolve(config)
    if config["scene"] in COUPLED_DEFAULTS:
        return simulate_coupled(config)
    if config["scene"] in FLOW_DEFAULTS:
        return simulate_flow(config)
    p, s, o = config["params"], config["solver"], config["output"]
    grid, state, mesh, kept = _initial(config["scene"], p)
    x = mesh.nodes
    states, times, wall, iterations, substeps = gas_frames(config["scene"], grid, state, p["gamma"], s, o)
    stacked = np.stack(states).reshape(len(states), grid.dim + 2, -1)  # (T, d + 2, N)
    if kept is not None:
        stacked = stacked[:, :, kept]
    volume = grid.dx ** grid.dim
    rho = stacked[:, 0]
    velocity = np.moveaxis(stacked[:, 1:-1] / rho[:, None], 1, -1)  # (T, N, d)
    pressure = gas.pressure(np.moveaxis(stacked, 1, 0), p["gamma"])
    diagnostics = {"mass": rho.sum(1) * volume, "momentum": stacked[:, 1:-1].sum(-1) * volume,
                   "energy": stacked[:, -1].sum(1) * volume, "cg_iterations": np.array(iterations)}
    n = len(x)
    return Trajectory(
        mesh=mesh, positions=np.broadcast_to(x[None], (len(states), n, grid.dim)).copy(),
        velocities=velocity.copy(), times=np.array(times), diagnostics=diagnostics,
        wall_time=float(sum(wall)), config=config, dt=times[-1] / max(substeps, 1), substeps=substeps, n_particles=0,
        frame_wall_times=np.array(wall), node_type=np.full(n, NodeType.FREE, np.int64),
        fields={"x": x[:, 0].copy() if grid.dim == 1 else x.copy(), "density": rho,
                "velocity": velocity[..., 0] if grid.dim == 1 else velocity, "pressure": pressure},
    )
