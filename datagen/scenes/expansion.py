"""An elastic body expanding inside a spherical container (thesis §2.3.5, UMLS §3.6).

The container is the ball of radius ``radius`` (0.5 m) centred at the origin, tetrahedralised at
``mesh_size``: the background mesh conforms to the curved wall. The body (``mesh``: any meshio
tetrahedral file; empty: a stella octangula, two interpenetrating tetrahedra, all sharp tips and
re-entrant edges) is centred at the origin and scaled so that its farthest vertex is ``extent``
times the radius away at rest; it starts compressed, F = ``compression`` I (0.75), positions
scaled about the centre, at rest, and is released. Neo-Hookean, E = 3.3 MPa, nu = 0.49.

Contact with the wall: separating contact with Coulomb friction (mu = ``friction``, 0.5) on the
conforming boundary, the solver's node condition (:class:`~datagen.mpm.boundary.SeparatingSlip`
on the boundary nodes and their extra-layer copies, with the outward normals of the sphere's
facets): a node may leave the wall freely but never move into it, and its tangential velocity
is cut by mu times the normal velocity removed. We use it rather than a barrier because the mesh
conforms to the wall: the wall is where the nodes are, the condition is exact there (no
penalty or barrier stiffness, no time-step limit of its own, no distance parameter d_hat), and
it only ever removes kinetic energy. Its cost: the wall nodes are in the kernel support of
particles up to ~1 h inside, so the body is stopped about a cell short of the wall (at h = 0.1 the
farthest particle reaches 0.413 m of 0.5; tests/test_expansion.py checks distance <= 0.5 m, i.e.
tolerance 0). Energy falls frame to frame; within a frame the explicit step's energy error moves
it up to ~4% of the initial energy during the violent first expansion.

Per-frame diagnostics: ``contact_force`` (N, the magnitude of the total force the wall exerts
on the body: sum over nodes of m_i (v_constrained - v_free) / dt, recomputed at the frame's state)
and ``distance_max`` (m, the largest particle distance from the centre). Gravity (``gravity``,
along -y) makes the body settle at the bottom of the container.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from .. import shapes
from ..config import ConfigError
from ..mesh import Mesh, MeshError
from ..mpm.boundary import Wall
from ..mpm.contact import wall_force
from .base import Scene, check_params, make_material, outline, vertex_volumes

NAME = "expansion"
DEFAULTS = {
    "mesh": "", "radius": 0.5, "extent": 0.9, "compression": 0.75, "E": 3.3e6, "nu": 0.49, "density": 1000.0,
    "friction": 0.5, "gravity": 9.81, "mesh_size": 0.05, "body_size": 0.05, "material": "neo_hookean",
}
OUTPUT = {"frames": 40, "frame_interval": 0.01}
SOLVER = {"transfer": "apic"}


def params(given: dict) -> dict:
    p = check_params(NAME, DEFAULTS, given, positive=("radius", "E", "density", "mesh_size", "body_size"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"}})
    for key in ("extent", "compression"):
        if not 0.0 < p[key] <= 1.0:
            raise ConfigError(f"params.{key} must be in (0, 1], got {p[key]!r}")
    if not (p["friction"] >= 0 and p["gravity"] >= 0):
        raise ConfigError("params.friction and params.gravity must be >= 0")
    if p["mesh"]:
        body_mesh(p)  # a bad file is named now, not after meshing the container
    return p


@functools.lru_cache(maxsize=8)
def _read(path: str, mtime_ns: int) -> Mesh:
    return Mesh.read(path)


def body_mesh(p: dict) -> Mesh:
    """The body at rest, centred (vertex-volume centroid) at the origin, farthest vertex at extent * radius."""
    reach = p["extent"] * p["radius"]
    if not p["mesh"]:
        return shapes.star(reach, p["body_size"])
    path = Path(p["mesh"])
    try:
        mesh = _read(str(path.resolve()), path.stat().st_mtime_ns)
    except (OSError, MeshError) as exc:
        raise ConfigError(f"params.mesh: cannot read a tetrahedral mesh from {p['mesh']!r}: {exc}") from None
    if mesh.dim != 3:
        raise ConfigError(f"params.mesh must be a tetrahedral (3D) mesh, {p['mesh']!r} is {mesh.dim}D")
    w = vertex_volumes(mesh)
    nodes = mesh.nodes - (w[:, None] * mesh.nodes).sum(0) / w.sum()
    return Mesh(nodes * (reach / np.linalg.norm(nodes, axis=1).max()), mesh.cells)


def build(p: dict) -> Scene:
    rest = body_mesh(p)
    c = p["compression"]
    body = Mesh(rest.nodes * c, rest.cells)  # positions at t = 0; F = c I
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    domain = shapes.sphere(p["radius"], p["mesh_size"])
    obstacle_nodes, obstacle_facets = outline(domain)

    def frame_diagnostics(sim, state) -> dict:
        force = wall_force(sim.model, state, sim.dt)
        return {"contact_force": force.norm(), "distance_max": state.x.norm(dim=1).max()}

    return Scene(
        domain=domain, body=body, x=body.nodes.copy(), v=np.zeros_like(body.nodes), volume=vertex_volumes(rest),
        materials=[(material, None)], tracked=np.arange(body.n_nodes),
        walls=[Wall("separating", lambda c_, n: np.ones(len(c_), bool), p["friction"])],
        gravity=np.array([0.0, -p["gravity"], 0.0]), grid_spacing=p["mesh_size"],
        obstacle_nodes=obstacle_nodes, obstacle_facets=obstacle_facets, initial_F=c * np.eye(3),
        frame_diagnostics=frame_diagnostics,
    )
