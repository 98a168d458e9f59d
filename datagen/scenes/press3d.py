"""A stiff elastic solid held at its base, pressed by a moving rigid indenter and released (3D).

The 3D counterpart of :mod:`datagen.scenes.press`; y is up, gravity along -y. The body
(``body``, meshed by :mod:`datagen.shapes3d` as tetrahedra, :mod:`datagen.scenes.solids`):

- ``extrusion``: a profile in the x-y plane -- a letter (``char``) or a polygon (``polygon``, its
  vertices, with optional ``holes``) -- scaled so that its largest extent is ``size``, turned onto
  its most stable side where it would topple (``pose: stable``, as the 2D press does), and
  extruded along z by ``depth`` x ``size``;
- ``block``: a block of ``block`` x ``size`` (x, y, z lengths) with a round through hole of radius
  ``hole`` x ``size`` (``feature: hole``) or a round-ended through slot ``slot`` x ``size`` (width,
  length; ``feature: slot``) along axis ``feature_axis`` (0 x, 1 y, 2 z), or none (``feature: none``);
- ``cylinder``: a round bar standing along y, ``cylinder`` x ``size`` (diameter, height);
- ``mesh``: any tetrahedral mesh (``mesh``: a file path or an inline ``{nodes, cells}``; a part for
  zero-shot use, :func:`datagen.families.press3d.place`), kept as given where it stands with y up
  and otherwise turned onto the face of its convex hull nearest its centre of mass (``pose:
  stable``, :func:`datagen.scenes.solids.rest_pose`), scaled so that its largest extent is ``size``;
  with ``refine`` subdivided (each tetrahedron into eight, its own nodes first: :mod:`datagen.refine`)
  until its median edge is at most sqrt(2) times the spacing a body of its volume meshed to ``nodes``
  nodes has, the resolution of the scene's own bodies.

The other bodies are meshed to about ``nodes`` nodes (:func:`datagen.shapes3d.with_nodes`). Each is
set on the floor in the middle of the box ``[x0, y0, z0, x1, y1, z1]`` (``lift`` above it), and held there:
``base: bonded`` (the floor is sticky: the base is glued to it, so that what the indenter makes is
deformation), ``resting`` (separating contact with ``friction``) or ``clamped`` (set against the
box's sticky left wall, centred in height). The background mesh has spacing ``mesh_size``.

The indenter (``indenter``: ``sphere``, size [radius]; ``box``, a flat punch of half extents
[hx, hy, hz]; ``bar``, a square bar of half extents [hx, hy] lying across the body along z, as long
as the body is deep and ``bar_overhang`` x ``size`` more at each end -- the solver has no cylinder
collider, so a bar stands in for a roller lying across) starts with its underside ``gap`` above
the body where they come closest (vertically), its centre at (``indenter_x``, ``indenter_z``) from
the body's middle, moves for ``press_time`` at ``speed`` along a line tilted ``angle`` degrees from
straight down towards azimuth ``azimuth`` (degrees from +x towards +z), waits ``hold_time`` and
goes back. It acts on the background nodes as separating contact with Coulomb friction
``indenter_friction`` (:mod:`datagen.mpm.colliders`); its surface, moved along its path, is
obstacle geometry a model sees, next to the box's walls. The contact acts about a background cell
before the surfaces meet (a node inside the indenter that carries the body's mass is stopped): a
``gap`` under a cell leaves the returned indenter holding the body down (docs/press3d.md).
``settle_time``, ``settle_damping`` and ``damping`` as in the 2D press. ``kind``: a label naming the
kind of body (the family's draw records it; the build does not use it).
"""

from __future__ import annotations

import math

import numpy as np

from ..config import ConfigError
from ..mesh import Mesh
from ..mpm.colliders import Collider, Path
from ..refine import refine_to
from ..shapes3d import NODES_PER_VOLUME
from .base import Scene, box_bounds, box_domain, check_params, make_material, outline, vertex_volumes
from .press import walls
from .solids import BODIES, FEATURES, body_mesh

