"""Cantilever under its own weight, on a rotated background mesh (UMLS §3.3).

Beam [0, 10] x [0, 2] m, E = 1e5 Pa, nu = 0.29, rho = 2 kg/m^3, g = 9.81 m/s^2, particles on
a uniform lattice. The background is a square large enough to hold the beam and its
deflection at any rotation, rotated by ``rotation`` degrees about the beam's centre (UMLS
Fig. 13) and cut by the wall x = 0, then triangulated (element size 0.5 m). The cut is a
conforming boundary where the beam is clamped (a sticky wall), whatever the rotation; the
rest of the boundary is a separating wall the beam never reaches. The lattice column next to
the wall is marked CLAMPED in the learned graph (it moves with the wall, up to the solver's
small slack) and the wall is its obstacle geometry.
"""

from __future__ import annotations

import math

import numpy as np

from .. import shapes
from ..mesh import Mesh
from ..mpm.boundary import Wall
from ..trajectory import NodeType
from .base import Scene, check_params, lattice, lattice_mesh, make_material, nearest, outline

NAME = "cantilever"
DEFAULTS = {
    "length": 10.0, "height": 2.0, "E": 1e5, "nu": 0.29, "density": 2.0, "gravity": 9.81,
    "mesh_size": 0.5, "particle_spacing": 0.25, "rotation": 0.0, "margin": 1.0, "drop": 4.0,
    "material": "neo_hookean",
}
OUTPUT = {"frames": 60, "frame_interval": 0.05}
SOLVER = {"transfer": "flip"}


def params(given: dict) -> dict:
    return check_params(
        NAME, DEFAULTS, given,
        positive=("length", "height", "E", "density", "mesh_size", "particle_spacing", "margin", "drop"),
        choices={"material": {"linear", "neo_hookean", "fixed_corotated"}},
    )


def _clip_left(ring: np.ndarray) -> np.ndarray:
    """The part x >= 0 of a convex polygon (K, 2) (one Sutherland-Hodgman pass)."""
    out = []
    for a, b in zip(ring, np.roll(ring, -1, axis=0), strict=True):
        if a[0] >= 0:
            out.append(a)
        if (a[0] >= 0) != (b[0] >= 0):
            out.append(a + (b - a) * (a[0] / (a[0] - b[0])))
    return np.array(out)


def background(p: dict) -> Mesh:
    """The rotated square, cut at the wall x = 0, triangulated."""
    lo = np.array([0.0, -p["drop"]])
    hi = np.array([p["length"] + p["margin"], p["height"] + p["margin"]])
    center, half = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    angle = math.radians(p["rotation"])
    corners = [angle + math.pi / 4 + k * math.pi / 2 for k in range(4)]
    square = center + half * math.sqrt(2) * np.array([[math.cos(c), math.sin(c)] for c in corners])
    return shapes.polygon(_clip_left(square), size=p["mesh_size"])


def build(p: dict) -> Scene:
    L, H = p["length"], p["height"]
    x, counts, step = lattice([0.0, 0.0], [L, H], p["particle_spacing"])
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    walls = [
        Wall("separating", lambda c, n: n[:, 0] > -0.999),
        Wall("sticky", lambda c, n: n[:, 0] <= -0.999),  # the cut x = 0 clamps the beam
    ]
    domain = background(p)
    clamp_nodes, clamp_facets = _clamp_wall(domain)
    return Scene(
        domain=domain, body=lattice_mesh(x, counts), x=x, v=np.zeros_like(x),
        volume=np.full(len(x), float(np.prod(step))), materials=[(material, None)],
        tracked=np.arange(len(x)), walls=walls, gravity=np.array([0.0, -p["gravity"]]),
        probes={"tip": nearest(x, [L, H / 2])}, grid_spacing=p["mesh_size"] / 2,
        obstacle_nodes=clamp_nodes, obstacle_facets=clamp_facets,
        node_type=np.where(x[:, 0] < step[0], NodeType.CLAMPED, NodeType.FREE).astype(np.int8),
    )


def _clamp_wall(domain: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The clamping wall x = 0 as obstacle geometry: nodes (M, 2), segments (F, 2)."""
    on_wall = domain.boundary_normals[:, 0] <= -0.999
    nodes, facets = outline(domain)
    used, inverse = np.unique(facets[on_wall].ravel(), return_inverse=True)
    return nodes[used], inverse.reshape(-1, 2).astype(np.int64)
