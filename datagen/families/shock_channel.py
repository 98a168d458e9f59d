"""Family ``shock_channel``: a shock of random strength hitting a rigid obstacle of random shape
in a channel (CSMPM's gas; :mod:`datagen.csmpm.flow`), Eulerian data for the learned side.

Each trajectory draws a star-shaped polygon (``vertices`` corners, radii 0.55-1 of ``radius``,
turned at random) centred at (``x``, ``y``) and a shock of Mach ``mach`` into still gas of
density 1.4 and pressure 1 (sound speed 1).
"""

from __future__ import annotations

import math

import numpy as np

from ..config import ConfigError
from .base import check_ranges, integer, uniform
from .press import random_polygon

NAME = "shock_channel"
SCENE = "shock_channel"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, False, False, True
RANGES = {"x": [0.45, 0.75], "y": [0.35, 0.65], "radius": [0.1, 0.2], "vertices": [4, 8], "mach": [1.5, 3.0]}


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    ring = np.asarray(random_polygon(rng, integer(r, "vertices", rng, minimum=3)))
    turn = rng.uniform(0.0, 2.0 * math.pi)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    centre = np.array([uniform(r, "x", rng), uniform(r, "y", rng)])
    corners = centre + uniform(r, "radius", rng) * ring @ rotation.T
    return {"obstacle": np.round(corners, 6).tolist(), "mach": uniform(r, "mach", rng)}


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """Not supported: the obstacle is a polygon of the channel's cells, not a body mesh; raises ConfigError."""
    raise ConfigError(f"zero-shot placement is not supported for family {NAME}: its obstacle is a polygon "
                      "(params.obstacle: [[x, y], ...]) of the gas grid's cells; give one to datagen.simulate "
                      "with scene shock_channel instead")