NAME = "press3d"
QUASI_STATIC = True  # the drive is slow next to the body's waves, as in the 2D press
DEFAULTS = {
    "kind": "", "body": "extrusion", "char": "A", "depth": 0.4, "pose": "stable",
    "block": [1.0, 0.6, 0.5], "feature": "hole", "hole": 0.12, "slot": [0.12, 0.4], "feature_axis": 2,
    "cylinder": [0.6, 1.0], "size": 0.12, "nodes": 2500,
    "box": [0.0, 0.0, 0.0, 0.18, 0.16, 0.18], "lift": 0.0, "base": "bonded",
    "E": 5e7, "nu": 0.35, "density": 1200.0, "gravity": 9.81, "friction": 0.5, "material": "neo_hookean",
    "mesh_size": 0.012, "damping": 0.0, "settle_time": 0.0, "settle_damping": 400.0,
    "indenter": "sphere", "indenter_size": [0.025], "bar_overhang": 0.1, "indenter_x": 0.0, "indenter_z": 0.0,
    "indenter_friction": 0.3, "gap": 0.016, "speed": 0.16, "angle": 0.0, "azimuth": 0.0,
    "press_time": 0.15, "hold_time": 0.0, "refine": False,
}
OUTPUT = {"frames": 30, "frame_interval": 0.01}
SOLVER = {"transfer": "flip"}
INDENTER_SIZES = {"sphere": 1, "box": 3, "bar": 2}
_OPTIONAL = ("polygon", "holes", "mesh")


def params(given: dict) -> dict:
    if not isinstance(given, dict):
        raise ConfigError(f"params must be a mapping of {NAME} parameters, got {type(given).__name__}")
    optional = {k: given.get(k) for k in _OPTIONAL}
    p = check_params(NAME, DEFAULTS, {k: v for k, v in given.items() if k not in _OPTIONAL},
                     positive=("size", "E", "density", "mesh_size", "speed", "press_time", "depth", "nodes"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"}, "body": set(BODIES),
                              "feature": set(FEATURES), "feature_axis": {0, 1, 2},
                              "indenter": set(INDENTER_SIZES), "pose": {"upright", "stable"},
                              "base": {"resting", "bonded", "clamped"}})
    p.update(optional)
    if (p["body"] == "mesh") != (p["mesh"] is not None):
        raise ConfigError("params.mesh gives the body with params.body: mesh, and only then; got params.body "
                          f"{p['body']!r} and {'a' if p['mesh'] is not None else 'no'} params.mesh")
    sizes, want = p["indenter_size"], INDENTER_SIZES[p["indenter"]]
    if len(sizes) != want or not all(isinstance(s, (int, float)) and not isinstance(s, bool) and s > 0
                                     for s in sizes):
        raise ConfigError(f"params.indenter_size must list {want} positive length(s) for a {p['indenter']} "
                          f"indenter, got {sizes!r}")
    for key in ("gap", "lift", "hold_time", "damping", "friction", "indenter_friction", "settle_time",
                "settle_damping", "bar_overhang"):
        if not p[key] >= 0:
            raise ConfigError(f"params.{key} must be >= 0, got {p[key]!r}")
    if not -80.0 <= p["angle"] <= 80.0:
        raise ConfigError(f"params.angle must lie in [-80, 80] degrees from straight down, got {p['angle']!r}")
    if len(box_bounds(p["box"])[0]) != 3:
        raise ConfigError(f"params.box must be a 3D box [x0, y0, z0, x1, y1, z1], got {p['box']!r}")
    return p


def indenter_shape(p: dict, body: Mesh) -> tuple[str, tuple]:
    """The collider shape and half extents of ``indenter`` for ``body`` (a bar is a box as long as
    the body is deep plus ``bar_overhang`` x ``size`` at each end)."""
    sizes = tuple(float(s) for s in p["indenter_size"])
    if p["indenter"] == "bar":
        depth = float(np.ptp(body.nodes[:, 2]))
        return "box", (sizes[0], sizes[1], 0.5 * depth + p["bar_overhang"] * p["size"])
    return p["indenter"], sizes


