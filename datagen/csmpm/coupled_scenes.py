"""Gas and MPM solids in one solve (:mod:`datagen.csmpm.coupled`), run by :func:`datagen.simulate`.

Every scene's solid is a body of the package's MPM materials (``material``: ``neo_hookean``,
``linear`` or ``fixed_corotated``; ``E``, ``nu``, ``density``) meshed at ``mesh_size`` (default:
half a cell), one particle per mesh node; ``cells`` is the number of grid cells per unit length.

``lifting_cylinder`` (Arienti et al. 2003; the thesis' Fig. 3.7): a channel of ``size`` =
[length, height], walls at the bottom and top, an inlet on the left and an outlet on the right.
A shock of Mach ``mach`` moving right through still gas ``ahead`` = [rho, p] starts at x =
``shock_at``; behind it the gas holds the Rankine–Hugoniot state, which the inlet keeps feeding.
A cylinder of ``radius`` lies at ``centre`` (on the floor by default). Swept over by the shock,
it is carried downstream and lifted off the floor.

``shell_explosion`` (the thesis' Fig. 3.10, scaled to this machine): a square box of side
``length`` with walls all round; an elastic ring (``radius`` = [inner, outer]) at its centre holds
gas ``inside`` = [rho, p] in still gas ``outside``; the ring is blown outwards.

``bullet`` (the thesis' Fig. 3.12, scaled): a box of ``size`` with walls except the outlet on the
right; a barrel of static solid cells (walls ``wall`` thick above and below a bore of
``bore``, open to the right, ``barrel`` long) holds a bullet (``bullet`` = [length, height],
a rectangle with a rounded nose, its back at ``breech``) with gas ``chamber`` = [rho, p] behind
it and still gas ``outside`` everywhere else; the bullet is fired out of the barrel.

The Trajectory's mesh is the body's, its positions and velocities the body's nodes; its
``fields`` hold the gas on every cell: ``x`` (N, 2) cell centres (row-major over x then y),
``density``, ``pressure`` (frames + 1, N) and ``velocity`` (frames + 1, N, 2) (inside the solid:
the gas it encloses), and ``solid`` (frames + 1, N) the cells the solve took as solid (the body's
and the static ones); its
diagnostics per frame: gas ``mass``, the solid's ``momentum`` and ``centre``, ``cg_iterations``
(the most of any step reaching the frame) and ``floored`` (gas cell-steps whose pressure was
floored: :func:`datagen.csmpm.coupled.step`).
"""

from __future__ import annotations

import math

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mpm.materials import MATERIALS
from ..trajectory import NodeType, Trajectory
from . import coupled, euler, gas
from .frames import frames
from .gas import shock_state

__all__ = ["COUPLED_DEFAULTS", "COUPLED_OUTPUT", "check", "simulate", "shock_state"]

_BODY = {"material": "neo_hookean", "mesh_size": None, "gamma": gas.GAMMA}
COUPLED_DEFAULTS = {
    "lifting_cylinder": {"size": [1.0, 0.2], "cells": 100, "mach": 3.0, "ahead": [1.4, 1.0], "shock_at": 0.08,
                         "radius": 0.05, "centre": [0.15, 0.05], "E": 2.0e4, "nu": 0.3, "density": 10.77, **_BODY},
    "shell_explosion": {"length": 1.0, "cells": 128, "radius": [0.12, 0.16], "inside": [1.0, 10.0],
                        "outside": [1.0, 1.0], "E": 100.0, "nu": 0.3, "density": 1.0, **_BODY},
    "bullet": {"size": [3.0, 1.0], "cells": 100, "bore": 0.16, "wall": 0.06, "barrel": 1.0, "bullet": [0.2, 0.14],
               "breech": 0.3, "chamber": [5.0, 50.0], "outside": [1.0, 1.0], "E": 1.0e4, "nu": 0.25,
               "density": 10.0, **_BODY},
}
COUPLED_OUTPUT = {"lifting_cylinder": {"frames": 10, "frame_interval": 0.03},
                  "shell_explosion": {"frames": 10, "frame_interval": 0.02},
                  "bullet": {"frames": 10, "frame_interval": 0.06}}
ELASTIC = ("neo_hookean", "linear", "fixed_corotated")


def _pair(value, key: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in value):
        raise ConfigError(f"config key 'params.{key}' must be two positive numbers, got {value!r}")
    return [float(v) for v in value]


def _inside(ok: bool, what: str) -> None:
    if not ok:
        raise ConfigError(what)


