"""Rotating hyperelastic plate (A-ULMPM §6.1.1): numerical fracture under spin.

A square plate of side ``side`` sampled by ``particles_per_cell`` particles per background
cell and direction spins about its centre at ``omega`` rad/s inside a box with separating
walls, without gravity. The spin stretches it (centrifugal load) and makes it breathe.
Eulerian MPM lets the stretched, fast-moving particles lose their shared nodes and the plate
tears (numerical fracture); the total and adaptive reference configurations keep it whole.
The body mesh is the particle lattice (two triangles per quad); :func:`fracture_fraction`
counts its edges longer than twice the background cell size. The defaults are the settings
of tests/test_reference_modes.py (small and short enough for a CPU test in about a second per mode).
"""

from __future__ import annotations

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mpm.boundary import Wall
from .base import Scene, check_params, lattice, lattice_mesh, make_material

NAME = "rotating_plate"
DEFAULTS = {
    "side": 0.3, "box": 1.0, "mesh_size": 0.05, "particles_per_cell": 2, "omega": 150.0,
    "E": 100.0, "nu": 0.3, "density": 1.0, "material": "neo_hookean",
}
# cfl 0.4 (default 0.3): fewer steps for the CPU tests; all three modes are stable there, and the
# eulerian plate tears after ~0.12 s (frame 4) instead of ~0.27 s.
OUTPUT = {"frames": 8, "frame_interval": 0.03}
SOLVER = {"transfer": "apic", "epsilon": 0.5, "fraction": 0.1, "cfl": 0.4}


def params(given: dict) -> dict:
    return check_params(
        NAME, DEFAULTS, given,
        positive=("side", "box", "mesh_size", "particles_per_cell", "E", "density"),
        choices={"material": {"linear", "neo_hookean", "fixed_corotated"}},
    )


def build(p: dict) -> Scene:
    box, side = p["box"], p["side"]
    if not side < box:
        raise ConfigError(f"params.side ({side}) must be smaller than params.box ({box})")
    center = np.full(2, box / 2)
    spacing = p["mesh_size"] / p["particles_per_cell"]
    x, counts, step = lattice(center - side / 2, center + side / 2, spacing)
    r = x - center
    v = p["omega"] * np.stack([-r[:, 1], r[:, 0]], axis=1)
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    return Scene(
        domain=shapes.rectangle(box, box, p["mesh_size"]), body=lattice_mesh(x, counts), x=x, v=v,
        volume=np.full(len(x), float(np.prod(step))), materials=[(material, None)], tracked=np.arange(len(x)),
        walls=[Wall("separating", lambda c, n: np.ones(len(c), bool))], gravity=np.zeros(2),
        grid_spacing=p["mesh_size"],
    )
