"""Elastic letters dropped into a box.

Each entry of ``chars`` is meshed with ``datagen.shapes.glyph`` at font size ``height`` and
moved so its bounding-box centre sits at the matching entry of ``centers``; it starts with
the matching velocity and falls under gravity onto the floor of the box (a separating wall
with friction, the container a model sees as obstacle nodes).
"""

from __future__ import annotations

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mesh import Mesh
from .base import Scene, check_params, contained_bodies, merge_bodies

NAME = "glyphs"
DEFAULTS = {
    "chars": ["A"], "centers": [[0.5, 0.6]], "velocities": [[0.0, 0.0]], "height": 0.4,
    "box": [0.0, 0.0, 1.0, 1.0], "E": 2000.0, "nu": 0.3, "density": 1000.0, "gravity": 2.0,
    "friction": 0.2, "body_size": 0.03, "mesh_size": 0.05, "material": "neo_hookean",
}
OUTPUT = {"frames": 40, "frame_interval": 0.05}
SOLVER = {"transfer": "flip"}


def params(given: dict) -> dict:
    p = check_params(NAME, DEFAULTS, given, positive=("height", "E", "density", "body_size", "mesh_size"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"}})
    n = len(p["chars"])
    if n == 0 or len(p["centers"]) != n or len(p["velocities"]) != n:
        raise ConfigError("params.chars, params.centers and params.velocities must list the same number "
                          f"(at least one) of letters, got {n}, {len(p['centers'])}, {len(p['velocities'])}")
    bad = [c for c in p["chars"] if not isinstance(c, str) or len(c.strip()) != 1]
    if bad:
        raise ConfigError(f"params.chars must hold single visible characters, got {bad[0]!r}")
    return p


def letter(char: str, height: float, size: float, center) -> Mesh:
    """``char`` meshed and moved so that its bounding-box centre is ``center``."""
    mesh = shapes.glyph(char, size, height=height)
    shift = np.asarray(center, float) - (mesh.nodes.min(0) + mesh.nodes.max(0)) / 2
    return Mesh(mesh.nodes + shift, mesh.cells)


def build(p: dict) -> Scene:
    meshes = [letter(c, p["height"], p["body_size"], x) for c, x in zip(p["chars"], p["centers"], strict=True)]
    body, body_id = merge_bodies(meshes)
    lo, hi = np.asarray(p["box"][:2], float), np.asarray(p["box"][2:], float)
    if np.any(body.nodes < lo) or np.any(body.nodes > hi):
        raise ConfigError(f"params.centers: the letters {p['chars']} of height {p['height']} do not fit "
                          f"inside params.box {p['box']}; move them or make them smaller")
    v = np.asarray(p["velocities"], float)[body_id]
    domain = shapes.rectangle(*(hi - lo), p["mesh_size"], origin=lo)
    return contained_bodies(domain, body, v, p, body_id)
