"""Family ``glyphs``: 1-3 elastic letters dropped into a box.

Letters come from ``ranges.train_chars`` for the train and valid splits and from
``ranges.test_chars`` for the test split, so a model is tested on shapes it never saw.
Letters sit in equal columns across the box (one each), jittered, in its upper part.
"""

from __future__ import annotations

import numpy as np

from ..config import ConfigError
from .base import check_ranges, integer, log_midpoint, log_uniform, midpoint, uniform
from .placement import bodies_config, row_centers

NAME = "glyphs"
SCENE = "glyphs"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, True, True, False
RANGES = {
    "count": [1, 3], "train_chars": "ABCDEFHKLMNPRTVWXYZ", "test_chars": "GJQSU", "height": [0.22, 0.3],
    "speed_x": [-0.3, 0.3], "speed_y": [-0.5, 0.0], "E": [1e4, 4e4], "density": [800.0, 1200.0],
    "box": [0.0, 0.0, 1.0, 1.0],
}


def _alphabet(r: dict, split: str) -> str:
    key = "test_chars" if split == "test" else "train_chars"
    chars = r[key]
    if not isinstance(chars, str) or not chars.strip():
        raise ConfigError(f"ranges.{key} must be a non-empty string of characters, got {chars!r}")
    if split == "test" and set(chars) & set(r["train_chars"]):
        shared = "".join(sorted(set(chars) & set(r["train_chars"])))
        raise ConfigError(f"ranges.test_chars shares {shared!r} with ranges.train_chars; test letters must be unseen")
    return chars.replace(" ", "")


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    chars = _alphabet(r, split)
    n = integer(r, "count", rng)
    x0, y0, x1, y1 = (float(v) for v in r["box"])
    column = (x1 - x0) / n
    height = min(uniform(r, "height", rng), 0.8 * column, 0.4 * (y1 - y0))
    jitter = 0.5 * (column - height * 0.9)
    centers = [[x0 + (k + 0.5) * column + rng.uniform(-jitter, jitter) * 0.5,
                rng.uniform(y0 + 0.5 * (y1 - y0), y1 - 0.6 * height)] for k in range(n)]
    return {
        "chars": [chars[int(i)] for i in rng.integers(len(chars), size=n)], "centers": centers, "height": height,
        "velocities": [[uniform(r, "speed_x", rng), uniform(r, "speed_y", rng)] for _ in range(n)],
        "box": [x0, y0, x1, y1], "E": log_uniform(r, "E", rng), "density": uniform(r, "density", rng),
    }


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``bodies`` config dropping ``meshes`` (2D) into this family's box like its letters.

    Each mesh is scaled so its largest extent is the mid-range letter height (capped as the
    sampler caps it: 0.8 of a column, 0.4 of the box height); one column each across the box,
    at the middle of the sampler's height range; mid-range velocity, E (log scale) and
    density. ``overrides`` replace any of these bodies scene parameters.
    """
    def choose(r: dict, n: int) -> dict:
        r = check_ranges(NAME, RANGES, r)
        x0, y0, x1, y1 = (float(v) for v in r["box"])
        size = min(midpoint(r, "height"), 0.8 * (x1 - x0) / n, 0.4 * (y1 - y0))
        centers = row_centers(n, [x0, y0 + 0.5 * (y1 - y0)], [x1, y1 - 0.6 * size])
        velocity = [midpoint(r, "speed_x"), midpoint(r, "speed_y")]
        return {"box": [x0, y0, x1, y1], "centers": centers.tolist(), "sizes": [size] * n,
                "velocities": [velocity] * n, "E": log_midpoint(r, "E"), "density": midpoint(r, "density")}

    return bodies_config(NAME, DIM, SCENE, meshes, dconfig, overrides, choose)
