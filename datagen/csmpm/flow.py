"""``shock_channel``: a shock hitting an obstacle in a channel, written as Eulerian data the
learned side trains on (the flow family, :mod:`datagen.families.shock_channel`).

A channel of ``size`` = [length, height] with ``cells`` cells per unit length, walls above and
below, an inlet on the left and an outlet on the right, holds still gas ``ahead`` = [rho, p]
and a rigid ``obstacle`` (a polygon, [[x, y], ...] in the channel's coordinates: its cells are
static solid cells). A shock of Mach ``mach`` starts at x = ``shock_at`` moving right; behind
it the gas holds the Rankine–Hugoniot state, which the inlet keeps feeding. The shock's
reflection off the obstacle, its diffraction around it and the reflections off the walls are
the motion. (An obstacle appearing in a uniform supersonic stream instead leaves a
near-vacuum wake behind it, where the pressure goes negative.) The gas solver is CSMPM's
(:mod:`datagen.csmpm.euler`; ``solver.cfl`` on |u| + ``solver.acoustic`` c); ``outlet``
``extrapolate`` (the default) or ``characteristic`` (the far field: the still gas ahead).

The Trajectory is Eulerian data like DeepMind's compressible ``airfoil``: its mesh triangulates
the gas cells' centres (fixed positions, velocities the gas velocity), its ``fields`` hold
``velocity`` (frames + 1, N, 2), ``density`` and ``pressure`` (frames + 1, N, 1) and
``node_type`` (1, N, 1) in DeepMind's codes (inflow: the first column; outflow: the last; wall
boundary: cells next to a channel wall or the obstacle; normal: the rest), and its config the
field spec ``bsms.fields.infer_spec`` gives those fields (velocity and density in; their
changes and the next pressure out). The inflow column is prescribed (node role CLAMPED); every
other cell is free.
"""

from __future__ import annotations

import numpy as np
from matplotlib.path import Path as Outline

from ..config import ConfigError
from ..mesh import Mesh
from ..trajectory import NodeType, Trajectory
from . import euler, gas
from .frames import gas_frames

__all__ = ["FLOW_DEFAULTS", "FLOW_OUTPUT", "check", "simulate", "cell_mesh", "DEEPMIND_TYPES"]

FLOW_DEFAULTS = {"shock_channel": {"size": [2.0, 1.0], "cells": 32, "mach": 2.0, "ahead": [1.4, 1.0],
                                   "shock_at": 0.1, "obstacle": [[0.45, 0.4], [0.65, 0.35], [0.75, 0.55], [0.55, 0.68]],
                                   "gamma": gas.GAMMA, "outlet": "extrapolate"}}
FLOW_OUTPUT = {"shock_channel": {"frames": 40, "frame_interval": 0.02}}
DEEPMIND_TYPES = {"normal": 0, "inflow": 4, "outflow": 5, "wall": 6}  # DeepMind's NodeType codes
# what bsms.fields.infer_spec makes of these fields (tested equal): airfoil's spec
FIELD_SPEC = {"kind": "eulerian", "dim": 2, "material_dim": 2, "inputs": [["velocity", 2], ["density", 1]],
              "outputs": [["velocity", 2, "change"], ["density", 1, "change"], ["pressure", 1, "value"]],
              "positions": "", "types": "node_type", "n_types": 9}


def check(name: str, p: dict, number, state) -> dict:
    """``shock_channel``'s params checked (``number``/``state``: the gas scenes' checks)."""
    p["cells"] = number(p["cells"], "params.cells", low=1, integer=True)
    p["gamma"] = float(number(p["gamma"], "params.gamma", low=1))
    if p["outlet"] not in ("extrapolate", "characteristic"):
        raise ConfigError(f"config key 'params.outlet' must be extrapolate or characteristic, got {p['outlet']!r}")
    p["mach"], p["shock_at"] = (float(number(p[k], f"params.{k}", low=0)) for k in ("mach", "shock_at"))
    if p["mach"] <= 1:
        raise ConfigError(f"config key 'params.mach' must be > 1 (a shock), got {p['mach']!r}")
    rho, pressure = state(p["ahead"], "params.ahead", with_velocity=False)
    p["ahead"] = [rho, pressure]
    size = p["size"]
    if not isinstance(size, (list, tuple)) or len(size) != 2:
        raise ConfigError(f"config key 'params.size' must be [length, height], got {size!r}")
    p["size"] = [float(number(v, f"params.size[{i}]", low=0)) for i, v in enumerate(size)]
    ring = p["obstacle"]
    if not isinstance(ring, (list, tuple)) or len(ring) < 3 or not all(
            isinstance(v, (list, tuple)) and len(v) == 2 for v in ring):
        raise ConfigError(f"config key 'params.obstacle' must be a polygon [[x, y], ...] of >= 3 corners, got {ring!r}")
    p["obstacle"] = [[float(number(c, f"params.obstacle[{i}]")) for c in v] for i, v in enumerate(ring)]
    corners = np.asarray(p["obstacle"])
    (length, height), dx = p["size"], 1.0 / p["cells"]
    if not (corners[:, 0].min() > p["shock_at"] + 2 * dx and corners[:, 0].max() < length - 2 * dx
            and corners[:, 1].min() > 2 * dx and corners[:, 1].max() < height - 2 * dx):
        raise ConfigError(f"config key 'params.obstacle' must lie inside the channel {p['size']}, two cells "
                          f"({2 * dx:g}) clear of its walls, its outlet and the shock's start (params.shock_at)")
    if min(round(v * p["cells"]) for v in p["size"]) < 8:
        raise ConfigError(f"config key 'params.cells' ({p['cells']} per unit length) gives fewer than 8 cells "
                          f"across the channel {p['size']}; raise it")
    return p


