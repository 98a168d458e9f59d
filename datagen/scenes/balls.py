"""Elastic 3D bodies (balls, or cubes for zero-shot tests) dropped into a box.

Each body is a tetrahedralised sphere of radius ``radii[k]`` or an axis-aligned cube that
fits in that sphere (half-diagonal = radius), centred at ``centers[k]`` with initial velocity
``velocities[k]``. The box ``[x0, y0, z0, x1, y1, z1]`` is the background mesh; its whole
boundary is a separating wall with friction, and its boundary triangles are the obstacle
geometry a model sees. Gravity points along -y (y is up, as in the 2D box scenes).
"""

from __future__ import annotations

import math

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mesh import Mesh
from .base import Scene, box_bounds, box_domain, check_params, contained_bodies, merge_bodies

NAME = "balls"
DEFAULTS = {
    "shapes": ["sphere"], "radii": [0.15], "centers": [[0.5, 0.6, 0.5]], "velocities": [[0.0, 0.0, 0.0]],
    "box": [0.0, 0.0, 0.0, 1.0, 1.0, 1.0], "E": 2e4, "nu": 0.3, "density": 1000.0, "gravity": 2.0,
    "friction": 0.2, "body_size": 0.05, "mesh_size": 0.1, "material": "neo_hookean",
}
OUTPUT = {"frames": 40, "frame_interval": 0.05}
SOLVER = {"transfer": "flip"}
BODY_SHAPES = ("sphere", "cube")


def params(given: dict) -> dict:
    p = check_params(NAME, DEFAULTS, given, positive=("E", "density", "body_size", "mesh_size"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"}})
    n = len(p["radii"])
    if n == 0 or any(len(p[k]) != n for k in ("shapes", "centers", "velocities")):
        raise ConfigError("params.shapes, params.radii, params.centers and params.velocities must list the same "
                          f"number (at least one) of bodies, got {len(p['shapes'])}, {n}, {len(p['centers'])}, "
                          f"{len(p['velocities'])}")
    bad = [s for s in p["shapes"] if s not in BODY_SHAPES]
    if bad:
        raise ConfigError(f"params.shapes entries must be one of {list(BODY_SHAPES)}, got {bad[0]!r}")
    lower, upper = box_bounds(p["box"])
    if len(lower) != 3:
        raise ConfigError(f"params.box must be a 3D box [x0, y0, z0, x1, y1, z1], got {p['box']!r}")
    for key in ("centers", "velocities"):
        if any(not isinstance(c, (list, tuple)) or len(c) != 3 for c in p[key]):
            raise ConfigError(f"params.{key} entries must be 3D vectors [x, y, z], got {p[key]!r}")
    for r, c in zip(p["radii"], p["centers"], strict=True):
        if not r > 0 or np.any(np.asarray(c) - r < lower) or np.any(np.asarray(c) + r > upper):
            raise ConfigError(f"params.centers: body of radius {r} at {c} is not inside params.box {p['box']}")
    return p


def body(shape: str, radius: float, size: float, center) -> Mesh:
    """A sphere of ``radius``, or the cube inscribed in it, centred at ``center``."""
    if shape == "cube":
        half = radius / math.sqrt(3.0)
        return shapes.box((2 * half,) * 3, size, origin=np.asarray(center, float) - half)
    return shapes.sphere(radius, size, center=center)


def build(p: dict) -> Scene:
    meshes = [body(s, r, p["body_size"], c) for s, r, c in zip(p["shapes"], p["radii"], p["centers"], strict=True)]
    merged, body_id = merge_bodies(meshes)
    v = np.asarray(p["velocities"], float)[body_id]
    return contained_bodies(box_domain(*box_bounds(p["box"]), p["mesh_size"]), merged, v, p, body_id)
