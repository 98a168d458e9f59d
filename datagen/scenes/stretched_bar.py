"""Stretched bar (2D analogue of A-ULMPM §6.2): pulled at both ends, held, then released.

A hyperelastic bar of ``length`` x ``height`` lies in a box with room to stretch. The particles
within ``grip`` of each end are held by grips (:class:`datagen.mpm.model.Grip`) that move
apart at ``pull_speed`` each until ``pull_time``, stand still until ``release_time`` and then
let go. A mass-proportional ``damping`` (1/s; the default is near critical) lets the released
bar settle within the run. Elastic material: a bar that kept its material connectivity
recovers its rest length; eulerian MPM tears the stretched bar (numerical fracture) and it
cannot. No gravity; the box walls are slip walls far from the bar. The defaults are the settings of
tests/test_reference_modes.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mpm.boundary import Wall
from .base import Scene, check_params, lattice, lattice_mesh, make_material

NAME = "stretched_bar"
DEFAULTS = {
    "length": 1.0, "height": 0.2, "mesh_size": 0.05, "particles_per_cell": 2, "grip": 0.1,
    "pull_speed": 2.0, "pull_time": 0.25, "release_time": 0.35, "damping": 40.0, "margin": 1.0,
    "E": 100.0, "nu": 0.3, "density": 1.0, "material": "neo_hookean",
}
# The bar settles (near critical damping) within ~0.25 s of its release at 0.35 s. cfl 0.4 (default
# 0.3): fewer steps for the CPU tests; all three modes are stable there.
OUTPUT = {"frames": 28, "frame_interval": 0.025}
SOLVER = {"transfer": "flip", "epsilon": 0.5, "fraction": 0.1, "cfl": 0.4}


@dataclass
class GrippedScene(Scene):
    """A scene whose particle sets ``grips`` [(ids, velocity(t) -> (d,) or None)] move as
    prescribed (with :class:`Scene`'s mass-proportional ``damping``, 1/s, of the nodal velocities)."""

    grips: list = field(default_factory=list)


def params(given: dict) -> dict:
    p = check_params(
        NAME, DEFAULTS, given,
        positive=("length", "height", "mesh_size", "particles_per_cell", "grip", "pull_time", "release_time",
                  "margin", "E", "density"),
        choices={"material": {"linear", "neo_hookean", "fixed_corotated"}},
    )
    if p["damping"] < 0:
        raise ConfigError(f"params.damping must be >= 0, got {p['damping']!r}")
    if p["release_time"] < p["pull_time"]:
        raise ConfigError(f"params.release_time ({p['release_time']}) must not come before "
                          f"params.pull_time ({p['pull_time']})")
    if 2 * p["grip"] >= p["length"]:
        raise ConfigError(f"params.grip ({p['grip']}) must be less than half of params.length ({p['length']})")
    if p["pull_speed"] * p["pull_time"] >= p["margin"]:
        raise ConfigError("params.margin must exceed params.pull_speed * params.pull_time (the pull per end)")
    return p


def grip_ids(p: dict, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Particle ids of the left and right grips."""
    return np.flatnonzero(x[:, 0] < p["grip"]), np.flatnonzero(x[:, 0] > p["length"] - p["grip"])


def build(p: dict) -> Scene:
    L, H, margin, h = p["length"], p["height"], p["margin"], p["mesh_size"]
    x, counts, step = lattice([0.0, 0.0], [L, H], h / p["particles_per_cell"])
    left, right = grip_ids(p, x)
    pull, hold = p["pull_time"], p["release_time"]

    def grip_velocity(sign: float):
        def velocity(t: float):
            if t >= hold:
                return None
            return (sign * p["pull_speed"], 0.0) if t < pull else (0.0, 0.0)
        return velocity

    domain = shapes.rectangle(L + 2 * margin, H + 2 * 4 * h, h, origin=(-margin, -4 * h))
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    return GrippedScene(
        domain=domain, body=lattice_mesh(x, counts), x=x, v=np.zeros_like(x),
        volume=np.full(len(x), float(np.prod(step))), materials=[(material, None)], tracked=np.arange(len(x)),
        walls=[Wall("slip", lambda c, n: np.ones(len(c), bool))], gravity=np.zeros(2), grid_spacing=h,
        grips=[(left, grip_velocity(-1.0)), (right, grip_velocity(1.0))], damping=p["damping"],
    )


def bar_length(p: dict, positions: np.ndarray) -> np.ndarray:
    """(T,) distance between the centroids of the two grips' particles, per frame (positions (T, P, 2))."""
    x0 = positions[0]
    left, right = grip_ids(p, x0)
    return positions[:, right, 0].mean(1) - positions[:, left, 0].mean(1)
