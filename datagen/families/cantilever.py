"""Family ``cantilever``: beams of random size, stiffness, density and background rotation (UMLS §3.3).

A sampler over the verification scene ``cantilever`` (clamped at x = 0 by a sticky wall,
swinging under gravity); the room below the beam grows with its length.
"""

from __future__ import annotations

import numpy as np

from ..config import ConfigError
from .base import check_ranges, log_uniform, uniform

NAME = "cantilever"
SCENE = "cantilever"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, False, True, True
RANGES = {
    "length": [6.0, 10.0], "height": [1.5, 2.5], "E": [5e4, 2e5], "density": [1.5, 3.0],
    "rotation": [0.0, 45.0],
}


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    length = uniform(r, "length", rng)
    return {
        "length": length, "height": uniform(r, "height", rng), "E": log_uniform(r, "E", rng),
        "density": uniform(r, "density", rng), "rotation": uniform(r, "rotation", rng), "drop": 0.5 * length,
    }


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """Not supported: a clamped beam has no free body to swap; raises ConfigError saying what to use instead."""
    raise ConfigError(f"zero-shot placement is not supported for family {NAME}: its body is a beam clamped to a "
                      "wall, which an arbitrary mesh has no part to clamp by; to drop your own mesh into a box use "
                      "family glyphs or disks (2D) or balls (3D)")
