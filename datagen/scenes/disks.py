"""Elastic disks colliding inside a box (UMLS §3.2 generalised).

Any number of triangulated disks with their own radii, centres and initial velocities; the
box is the background mesh and its boundary a separating wall (the container a model sees
as obstacle nodes). Optional gravity along -y.
"""

from __future__ import annotations

import numpy as np

from .. import shapes
from ..config import ConfigError
from .base import Scene, check_params, contained_bodies, merge_bodies

NAME = "disks"
DEFAULTS = {
    "radii": [0.2, 0.2], "centers": [[0.3, 0.3], [0.7, 0.7]], "velocities": [[0.1, 0.1], [-0.1, -0.1]],
    "box": [0.0, 0.0, 1.0, 1.0], "E": 1000.0, "nu": 0.3, "density": 1000.0, "gravity": 0.0,
    "body_size": 0.04, "mesh_size": 0.05, "friction": 0.0, "material": "neo_hookean",
}
OUTPUT = {"frames": 40, "frame_interval": 0.1}
SOLVER = {"transfer": "flip"}


def params(given: dict) -> dict:
    p = check_params(NAME, DEFAULTS, given, positive=("E", "density", "body_size", "mesh_size"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"}})
    n = len(p["radii"])
    if n == 0 or len(p["centers"]) != n or len(p["velocities"]) != n:
        raise ConfigError("params.radii, params.centers and params.velocities must list the same number "
                          f"(at least one) of disks, got {n}, {len(p['centers'])}, {len(p['velocities'])}")
    lo, hi = np.asarray(p["box"][:2], float), np.asarray(p["box"][2:], float)
    for r, c in zip(p["radii"], p["centers"], strict=True):
        if r <= 0 or np.any(np.asarray(c) - r < lo) or np.any(np.asarray(c) + r > hi):
            raise ConfigError(f"params.centers: disk of radius {r} at {c} is not inside params.box {p['box']}")
    return p


def build(p: dict) -> Scene:
    meshes = [shapes.disk(r, p["body_size"], center=c) for r, c in zip(p["radii"], p["centers"], strict=True)]
    body, body_id = merge_bodies(meshes)
    v = np.asarray(p["velocities"], float)[body_id]
    lo, hi = np.asarray(p["box"][:2], float), np.asarray(p["box"][2:], float)
    domain = shapes.rectangle(*(hi - lo), p["mesh_size"], origin=lo)
    return contained_bodies(domain, body, v, p, body_id)
