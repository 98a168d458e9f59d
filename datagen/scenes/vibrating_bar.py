"""Vibrating bar (UMLS §3.1): a bar fixed at x = 0, free at x = L, started in its first mode.

Initial velocity v0 sin(beta_1 x), beta_1 = pi / (2L); the centre of mass follows UMLS eq. 34.
``dim = 1`` is the paper's 1D bar; ``dim = 2`` a strip of the given height between slip walls
(with nu = 0 it is the same 1D problem). The background mesh extends ``margin`` beyond the
free end so the bar can stretch into it.

``fixed_end`` picks the treatment of the extra-layer nodes beyond the sticky wall x = 0
(datagen/mpm/boundary.py): ``fold`` (default) mirror ghosts whose P2G sums are folded onto the
nodes they mirror (the bar sees its odd mirror image; second order in dx); ``overwrite`` mirror
ghosts only overwritten after the update (the clamp about 0.07 dx beyond x = 0: first order);
``rest`` held at rest (about 0.14 dx beyond: first order).
"""

from __future__ import annotations

import math

import numpy as np

from .. import shapes
from ..mpm.boundary import Wall
from .base import Scene, check_params, lattice, lattice_mesh, line_mesh, make_material, nearest

NAME = "vibrating_bar"
DEFAULTS = {
    "E": 100.0, "nu": 0.0, "density": 1.0, "length": 25.0, "v0": 0.75,
    "n_cells": 80, "particles_per_cell": 2, "dim": 1, "height": 1.0, "margin": 2.5,
    "material": "linear", "probe_x": 12.75, "fixed_end": "fold",
}
OUTPUT = {"frames": 100, "frame_interval": 0.1}  # one period (10 s) with the defaults
FIXED_END = {"fold": {"fold": True}, "overwrite": {"fold": False}, "rest": {"mirror": False}}  # Wall options of x = 0
SOLVER = {"transfer": "flip"}


def params(given: dict) -> dict:
    return check_params(
        NAME, DEFAULTS, given,
        positive=("E", "density", "length", "n_cells", "particles_per_cell", "height", "margin"),
        choices={"dim": {1, 2}, "material": {"linear", "neo_hookean", "fixed_corotated"},
                 "fixed_end": set(FIXED_END)},
    )


def omega(p: dict) -> float:
    """First angular frequency omega_1 = beta_1 sqrt(E / rho)."""
    return math.pi / (2 * p["length"]) * math.sqrt(p["E"] / p["density"])


def amplitude(p: dict) -> float:
    """Amplitude of the centre-of-mass oscillation, v0 / (beta_1 L omega_1) (UMLS eq. 34)."""
    return p["v0"] / (math.pi / 2 * omega(p))


def center_of_mass(p: dict, t) -> np.ndarray:
    """x_CM(t) = L/2 + v0 / (beta_1 L omega_1) sin(omega_1 t) (UMLS eq. 34)."""
    return p["length"] / 2 + amplitude(p) * np.sin(omega(p) * np.asarray(t, float))


def stress(p: dict, x0: float, t) -> np.ndarray:
    """Exact axial stress E du/dx at material point x0: E v0 / c cos(beta_1 x0) sin(omega_1 t)."""
    beta = math.pi / (2 * p["length"])
    c = math.sqrt(p["E"] / p["density"])
    return p["E"] * p["v0"] / c * math.cos(beta * x0) * np.sin(omega(p) * np.asarray(t, float))


def build(p: dict) -> Scene:
    L, dim = p["length"], p["dim"]
    dx = L / p["n_cells"]
    extra = math.ceil(p["margin"] / dx)
    if dim == 1:
        domain = line_mesh(0.0, L + extra * dx, p["n_cells"] + extra)
        upper = [L]
    else:
        domain = shapes.rectangle(L + extra * dx, p["height"], dx)
        upper = [L, p["height"]]
    x, counts, step = lattice(np.zeros(dim), upper, dx / p["particles_per_cell"])
    v = np.zeros_like(x)
    v[:, 0] = p["v0"] * np.sin(math.pi / (2 * L) * x[:, 0])
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    walls = [
        Wall("sticky", lambda c, n: n[:, 0] < -0.5, **FIXED_END[p["fixed_end"]]),  # fixed end x = 0
        Wall("separating", lambda c, n: n[:, 0] > 0.5),
    ]
    if dim == 2:
        walls.insert(0, Wall("slip", lambda c, n: np.abs(n[:, 1]) > 0.5))
    probe = [p["probe_x"]] + ([p["height"] / 2] if dim == 2 else [])
    return Scene(
        domain=domain, body=lattice_mesh(x, counts), x=x, v=v,
        volume=np.full(len(x), float(np.prod(step))), materials=[(material, None)],
        tracked=np.arange(len(x)), walls=walls, gravity=np.zeros(dim),
        probes={"probe": nearest(x, probe)}, grid_spacing=dx,
    )
