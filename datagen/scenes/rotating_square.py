"""Rotating elastic square (UMLS App. D.1): APIC + UMLS conserves linear and angular momentum.

A square of side 0.2 sampled by 20 x 20 particles in the middle of a 1 x 1 box; its left
half starts moving up and its right half down at 1 m/s, so it spins. (The paper's text
writes the velocities as (+-1, 0) while calling them upward/downward; we use (0, +-1).)
Time step 1e-5 s as in the paper; the default output covers 5000 steps of its 10^6.
"""

from __future__ import annotations

import numpy as np

from .. import shapes
from ..mpm.boundary import Wall
from .base import Scene, check_params, lattice, lattice_mesh, make_material

NAME = "rotating_square"
DEFAULTS = {
    "side": 0.2, "particles_per_side": 20, "E": 1e4, "nu": 0.3, "density": 1.0, "speed": 1.0,
    "box": 1.0, "mesh_size": 0.01, "material": "neo_hookean",
}
OUTPUT = {"frames": 50, "frame_interval": 1e-3}
SOLVER = {"transfer": "apic", "dt": 1e-5}


def params(given: dict) -> dict:
    return check_params(
        NAME, DEFAULTS, given,
        positive=("side", "particles_per_side", "E", "density", "box", "mesh_size"),
        choices={"material": {"linear", "neo_hookean", "fixed_corotated"}},
    )


def build(p: dict) -> Scene:
    box, side = p["box"], p["side"]
    center = np.full(2, box / 2)
    x, counts, step = lattice(center - side / 2, center + side / 2, side / p["particles_per_side"])
    v = np.zeros_like(x)
    v[:, 1] = np.where(x[:, 0] < center[0], p["speed"], -p["speed"])
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    return Scene(
        domain=shapes.rectangle(box, box, p["mesh_size"]), body=lattice_mesh(x, counts), x=x, v=v,
        volume=np.full(len(x), float(np.prod(step))), materials=[(material, None)],
        tracked=np.arange(len(x)), walls=[Wall("separating", lambda c, n: np.ones(len(c), bool))],
        gravity=np.zeros(2), grid_spacing=p["mesh_size"],
    )
