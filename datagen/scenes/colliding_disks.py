"""Two colliding elastic disks (UMLS §3.2).

E = 1000 Pa, nu = 0.3, rho = 1000 kg/m^3, velocities +-(0.1, 0.1) m/s; each disk is a
triangle mesh whose ~462 vertices are the material points (volumes lumped from the cells).
The background is an unstructured triangulation of element size 0.025 m. The disks start at
(0.2, 0.2) and (0.8, 0.8) with radius 0.2 (UMLS Fig. 11); the background box is padded by
``padding`` so the disks do not start on its walls (separating slip walls).
"""

from __future__ import annotations

import numpy as np

from .. import shapes
from ..mesh import Mesh
from ..mpm.boundary import Wall
from .base import Scene, check_params, make_material, nearest, vertex_volumes

NAME = "colliding_disks"
DEFAULTS = {
    "E": 1000.0, "nu": 0.3, "density": 1000.0, "radius": 0.2, "speed": 0.1,
    "centers": [[0.2, 0.2], [0.8, 0.8]], "body_size": 0.0188, "mesh_size": 0.025,
    "box": [0.0, 0.0, 1.0, 1.0], "padding": 0.1, "material": "neo_hookean",
}
OUTPUT = {"frames": 40, "frame_interval": 0.1}
SOLVER = {"transfer": "flip"}


def params(given: dict) -> dict:
    return check_params(
        NAME, DEFAULTS, given,
        positive=("E", "density", "radius", "body_size", "mesh_size"),
        choices={"material": {"linear", "neo_hookean", "fixed_corotated"}},
    )


def _merge(meshes: list[Mesh]) -> Mesh:
    nodes = np.concatenate([m.nodes for m in meshes])
    offsets = np.cumsum([0] + [m.n_nodes for m in meshes[:-1]])
    return Mesh(nodes, np.concatenate([m.cells + o for m, o in zip(meshes, offsets, strict=True)]))


def build(p: dict) -> Scene:
    centers = np.asarray(p["centers"], float)
    disks = [shapes.disk(p["radius"], p["body_size"], center=c) for c in centers]
    body = _merge(disks)
    x = body.nodes.copy()
    v = np.zeros_like(x)
    first = np.arange(len(x)) < disks[0].n_nodes
    v[first] = p["speed"]
    v[~first] = -p["speed"]
    lo, hi = np.asarray(p["box"][:2], float) - p["padding"], np.asarray(p["box"][2:], float) + p["padding"]
    domain = shapes.rectangle(*(hi - lo), p["mesh_size"], origin=lo)
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    return Scene(
        domain=domain, body=body, x=x, v=v, volume=vertex_volumes(body), materials=[(material, None)],
        tracked=np.arange(len(x)), walls=[Wall("separating", lambda c, n: np.ones(len(c), bool))],
        gravity=np.zeros(2), probes={"left_center": nearest(x, centers[0])}, grid_spacing=p["mesh_size"],
    )

