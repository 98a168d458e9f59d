"""Family ``wavy_channel``: an elastic body falling through a random wavy channel (UMLS §3.4)."""

from __future__ import annotations

import numpy as np

from ..config import ConfigError
from .base import check_ranges, choice, log_uniform, uniform

NAME = "wavy_channel"
SCENE = "wavy_channel"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, True, True, False
RANGES = {
    "amplitude": [0.2, 0.6], "omega1": [0.4, 0.8], "omega2": [0.1, 0.2], "width": [1.6, 2.4],
    "radius": [0.35, 0.6], "shape": ["disk"], "E": [5e4, 2e5], "density": [80.0, 120.0],
    "velocity_x": [-0.5, 0.5], "velocity_y": [-1.0, 0.0],
}


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    width = uniform(r, "width", rng)
    radius = min(uniform(r, "radius", rng), 0.4 * width)
    return {
        "amplitude": uniform(r, "amplitude", rng), "omega1": uniform(r, "omega1", rng),
        "omega2": uniform(r, "omega2", rng), "width": width, "radius": radius, "inlet": 2.5 * radius,
        "shape": choice(r, "shape", rng), "E": log_uniform(r, "E", rng), "density": uniform(r, "density", rng),
        "velocity": [uniform(r, "velocity_x", rng), uniform(r, "velocity_y", rng)],
    }




def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """Not supported: the channel scene builds its own body; raises ConfigError saying what to use instead."""
    raise ConfigError(f"zero-shot placement is not supported for family {NAME}: its scene meshes its own body "
                      "(params.shape: disk, square, ring or 'glyph:<text>'); to drop your own mesh into a box use "
                      "family glyphs or disks (2D) or balls (3D)")
