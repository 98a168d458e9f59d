"""What a scene builds, the error for bad scene parameters, and particle seeding helpers."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .. import shapes
from ..config import ConfigError, reject_unknown
from ..mesh import Mesh
from ..mpm.boundary import Clamp, Wall
from ..mpm.materials import MATERIALS, Material

__all__ = [
    "Scene", "check_params", "make_material", "lattice", "lattice_mesh", "lattice_cells",
    "chain_mesh", "line_mesh", "vertex_volumes", "nearest", "contained_bodies", "merge_bodies", "outline",
    "box_bounds", "box_domain",
]


@dataclass
class Scene:
    """A scene ready to simulate.

    domain: the physical background mesh; walls act on its boundary. body: the tracked
    material points (its vertices) and their connectivity, the graph a model learns.
    x, v: (P, d) particles; volume: (P,) rest volumes; materials: (material, particle ids or
    None = all); tracked: (N,) the particle index of each body vertex; walls, clamps:
    boundary conditions; gravity: (d,); probes: name -> particle index whose stress is
    recorded; grid_spacing: default grid spacing of the structured B-spline solver.
    node_type: (N,) datagen.trajectory.NodeType codes of the body vertices (None: all free);
    body_id: (N,) body of each vertex (None: one body); obstacle_nodes (M, d) and
    obstacle_facets (F, d): wall/container geometry a model can see (None: none).
    initial_F: (P, d, d) or (d, d) deformation gradient at t = 0 (None: the identity).
    colliders: moving rigid obstacles (:class:`~datagen.mpm.colliders.Collider`) acting on the
    background nodes; each one's surface is the last ``collider_nodes[k]`` obstacle nodes, moved
    with it (:meth:`obstacle_positions`). damping: mass-proportional damping rate (1/s) of the
    nodal velocities. settle: (seconds, damping) of a pre-roll before frame 0 in which the body
    comes to rest under gravity (:func:`datagen.simulation.settle`), or None.
    frame_diagnostics: (simulation, state) -> name -> array, extra per-frame diagnostics
    (e.g. a slope's run-out); the simulation is a datagen.simulation.Simulation.
    given_cells: where the body is a given mesh refined (the press scene's ``refine``), that mesh's
    cells; its nodes are the body's first ones (None: the body is the mesh as given or built).
    """

    domain: Mesh
    body: Mesh
    x: np.ndarray
    v: np.ndarray
    volume: np.ndarray
    materials: list[tuple[Material, np.ndarray | None]]
    tracked: np.ndarray
    walls: list[Wall] = field(default_factory=list)
    clamps: list[Clamp] = field(default_factory=list)
    gravity: np.ndarray | None = None
    probes: dict[str, int] = field(default_factory=dict)
    grid_spacing: float | None = None
    node_type: np.ndarray | None = None
    body_id: np.ndarray | None = None
    obstacle_nodes: np.ndarray | None = None
    obstacle_facets: np.ndarray | None = None
    initial_F: np.ndarray | None = None
    frame_diagnostics: Callable | None = None
    colliders: list = field(default_factory=list)
    collider_nodes: list = field(default_factory=list)
    damping: float = 0.0
    settle: tuple[float, float] | None = None
    given_cells: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return self.x.shape[1]

    def obstacle_positions(self, times) -> np.ndarray | None:
        """(T, M, d) obstacle node positions at ``times`` (the colliders' surfaces moved along their
        paths, the static walls where they are); None when no obstacle moves."""
        if not self.colliders or self.obstacle_nodes is None:
            return None
        times = np.asarray(times, float).reshape(-1)
        out = np.broadcast_to(self.obstacle_nodes, (len(times), *self.obstacle_nodes.shape)).copy()
        end = len(self.obstacle_nodes)
        for collider, count in reversed(list(zip(self.colliders, self.collider_nodes, strict=True))):
            start = end - count
            shift = np.stack([collider.path.position(t) - collider.path.points[0] for t in times])
            out[:, start:end] += shift[:, None, :]
            end = start
        return out

    def density(self) -> np.ndarray:
        """(P,) rest density of every particle."""
        rho = np.zeros(len(self.x))
        for material, ids in self.materials:
            rho[slice(None) if ids is None else ids] = material.density
        return rho


def _type_name(value) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
            list: "a list", tuple: "a list"}.get(type(value), type(value).__name__)


def check_params(scene: str, defaults: dict, given: dict, *, positive=(), choices=None) -> dict:
    """Merge ``given`` over ``defaults``; unknown keys, wrong types, non-positive or
    out-of-choice values raise ConfigError naming ``params.<key>``."""
    if not isinstance(given, dict):
        raise ConfigError(f"params must be a mapping of {scene} parameters, got {type(given).__name__}")
    reject_unknown(given, defaults, prefix="params", where=f"scene {scene!r}")
    out = dict(defaults)
    for key, value in given.items():
        default = defaults[key]
        ok = (isinstance(value, bool) == isinstance(default, bool)) and (
            isinstance(value, type(default)) or (isinstance(default, float) and isinstance(value, int))
            or (isinstance(default, (list, tuple)) and isinstance(value, (list, tuple))))
        if not ok:
            raise ConfigError(f"params.{key} must be {_type_name(default)} (like {default!r}), got {value!r}")
        out[key] = float(value) if isinstance(default, float) else value
    for key in positive:
        if not out[key] > 0:
            raise ConfigError(f"params.{key} must be positive, got {out[key]!r}")
    for key, allowed in (choices or {}).items():
        if out[key] not in allowed:
            raise ConfigError(f"params.{key} must be one of {sorted(allowed)}, got {out[key]!r}")
    return out


def make_material(name: str, E: float, nu: float, density: float) -> Material:
    try:
        return MATERIALS[name](E, nu, density)
    except ValueError as exc:
        raise ConfigError(f"bad material parameters: {exc}") from None


def lattice(lower, upper, spacing: float) -> tuple[np.ndarray, tuple[int, ...], np.ndarray]:
    """Cell-centred particles filling the box [lower, upper] with about ``spacing`` between them.

    Returns points (P, d) in C order, the count per axis, and the exact spacing per axis.
    """
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    counts = np.maximum(np.round((upper - lower) / spacing).astype(int), 1)
    step = (upper - lower) / counts
    axes = [lower[k] + (np.arange(n) + 0.5) * step[k] for k, n in enumerate(counts)]
    points = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    return points, tuple(int(c) for c in counts), step


def lattice_mesh(points: np.ndarray, counts: tuple[int, ...]) -> Mesh:
    """Structured simplices over lattice points in C order: a chain in 1D, two triangles per quad in
    2D, six tetrahedra around the main diagonal of every cube in 3D."""
    if len(counts) == 1:
        return chain_mesh(points)
    return Mesh.from_arrays(points, lattice_cells(counts), orient=True)


def lattice_cells(counts: tuple[int, ...]) -> np.ndarray:
    """(C, d+1) the simplices of :func:`lattice_mesh` over a 2D or 3D lattice of ``counts`` points."""
    if len(counts) not in (2, 3):
        raise ValueError("lattice_mesh supports 1D, 2D and 3D lattices")
    idx = np.arange(int(np.prod(counts))).reshape(counts)
    if len(counts) == 2:
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    def corner(o):  # noqa: E306 - the lattice index of corner offset o of every cube
        return idx[o[0]:counts[0] - 1 + o[0], o[1]:counts[1] - 1 + o[1], o[2]:counts[2] - 1 + o[2]].ravel()
    cells = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):  # Kuhn's six tetrahedra
        path, o = [corner((0, 0, 0))], [0, 0, 0]
        for axis in perm:
            o[axis] = 1
            path.append(corner(tuple(o)))
        cells.append(np.stack(path, 1))
    return np.concatenate(cells)


def chain_mesh(points: np.ndarray) -> Mesh:
    """1D segments joining consecutive points (sorted along the line)."""
    n = len(points)
    return Mesh(points, np.stack([np.arange(n - 1), np.arange(1, n)], axis=1))


def line_mesh(start: float, stop: float, n_cells: int) -> Mesh:
    """Uniform 1D mesh of ``n_cells`` segments on [start, stop]."""
    return chain_mesh(np.linspace(start, stop, n_cells + 1)[:, None])


def vertex_volumes(mesh: Mesh) -> np.ndarray:
    """(N,) lumped volumes: each cell's measure shared equally among its d+1 vertices."""
    vol = np.zeros(mesh.n_nodes)
    np.add.at(vol, mesh.cells.ravel(), np.repeat(mesh.cell_measures / (mesh.dim + 1), mesh.dim + 1))
    return vol


def nearest(points: np.ndarray, target) -> int:
    """Index of the point closest to ``target``."""
    return int(np.argmin(np.linalg.norm(points - np.asarray(target, float), axis=1)))


def merge_bodies(meshes: list[Mesh]) -> tuple[Mesh, np.ndarray]:
    """One mesh from several bodies, and (N,) the body id of each of its nodes."""
    offsets = np.cumsum([0] + [m.n_nodes for m in meshes[:-1]])
    nodes = np.concatenate([m.nodes for m in meshes])
    cells = np.concatenate([m.cells + o for m, o in zip(meshes, offsets, strict=True)])
    body_id = np.concatenate([np.full(m.n_nodes, k) for k, m in enumerate(meshes)])
    return Mesh(nodes, cells), body_id


def outline(domain: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The boundary of ``domain`` as obstacle geometry: nodes (M, d) and facets (F, d) into them."""
    facets = domain.boundary_facets
    used, inverse = np.unique(facets.ravel(), return_inverse=True)
    return domain.nodes[used], inverse.reshape(facets.shape).astype(np.int64)


def box_bounds(box, key: str = "params.box") -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners of a 2D ``[x0, y0, x1, y1]`` or 3D ``[x0, y0, z0, x1, y1, z1]`` box."""
    ok = isinstance(box, (list, tuple)) and len(box) in (4, 6) and all(
        isinstance(b, (int, float)) and not isinstance(b, bool) and np.isfinite(b) for b in box)
    if not ok:
        raise ConfigError(f"{key} must be [x0, y0, x1, y1] (2D) or [x0, y0, z0, x1, y1, z1] (3D), got {box!r}")
    d = len(box) // 2
    lower, upper = np.asarray(box[:d], float), np.asarray(box[d:], float)
    if np.any(upper <= lower):
        raise ConfigError(f"{key} must have its upper corner above its lower corner on every axis, got {box!r}")
    return lower, upper


def box_domain(lower, upper, mesh_size: float) -> Mesh:
    """The background mesh of the box [lower, upper]: triangles in 2D, tetrahedra in 3D."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if len(lower) == 2:
        return shapes.rectangle(*(upper - lower), mesh_size, origin=lower)
    return shapes.box(upper - lower, mesh_size, origin=lower)


def contained_bodies(domain: Mesh, body: Mesh, v: np.ndarray, p: dict, body_id: np.ndarray | None = None) -> Scene:
    """Elastic bodies falling inside ``domain`` (2D or 3D) whose whole boundary is a separating wall.

    p: the scene parameters ``material``, ``E``, ``nu``, ``density``, ``friction``, ``gravity``
    and ``mesh_size``. Gravity points along -y in 2D and 3D alike (y is up). The walls are
    also stored as obstacle geometry a model can see: boundary segments in 2D, triangles in 3D.
    """
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    obstacle_nodes, obstacle_facets = outline(domain)
    gravity = np.zeros(domain.dim)
    gravity[1] = -p["gravity"]
    return Scene(
        domain=domain, body=body, x=body.nodes.copy(), v=v, volume=vertex_volumes(body),
        materials=[(material, None)], tracked=np.arange(body.n_nodes),
        walls=[Wall("separating", lambda c, n: np.ones(len(c), bool), p["friction"])],
        gravity=gravity, grid_spacing=p["mesh_size"], body_id=body_id,
        obstacle_nodes=obstacle_nodes, obstacle_facets=obstacle_facets,
    )
