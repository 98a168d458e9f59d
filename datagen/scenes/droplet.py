"""Falling droplet (A-ULMPM §6.1.2): a weakly compressible fluid disk drops and splashes.

A disk of fluid (:class:`datagen.mpm.materials.WeaklyCompressibleFluid`, Tait equation of
state, optional viscosity) of ``radius`` starts at ``height`` above the floor of a box with
separating walls and falls under gravity. On impact it spreads and splashes. Eulerian MPM
follows the free surface; total-Lagrangian MPM keeps the initial particle neighbourhoods and
cannot; the adaptive reference configuration rebuilds only when volumes change (none during
the free fall). The body mesh is a triangulated disk whose vertices are the particles. The
defaults are the settings of tests/test_reference_modes.py.
"""

from __future__ import annotations

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mpm.boundary import Wall
from ..mpm.materials import WeaklyCompressibleFluid
from .base import Scene, check_params, outline, vertex_volumes

NAME = "droplet"
DEFAULTS = {
    "radius": 0.15, "height": 0.3, "box": [1.0, 1.0], "mesh_size": 0.04, "body_size": 0.02,
    "bulk": 400.0, "gamma": 7.0, "viscosity": 0.0, "density": 1.0, "gravity": 9.81, "friction": 0.0,
}
OUTPUT = {"frames": 14, "frame_interval": 0.03}  # impact at ~0.17 s, then the splash
# One body: the contact trigger could only fire on the splash's own fragments flying apart (its
# bound is conservative; over these 0.42 s it does not fire: 56 rebuilds with or without it, and in
# a 0.6 s run from height 0.45 it took 96 -> 410 rebuilds for the same result).
# cfl 0.4 (default 0.3): fewer steps for the CPU tests; all three modes are stable there.
SOLVER = {"transfer": "apic", "contact_margin": None, "cfl": 0.4}


def params(given: dict) -> dict:
    p = check_params(NAME, DEFAULTS, given,
                     positive=("radius", "height", "mesh_size", "body_size", "bulk", "gamma", "density"))
    for key in ("viscosity", "gravity", "friction"):
        if p[key] < 0:
            raise ConfigError(f"params.{key} must be >= 0, got {p[key]!r}")
    if p["gamma"] < 1:
        raise ConfigError(f"params.gamma must be >= 1, got {p['gamma']!r}")
    width, tall = p["box"]
    if not (2 * p["radius"] < width and p["height"] + p["radius"] < tall and p["height"] > p["radius"]):
        raise ConfigError("params.radius and params.height must place the droplet inside params.box above the floor")
    return p


def fluid(p: dict) -> WeaklyCompressibleFluid:
    # E, nu = 0 give the bulk modulus K = E / 3: E = 3 K
    return WeaklyCompressibleFluid(3.0 * p["bulk"], 0.0, p["density"], gamma=p["gamma"], fluid_viscosity=p["viscosity"])


def build(p: dict) -> Scene:
    width, tall = p["box"]
    center = (width / 2, p["height"])
    body = shapes.disk(p["radius"], p["body_size"], center=center)
    domain = shapes.rectangle(width, tall, p["mesh_size"])
    obstacle_nodes, obstacle_facets = outline(domain)
    return Scene(
        domain=domain, body=body, x=body.nodes.copy(), v=np.zeros_like(body.nodes), volume=vertex_volumes(body),
        materials=[(fluid(p), None)], tracked=np.arange(body.n_nodes),
        walls=[Wall("separating", lambda c, n: np.ones(len(c), bool), p["friction"])],
        gravity=np.array([0.0, -p["gravity"]]), grid_spacing=p["mesh_size"],
        obstacle_nodes=obstacle_nodes, obstacle_facets=obstacle_facets,
    )
