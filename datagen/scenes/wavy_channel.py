"""An elastic body falling through a wavy channel (UMLS §3.4, UMLS eq. 36).

The channel (``datagen.shapes.wavy_channel``) is the background mesh; its whole boundary is
a separating wall with friction, closed at the bottom. The body (``shape``: ``disk``,
``square``, ``ring``, or ``glyph:<text>`` for the outline of any string, each fitting in a
circle of ``radius``) starts centred in the straight inlet section with ``velocity`` and
falls under gravity.
"""

from __future__ import annotations

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mesh import Mesh
from .base import Scene, check_params, contained_bodies

NAME = "wavy_channel"
DEFAULTS = {
    "amplitude": 0.5, "omega1": 0.6283185307179586, "omega2": 0.15707963267948966, "width": 2.0,
    "length": 10.0, "inlet": 2.5, "outlet": 0.5, "radius": 0.5, "shape": "disk", "velocity": [0.0, 0.0],
    "E": 1e5, "nu": 0.3, "density": 100.0, "gravity": 9.81, "friction": 0.1, "body_size": 0.125,
    "mesh_size": 0.2, "material": "neo_hookean",
}
OUTPUT = {"frames": 50, "frame_interval": 0.04}
SOLVER = {"transfer": "flip"}
BODY_SHAPES = {"disk", "square", "ring"}
GLYPH_PREFIX = "glyph:"


def params(given: dict) -> dict:
    p = check_params(
        NAME, DEFAULTS, given,
        positive=("width", "length", "radius", "E", "density", "body_size", "mesh_size"),
        choices={"material": {"linear", "neo_hookean", "fixed_corotated"}},
    )
    glyph_text = p["shape"].removeprefix(GLYPH_PREFIX).strip()
    if p["shape"] not in BODY_SHAPES and not (p["shape"].startswith(GLYPH_PREFIX) and glyph_text):
        raise ConfigError(f"params.shape must be one of {sorted(BODY_SHAPES)} or 'glyph:<text>' "
                          f"(e.g. 'glyph:B'), got {p['shape']!r}")
    if 2 * p["radius"] >= p["width"] or 2 * p["radius"] >= p["inlet"]:
        raise ConfigError(f"params.radius {p['radius']} does not fit the channel: it needs 2 * radius < "
                          f"params.width ({p['width']}) and < params.inlet ({p['inlet']})")
    return p


def glyph_body(text: str, radius: float, size: float, center) -> Mesh:
    """The outline of ``text`` scaled so that its bounding box fits in 2 * radius, centred at ``center``."""
    extent = np.ptp(shapes.glyph(text, size, height=1.0).nodes, axis=0).max()
    mesh = shapes.glyph(text, size, height=2 * radius / extent)
    middle = (mesh.nodes.min(axis=0) + mesh.nodes.max(axis=0)) / 2
    return Mesh(mesh.nodes - middle + np.asarray(center, float), mesh.cells)


def body_shape(shape: str, radius: float, size: float, center) -> Mesh:
    """The falling body: a disk, a square of half-side ``radius``, a ring or a glyph, centred at ``center``."""
    if shape.startswith(GLYPH_PREFIX):
        return glyph_body(shape.removeprefix(GLYPH_PREFIX).strip(), radius, size, center)
    if shape == "square":
        return shapes.rectangle(2 * radius, 2 * radius, size, origin=np.asarray(center) - radius)
    if shape == "ring":
        return shapes.annulus(0.5 * radius, radius, size, center=center)
    return shapes.disk(radius, size, center=center)


def build(p: dict) -> Scene:
    domain = shapes.wavy_channel(p["amplitude"], p["omega1"], p["omega2"], p["width"], p["length"],
                                 p["mesh_size"], inlet=p["inlet"], outlet=p["outlet"])
    center = [p["width"] / 2, p["length"] + p["inlet"] / 2]
    body = body_shape(p["shape"], p["radius"], p["body_size"], center)
    v = np.tile(np.asarray(p["velocity"], float), (body.n_nodes, 1))
    return contained_bodies(domain, body, v, p)
