"""Family ``disks``: 2-3 elastic disks of random radii, positions and velocities in a box (UMLS §3.2)."""

from __future__ import annotations

import math

import numpy as np

from .base import check_ranges, integer, log_midpoint, log_uniform, midpoint, place_disjoint, uniform
from .placement import bodies_config, row_centers, toward_axis

NAME = "disks"
SCENE = "disks"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, True, True, False
RANGES = {
    "count": [2, 3], "radius": [0.12, 0.2], "speed": [0.05, 0.2], "E": [500.0, 2000.0],
    "density": [800.0, 1200.0], "box": [0.0, 0.0, 1.0, 1.0], "gap": 0.02,
}


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    """Scene parameters for one trajectory (``split`` does not change the distribution)."""
    r = check_ranges(NAME, RANGES, ranges)
    n = integer(r, "count", rng)
    radii = [uniform(r, "radius", rng) for _ in range(n)]
    box = [float(v) for v in r["box"]]
    centers = place_disjoint(radii, box[:2], box[2:], uniform(r, "gap", rng), rng, "radius")
    angles = rng.uniform(0.0, 2 * math.pi, n)
    speeds = [uniform(r, "speed", rng) for _ in range(n)]
    velocities = [[s * math.cos(a), s * math.sin(a)] for s, a in zip(speeds, angles, strict=True)]
    return {
        "radii": radii, "centers": centers.tolist(), "velocities": velocities, "box": box,
        "E": log_uniform(r, "E", rng), "density": uniform(r, "density", rng),
    }


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``bodies`` config putting ``meshes`` (2D) into this family's box to collide.

    Each mesh is scaled so its largest extent is the mid-range disk diameter (at most 0.8 of
    its column); one column each across the box at mid-height; every body moves at the
    mid-range speed towards the box centre (a body at the centre moves along +x). E (log
    scale) and density are mid-range. ``overrides`` replace any of these bodies scene parameters.
    """
    def choose(r: dict, n: int) -> dict:
        r = check_ranges(NAME, RANGES, r)
        lower, upper = np.asarray(r["box"][:2], float), np.asarray(r["box"][2:], float)
        size = min(2 * midpoint(r, "radius"), 0.8 * (upper[0] - lower[0]) / n, 0.8 * (upper[1] - lower[1]))
        centers = row_centers(n, lower, upper)
        velocities = toward_axis(centers, (lower + upper) / 2, midpoint(r, "speed"))
        return {"box": [float(v) for v in r["box"]], "centers": centers.tolist(), "sizes": [size] * n,
                "velocities": velocities.tolist(), "E": log_midpoint(r, "E"), "density": midpoint(r, "density")}

    return bodies_config(NAME, DIM, SCENE, meshes, dconfig, overrides, choose)