def cell_mesh(x: np.ndarray, y: np.ndarray, keep: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """The triangulated centres of the ``keep`` cells of a 2D grid: two triangles per square of
    four kept cells; (mesh, the kept cells' flat indices)."""
    kept = np.flatnonzero(keep.ravel())
    number = np.full(keep.size, -1)
    number[kept] = np.arange(len(kept))
    ids = number.reshape(keep.shape)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    a, b, c, d = a[full], b[full], c[full], d[full]
    cells = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(np.stack([x.ravel()[kept], y.ravel()[kept]], 1), cells), kept


def _setup(p: dict):
    (length, height), n = p["size"], p["cells"]
    dx = 1.0 / n
    nx, ny = round(length * n), round(height * n)
    x, y = np.meshgrid((np.arange(nx) + 0.5) * dx, (np.arange(ny) + 0.5) * dx, indexing="ij")
    solid = Outline(np.asarray(p["obstacle"])).contains_points(np.stack([x.ravel(), y.ravel()], 1)).reshape(nx, ny)
    if not solid.any():
        raise ConfigError(f"config key 'params.obstacle' covers no cell centre at {n} cells per unit length; "
                          "make it larger or raise params.cells")
    inflow, state = gas.shock_start(x, p["shock_at"], p["mach"], p["ahead"], p["gamma"])
    far = gas.conserved(np.array(p["ahead"][0]), np.zeros(2), np.array(p["ahead"][1]), p["gamma"])  # still gas
    grid = euler.Grid((nx, ny), dx, (("inlet", "open"), ("wall", "wall")), inflow=inflow, solid=solid,
                      outlet=p["outlet"], outflow=far)
    mesh, kept = cell_mesh(x, y, ~solid)
    codes = np.full((nx, ny), DEEPMIND_TYPES["normal"])
    near = np.zeros((nx, ny), bool)
    near[:, [0, -1]] = True
    padded = np.pad(solid, 1)
    near |= padded[:-2, 1:-1] | padded[2:, 1:-1] | padded[1:-1, :-2] | padded[1:-1, 2:]
    codes[near] = DEEPMIND_TYPES["wall"]
    codes[-1] = DEEPMIND_TYPES["outflow"]
    codes[0] = DEEPMIND_TYPES["inflow"]
    return grid, state, mesh, kept, codes.ravel()[kept]


def simulate(config: dict) -> Trajectory:
    """Run a resolved ``shock_channel`` config."""
    p, s, o = config["params"], config["solver"], config["output"]
    grid, state, mesh, kept, codes = _setup(p)
    states, times, wall, iterations, substeps = gas_frames("shock_channel", grid, state, p["gamma"], s, o)
    stacked = np.stack(states).reshape(len(states), 4, -1)[:, :, kept]
    rho = stacked[:, 0]
    velocity = np.moveaxis(stacked[:, 1:3] / rho[:, None], 1, -1)
    pressure = gas.pressure(np.moveaxis(stacked, 1, 0), p["gamma"])
    fields = {"velocity": velocity, "density": rho[..., None], "pressure": pressure[..., None],
              "node_type": codes[None, :, None].astype(np.int64)}
    role = np.where(codes == DEEPMIND_TYPES["inflow"], NodeType.CLAMPED, NodeType.FREE).astype(np.int64)
    n = len(mesh.nodes)
    volume = grid.dx ** 2
    return Trajectory(
        mesh=mesh, positions=np.broadcast_to(mesh.nodes[None], (len(states), n, 2)).copy(), velocities=velocity.copy(),
        times=np.array(times), wall_time=float(sum(wall)),
        config={**config, "field_spec": FIELD_SPEC},
        diagnostics={"mass": rho.sum(1) * volume, "cg_iterations": np.array(iterations)},
        dt=times[-1] / max(substeps, 1), substeps=substeps, n_particles=0, frame_wall_times=np.array(wall),
        node_type=role,
        fields=fields,
    )