def underside(shape: str, sizes: tuple, dx: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """Height of the indenter's lower surface above its lowest point at horizontal offsets (dx, dz)
    from its centre, inside its footprint: box 0, sphere r - sqrt(r^2 - dx^2 - dz^2)."""
    if shape == "box":
        return np.zeros_like(dx)
    return sizes[0] - np.sqrt(np.maximum(sizes[0] ** 2 - dx**2 - dz**2, 0.0))


def indenter(p: dict, body: Mesh) -> Collider:
    """The indenter and its path: down along the tilted line for press_time, hold, and back."""
    shape, sizes = indenter_shape(p, body)
    middle = (body.nodes.min(0) + body.nodes.max(0)) / 2
    x, z = float(middle[0] + p["indenter_x"]), float(middle[2] + p["indenter_z"])
    dx, dz = body.nodes[:, 0] - x, body.nodes[:, 2] - z
    if shape == "box":
        under = (np.abs(dx) <= sizes[0]) & (np.abs(dz) <= sizes[2])
    else:
        under = dx**2 + dz**2 <= sizes[0] ** 2
    top = float((body.nodes[under, 1] - underside(shape, sizes, dx[under], dz[under])).max() if under.any()
                else body.nodes[:, 1].max())
    probe = Collider(shape, sizes, Path(np.zeros(1), np.zeros((1, 3))), p["indenter_friction"])
    start = np.array([x, top + p["gap"] - probe.lowest(), z])
    tilt, heading = math.radians(p["angle"]), math.radians(p["azimuth"])
    direction = np.array([math.sin(tilt) * math.cos(heading), -math.cos(tilt), math.sin(tilt) * math.sin(heading)])
    end = start + p["speed"] * p["press_time"] * direction
    t1, t2 = p["press_time"], p["press_time"] + p["hold_time"]
    times = np.array([0.0, t1, t2, t2 + t1]) if p["hold_time"] > 0 else np.array([0.0, t1, 2 * t1])
    points = np.stack([start, end, end, start]) if p["hold_time"] > 0 else np.stack([start, end, start])
    return Collider(shape, sizes, Path(times, points), p["indenter_friction"])


def placed(p: dict, body: Mesh) -> Mesh:
    """``body`` set in the box: centred in x and z on the floor (``lift`` above it), or for a
    ``clamped`` base against the left wall, centred in height and depth."""
    lower, upper = box_bounds(p["box"])
    low, high = body.nodes.min(0), body.nodes.max(0)
    shift = (lower + upper - low - high) / 2
    if p["base"] == "clamped":
        shift[0], shift[1] = lower[0] - low[0], shift[1] + p["lift"]
    else:
        shift[1] = lower[1] + p["lift"] - low[1]
    moved = Mesh(body.nodes + shift, body.cells)
    if np.any(moved.nodes.max(0) > upper + 1e-12) or np.any(moved.nodes.min(0) < lower - 1e-12):
        raise ConfigError(f"params.size: the body spans {np.round(np.ptp(moved.nodes, axis=0), 6).tolist()}, "
                          f"more than params.box {p['box']} holds; make it smaller or the box larger")
    return moved


def refined(p: dict, body: Mesh) -> tuple[Mesh, np.ndarray | None]:
    """A given mesh (``body: mesh``) with ``refine``: ``body`` subdivided (:func:`datagen.refine.refine_to`)
    until its median edge is at most sqrt(2) times the spacing :func:`datagen.shapes3d.with_nodes` first
    meshes a solid of its volume at for ``nodes`` nodes (the resolution of the scene's own bodies), its
    nodes first; and the given mesh's cells where it was subdivided (else None)."""
    if p["body"] != "mesh" or not p["refine"]:
        return body, None
    spacing = (NODES_PER_VOLUME * float(body.cell_measures.sum()) / p["nodes"]) ** (1 / 3)
    fine, times = refine_to(body, spacing)
    return fine, body.cells if times else None


def build(p: dict) -> Scene:
    lower, upper = box_bounds(p["box"])
    body, given_cells = refined(p, body_mesh(p))
    body = placed(p, body)
    collider = indenter(p, body)
    domain = box_domain(lower, upper, p["mesh_size"])
    walls_nodes, walls_facets = outline(domain)
    surface_nodes, surface_facets = collider.surface(p["mesh_size"])
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    return Scene(
        domain=domain, body=body, x=body.nodes.copy(), v=np.zeros_like(body.nodes), volume=vertex_volumes(body),
        materials=[(material, None)], tracked=np.arange(body.n_nodes), walls=walls(p["base"], p["friction"]),
        gravity=np.array([0.0, -p["gravity"], 0.0]), grid_spacing=p["mesh_size"],
        obstacle_nodes=np.concatenate([walls_nodes, surface_nodes]),
        obstacle_facets=np.concatenate([walls_facets, surface_facets + len(walls_nodes)]).astype(np.int64),
        colliders=[collider], collider_nodes=[len(surface_nodes)], damping=float(p["damping"]),
        settle=(p["settle_time"], p["settle_damping"]) if p["settle_time"] > 0 else None, given_cells=given_cells,
    )