def check(name: str, p: dict, number) -> dict:
    """Scene ``name``'s params checked (``number``: the scenes' number check)."""
    p["cells"] = number(p["cells"], "params.cells", low=1, integer=True)
    p["gamma"] = float(number(p["gamma"], "params.gamma", low=1))
    for key in ("E", "density"):
        p[key] = float(number(p[key], f"params.{key}", low=0))
    p["nu"] = float(number(p["nu"], "params.nu"))
    if not -1 < p["nu"] < 0.5:
        raise ConfigError(f"config key 'params.nu' must lie in (-1, 0.5), got {p['nu']!r}")
    if p["material"] not in ELASTIC:
        raise ConfigError(f"config key 'params.material' must be one of {', '.join(ELASTIC)}, got {p['material']!r}")
    dx = 1.0 / p["cells"]
    pairs = {"lifting_cylinder": ("size", "ahead", "centre"), "shell_explosion": ("radius", "inside", "outside"),
             "bullet": ("size", "bullet", "chamber", "outside")}[name]
    for key in pairs:
        p[key] = _pair(p[key], key)
    if name == "lifting_cylinder":
        p["mach"], p["radius"] = (float(number(p[k], f"params.{k}", low=0)) for k in ("mach", "radius"))
        if p["mach"] <= 1:
            raise ConfigError(f"config key 'params.mach' must be > 1 (a shock), got {p['mach']!r}")
        (length, height), (cx, cy), r = p["size"], p["centre"], p["radius"]
        p["shock_at"] = float(number(p["shock_at"], "params.shock_at", low=0))
        _inside(r <= cx - p["shock_at"] and cx + r < length and r <= cy and cy + r < height,
                f"config keys 'params.centre' {p['centre']} and 'params.radius' {r:g} must put the cylinder inside "
                f"the channel {p['size']}, ahead of the shock at x = {p['shock_at']:g}")
        thinnest = r
    elif name == "shell_explosion":
        p["length"] = float(number(p["length"], "params.length", low=0))
        inner, outer = p["radius"]
        _inside(inner < outer < 0.5 * p["length"] - 2 * dx,
                f"config key 'params.radius' [inner, outer] must have inner < outer < half the box less two cells "
                f"({0.5 * p['length'] - 2 * dx:g}), got {p['radius']}")
        thinnest = 0.5 * (outer - inner)
    else:
        for key in ("bore", "wall", "barrel", "breech"):
            p[key] = float(number(p[key], f"params.{key}", low=0))
        (length, height), (long, high) = p["size"], p["bullet"]
        _inside(high < p["bore"] and p["bore"] + 2 * p["wall"] < height - 4 * dx,
                f"config keys 'params.bullet' {p['bullet']}, 'params.bore' {p['bore']:g} and 'params.wall' "
                f"{p['wall']:g} must fit the bullet in the bore and the barrel in the box {p['size']}")
        _inside(2 * dx <= p["breech"] and p["breech"] + long < p["barrel"] < length - 4 * dx,
                f"config keys 'params.breech' {p['breech']:g} and 'params.barrel' {p['barrel']:g} must put the "
                f"bullet ({long:g} long) inside a barrel shorter than the box {p['size']}")
        _inside(p["wall"] >= 2 * dx, f"config key 'params.wall' ({p['wall']:g}) must be at least 2 cells thick "
                                     f"({2 * dx:g}); raise params.cells or the wall")
        thinnest = 0.5 * high
    if thinnest < 1.5 * dx:
        raise ConfigError(f"config key 'params.cells' ({p['cells']} per unit length) leaves the solid under 3 cells "
                          "across; raise it")
    p["mesh_size"] = 0.5 * dx if p["mesh_size"] is None else float(number(p["mesh_size"], "params.mesh_size", low=0))
    return p


def _cells(nx: int, ny: int, dx: float):
    return np.meshgrid((np.arange(nx) + 0.5) * dx, (np.arange(ny) + 0.5) * dx, indexing="ij")


def _lifting_cylinder(p: dict, dx: float):
    (length, height) = p["size"]
    nx, ny = round(length / dx), round(height / dx)
    x, _ = _cells(nx, ny, dx)
    inflow, state = gas.shock_start(x, p["shock_at"], p["mach"], p["ahead"], p["gamma"])
    grid = euler.Grid((nx, ny), dx, (("inlet", "open"), ("wall", "wall")), inflow=inflow)
    # a cylinder resting on the floor is meshed a hair above it, so no particle sits on the wall's nodes
    cx, cy = p["centre"]
    mesh = shapes.disk(p["radius"], p["mesh_size"], center=(cx, max(cy, p["radius"] + 1e-3 * dx)))
    return grid, state, mesh, p["ahead"][1]


def _shell_explosion(p: dict, dx: float):
    n = round(p["length"] / dx)
    grid = euler.Grid((n, n), dx, (("wall", "wall"), ("wall", "wall")))
    x, y = _cells(n, n, dx)
    centre = 0.5 * p["length"]
    inside = np.hypot(x - centre, y - centre) < p["radius"][0]
    (rho_in, p_in), (rho_out, p_out) = p["inside"], p["outside"]
    state = gas.conserved(np.where(inside, rho_in, rho_out), np.zeros((2, n, n)), np.where(inside, p_in, p_out),
                          p["gamma"])
    mesh = shapes.annulus(p["radius"][0], p["radius"][1], p["mesh_size"], center=(centre, centre))
    return grid, state, mesh, p_out


