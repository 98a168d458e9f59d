"""Family ``balls``: 1-2 elastic 3D bodies dropped into a box (y is up, gravity along -y).

Bodies are spheres (``ranges.train_shapes``) in the train and valid splits and cubes
(``ranges.test_shapes``) in the test split, so a model is tested on a shape it never saw;
a cube fits in the sphere of its sampled radius. Bodies start apart, in the upper part of
the box, falling with a random downward speed and a random horizontal drift.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import ConfigError
from ..scenes.balls import BODY_SHAPES
from ..scenes.base import box_bounds
from .base import check_ranges, integer, log_midpoint, log_uniform, midpoint, place_disjoint, uniform
from .placement import bodies_config, row_centers, toward_axis

NAME = "balls"
SCENE = "balls"
DIM, CONTACT, OBSTACLES, CLAMPED = 3, True, True, False
RANGES = {
    "count": [1, 2], "radius": [0.12, 0.2], "train_shapes": ["sphere"], "test_shapes": ["cube"],
    "speed_h": [0.0, 0.3], "speed_y": [-0.5, 0.0], "E": [1e4, 4e4], "density": [800.0, 1200.0],
    "box": [0.0, 0.0, 0.0, 1.0, 1.0, 1.0], "drop": 0.4, "gap": 0.02,
}


def _shapes(r: dict, split: str) -> list[str]:
    key = "test_shapes" if split == "test" else "train_shapes"
    chosen = r[key]
    if not isinstance(chosen, (list, tuple)) or not chosen or any(s not in BODY_SHAPES for s in chosen):
        raise ConfigError(f"ranges.{key} must be a non-empty list of {list(BODY_SHAPES)}, got {chosen!r}")
    if split == "test" and set(chosen) & set(r["train_shapes"]):
        shared = sorted(set(chosen) & set(r["train_shapes"]))
        raise ConfigError(f"ranges.test_shapes shares {shared} with ranges.train_shapes; test shapes must be unseen")
    return list(chosen)


def _box(r: dict) -> tuple[np.ndarray, np.ndarray]:
    lower, upper = box_bounds(r["box"], "ranges.box")
    if len(lower) != 3:
        raise ConfigError(f"ranges.box must be a 3D box [x0, y0, z0, x1, y1, z1], got {r['box']!r}")
    return lower, upper


def _drop_region(r: dict) -> tuple[np.ndarray, np.ndarray]:
    """Where bodies start: the box above the fraction ``ranges.drop`` of its height."""
    lower, upper = _box(r)
    fraction = midpoint(r, "drop")
    if not 0.0 <= fraction < 1.0:
        raise ConfigError(f"ranges.drop must be a fraction of the box height in [0, 1), got {r['drop']!r}")
    start = lower.copy()
    start[1] += fraction * (upper[1] - lower[1])
    return start, upper


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    shapes = _shapes(r, split)
    n = integer(r, "count", rng)
    radii = [uniform(r, "radius", rng) for _ in range(n)]
    start, upper = _drop_region(r)
    centers = place_disjoint(radii, start, upper, uniform(r, "gap", rng), rng, "radius")
    velocities = []
    for _ in range(n):
        speed, angle = uniform(r, "speed_h", rng), rng.uniform(0.0, 2 * math.pi)
        velocities.append([speed * math.cos(angle), uniform(r, "speed_y", rng), speed * math.sin(angle)])
    return {
        "shapes": [shapes[int(i)] for i in rng.integers(len(shapes), size=n)], "radii": radii,
        "centers": centers.tolist(), "velocities": velocities, "box": [float(v) for v in r["box"]],
        "E": log_uniform(r, "E", rng), "density": uniform(r, "density", rng),
    }


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``bodies`` config dropping ``meshes`` (3D) into this family's box.

    Each mesh is scaled to the mid-range ball diameter (smaller if the bodies would not fit
    side by side along x), the bodies stand in a row along x in the middle of the drop region
    (centred in z), and they fall at the mid-range speeds, drifting towards the box's vertical
    centre line. E (log scale) and density are mid-range; ``overrides`` replace any of these.
    """
    def choose(r: dict, n: int) -> dict:
        r = check_ranges(NAME, RANGES, r)
        start, upper = _drop_region(r)
        width = upper[0] - start[0]
        size = min(2 * midpoint(r, "radius"), 0.8 * width / n, 0.8 * (upper[1] - start[1]))
        centers = row_centers(n, start, upper)
        drift = toward_axis(centers, (start + upper) / 2, midpoint(r, "speed_h"), axes=(0, 2))
        drift[:, 1] = midpoint(r, "speed_y")
        return {"box": [float(v) for v in r["box"]], "centers": centers.tolist(), "sizes": [size] * n,
                "velocities": drift.tolist(), "E": log_midpoint(r, "E"), "density": midpoint(r, "density")}

    return bodies_config(NAME, DIM, SCENE, meshes, dconfig, overrides, choose)