def _bullet(p: dict, dx: float):
    (length, height), (long, high) = p["size"], p["bullet"]
    nx, ny = round(length / dx), round(height / dx)
    x, y = _cells(nx, ny, dx)
    axis, bore, wall = 0.5 * height, 0.5 * p["bore"], p["wall"]
    barrel = (x < p["barrel"]) & (np.abs(y - axis) > bore) & (np.abs(y - axis) < bore + wall)
    barrel |= (x < 2 * dx) & (np.abs(y - axis) <= bore)  # the breech closes the bore's back
    grid = euler.Grid((nx, ny), dx, (("wall", "open"), ("wall", "wall")), solid=barrel)
    chamber = (x < p["breech"]) & (np.abs(y - axis) <= bore)
    (rho_c, p_c), (rho_o, p_o) = p["chamber"], p["outside"]
    state = gas.conserved(np.where(chamber, rho_c, rho_o), np.zeros((2, nx, ny)), np.where(chamber, p_c, p_o),
                          p["gamma"])
    back, half = p["breech"] + 0.5 * dx, 0.5 * high
    nose = np.linspace(-0.5 * np.pi, 0.5 * np.pi, 17)
    ring = np.concatenate([[[back, axis - half]], np.stack([back + long - half + half * np.cos(nose),
                                                            axis + half * np.sin(nose)], 1), [[back, axis + half]]])
    return grid, state, shapes.polygon(ring, size=p["mesh_size"]), p_o


_SETUPS = {"lifting_cylinder": _lifting_cylinder, "shell_explosion": _shell_explosion, "bullet": _bullet}


def _setup(name: str, p: dict):
    dx = 1.0 / p["cells"]
    grid, state, mesh, ambient = _SETUPS[name](p, dx)
    material = MATERIALS[p["material"]](E=p["E"], nu=p["nu"], density=p["density"])
    solid = coupled.Solid.from_mesh(mesh, material, p0=ambient)
    x, y = _cells(*grid.shape, dx)
    return grid, state, solid, mesh, np.stack([x.ravel(), y.ravel()], 1)


def simulate(config: dict) -> Trajectory:
    """Run a resolved coupled scene (:func:`datagen.csmpm.scenes.resolve`)."""
    p, s, o = config["params"], config["solver"], config["output"]
    grid, state, solid, mesh, centres = _setup(config["scene"], p)
    start_cells = np.zeros(len(centres), bool) if grid.solid is None else grid.solid.ravel().copy()
    states, solids, cells, wall, times, iterations, floored = [state], [solid], [start_cells], [0.0], [0.0], [0], [0]
    run = {"state": state, "solid": solid, "floored": 0, "cells": start_cells}
    substeps = 0

    def advance(t: float, remaining: float):
        dt = min(coupled.time_step(run["state"], run["solid"], grid, s["cfl"]), remaining)
        run["state"], run["solid"], info = coupled.step(run["state"], run["solid"], grid, dt, gamma=p["gamma"])
        run["floored"] += info.floored
        run["cells"] = info.solid_cells if grid.solid is None else info.solid_cells | grid.solid
        if not (gas.physical(run["state"], p["gamma"]) and np.all(np.isfinite(run["solid"].x))):
            raise RuntimeError(f"{config['scene']}: the state became non-physical at t = {t + dt:.6g} s; lower "
                               "solver.cfl or refine params.cells")
        return dt, info.cg_iterations

    for _, t, steps, most, seconds in frames(o, s["max_substeps"], advance):
        wall.append(seconds)
        substeps += steps
        iterations.append(most)
        floored.append(run["floored"])
        run["floored"] = 0
        states.append(run["state"])
        solids.append(run["solid"])
        cells.append(run["cells"].ravel())
        times.append(t)
    stacked = np.stack(states).reshape(len(states), 4, -1)
    rho = stacked[:, 0]
    velocity = np.moveaxis(stacked[:, 1:-1] / rho[:, None], 1, -1)
    positions = np.stack([b.x for b in solids])
    node_type = np.full(mesh.n_nodes, NodeType.FREE, np.int64)
    return Trajectory(
        mesh=mesh, positions=positions, velocities=np.stack([b.v for b in solids]), times=np.array(times),
        diagnostics={"mass": rho.sum(1) * grid.dx ** 2, "momentum": np.stack([b.momentum for b in solids]),
                     "centre": positions.mean(1), "cg_iterations": np.array(iterations),
                     "floored": np.array(floored)},
        wall_time=float(sum(wall)), config=config, dt=times[-1] / max(substeps, 1), substeps=substeps,
        n_particles=len(solids[-1].x), frame_wall_times=np.array(wall), node_type=node_type,
        fields={"x": centres, "density": rho, "velocity": velocity,
                "pressure": gas.pressure(np.moveaxis(stacked, 1, 0), p["gamma"]), "solid": np.stack(cells)},
    )
