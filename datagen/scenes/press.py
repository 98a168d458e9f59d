"""An elastic body on a floor, pressed by a moving rigid indenter and released (2D).

The body is a letter (``char``, meshed by ``datagen.shapes.glyph``), a polygon (``polygon``:
its vertices) or any 2D mesh (``mesh``: a file path or an inline ``{nodes, cells}``), scaled so
that its largest bounding-box extent is ``size`` and set on the floor of the box at its middle,
``lift`` above it, meshed at spacing ``body_size`` (finer if it would get fewer than
``min_nodes`` nodes: thin letters stay resolved); a given mesh is kept as it is, or with
``refine`` subdivided to that resolution, its own nodes first (:func:`refined`). The background
mesh has spacing ``mesh_size``, or ``grid_ratio`` times the body's spacing where that is finer
(:func:`grid_spacing`). The material
is stiff (megapascals): the explicit solver then needs
hundreds of substeps per frame, while the motion is slow and smooth -- the setting where a
learned simulator pays (DeepMind's DEFORMINGPLATE is the same kind of scene).

The indenter (``indenter``: ``disk`` (size [radius]), ``box`` (half extents [hx, hy]) or
``wedge`` (apex down, [half width, height])) starts with its underside ``gap`` above the body
where they come closest (vertically), at ``indenter_x`` from the body's centre, moves for
``press_time`` at ``speed`` along a line ``angle`` degrees from straight down, waits
``hold_time`` and goes back the same way at the same speed. It acts on the background nodes
as separating contact with Coulomb friction ``indenter_friction`` (:mod:`datagen.mpm.colliders`);
its surface, moved along its path, is obstacle geometry a model sees, next to the box's walls
(separating, friction ``friction``).
Gravity points along -y. ``settle_time`` (s): a pre-roll with mass-proportional damping
``settle_damping`` (1/s) in which the body comes to rest on the floor under gravity before
frame 0 (the indenter held at its start), so that gravity coming on does not set it ringing;
``damping``: mass-proportional damping (1/s) of the nodal velocities during the frames.
``base``: ``resting`` (the body stands free on the floor: separating contact with friction
``friction``; pushed, it may slide and tip) or ``bonded`` (the floor is a sticky wall: the
body's base is glued to it, so that what the indenter makes is deformation, as in a part
bonded to its support or DeepMind's plate held at its ends) or ``clamped`` (the body is set
against the box's left wall, which is sticky, its bounding box centred in the box's height and
raised by ``lift``: a bracket held at one end and bent by the indenter; the floor and the other
walls are separating with ``friction``).
``pose``: ``upright`` sets the body down as given; ``stable`` (:func:`rest_pose`) keeps it so
where it stands there and otherwise turns it onto the side it rests on most stably, so that no
body starts out toppling (a J on its hook, a polygon on a corner).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import ConvexHull

from .. import shapes
from ..config import ConfigError
from ..holes import signed_area
from ..mesh import Mesh
from ..mpm.boundary import Wall
from ..mpm.colliders import Collider, Path
from ..refine import refine_to
from .base import Scene, box_bounds, box_domain, check_params, make_material, outline, vertex_volumes
from .bodies import place_body, read_body

NAME = "press"
# The drive (an indenter at a few cm/s, damped frames) is slow next to the body's waves: an engineer
# would run this load with mass scaling (bsms.rollouts.solver_runs, settings mass_scaling_S).
QUASI_STATIC = True
DEFAULTS = {
    "char": "A", "polygon": None, "mesh": None, "size": 0.12, "box": [0.0, 0.0, 0.24, 0.2], "lift": 0.0,
    "E": 5e6, "nu": 0.4, "density": 1200.0, "gravity": 9.81, "friction": 0.5, "material": "neo_hookean",
    "body_size": 0.0025, "min_nodes": 0, "mesh_size": 0.0075, "damping": 0.0, "settle_time": 0.0,
    "settle_damping": 400.0,
    "indenter": "disk", "indenter_size": [0.02], "indenter_x": 0.0, "indenter_friction": 0.3, "gap": 0.002,
    "speed": 0.045, "angle": 0.0, "press_time": 0.2, "hold_time": 0.0, "pose": "upright", "base": "resting",
    "refine": False, "grid_ratio": 0.0,
}
OUTPUT = {"frames": 40, "frame_interval": 0.01}
SOLVER = {"transfer": "flip"}
INDENTER_SIZES = {"disk": 1, "box": 2, "wedge": 2}
_OPTIONAL = ("polygon", "mesh")
# pose "stable": a body stays upright when its base (nodes within BASE_TOL x its size of its
# lowest point) spans at least MIN_BASE x its size and its centre of mass lies over the middle
# (1 - 2 COM_MARGIN) of the base
BASE_TOL, MIN_BASE, COM_MARGIN = 0.02, 0.25, 0.2


def params(given: dict) -> dict:
    if not isinstance(given, dict):
        raise ConfigError(f"params must be a mapping of {NAME} parameters, got {type(given).__name__}")
    optional = {k: given[k] for k in _OPTIONAL if k in given}
    p = check_params(NAME, DEFAULTS, {k: v for k, v in given.items() if k not in optional},
                     positive=("size", "E", "density", "body_size", "mesh_size", "speed", "press_time"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"},
                              "indenter": set(INDENTER_SIZES), "pose": {"upright", "stable"},
                              "base": {"resting", "bonded", "clamped"}})
    p.update(optional)
    if p["polygon"] is not None and p["mesh"] is not None:
        raise ConfigError("params.polygon and params.mesh both give the body; give one of them (or params.char)")
    if p["polygon"] is None and p["mesh"] is None and (not isinstance(p["char"], str) or len(p["char"].strip()) != 1):
        raise ConfigError(f"params.char must be a single visible character, got {p['char']!r}")
    sizes = p["indenter_size"]
    want = INDENTER_SIZES[p["indenter"]]
    if len(sizes) != want or not all(isinstance(s, (int, float)) and not isinstance(s, bool) and s > 0
                                     for s in sizes):
        raise ConfigError(f"params.indenter_size must list {want} positive length(s) for a {p['indenter']} "
                          f"indenter, got {sizes!r}")
    for key in ("gap", "lift", "hold_time", "damping", "friction", "indenter_friction", "min_nodes", "settle_time",
                "settle_damping", "grid_ratio"):
        if not p[key] >= 0:
            raise ConfigError(f"params.{key} must be >= 0, got {p[key]!r}")
    if not -80.0 <= p["angle"] <= 80.0:
        raise ConfigError(f"params.angle must lie in [-80, 80] degrees from straight down, got {p['angle']!r}")
    box_bounds(p["box"])
    if len(p["box"]) != 4:
        raise ConfigError(f"params.box must be a 2D box [x0, y0, x1, y1] (the press scene is 2D), got {p['box']!r}")
    return p


def body_mesh(p: dict) -> Mesh:
    """The body, scaled to ``size`` and centred at the origin (before it is set on the floor)."""
    if p["mesh"] is not None:
        mesh = read_body(p["mesh"], 0)
        if mesh.dim != 2:
            raise ConfigError(f"params.mesh holds a {mesh.dim}D mesh; the {NAME} scene needs a 2D mesh")
    elif p["polygon"] is not None:
        ring = np.asarray(p["polygon"], float)
        if ring.ndim != 2 or ring.shape[1] != 2 or len(ring) < 3 or not np.isfinite(ring).all():
            raise ConfigError(f"params.polygon must list at least 3 [x, y] vertices, got {p['polygon']!r}")
        ring = ring * (p["size"] / float(np.ptp(ring, axis=0).max()))
        mesh = shapes.polygon(ring, size=_spacing(p, abs(signed_area(ring))))
    else:  # a font height that makes the letter's largest extent ``size``
        coarse = shapes.glyph(p["char"], 0.25 * p["size"], height=p["size"])
        scale = p["size"] / float(np.ptp(coarse.nodes, axis=0).max())
        mesh = shapes.glyph(p["char"], _spacing(p, float(coarse.cell_measures.sum()) * scale**2),
                            height=p["size"] * scale)
    return place_body(rest_pose(mesh) if p["pose"] == "stable" else mesh, np.zeros(2), p["size"])


def centre_of_mass(mesh: Mesh) -> np.ndarray:
    """(2,) the centroid of the body's area (uniform density)."""
    centroids = mesh.nodes[mesh.cells].mean(1)
    return mesh.cell_measures @ centroids / mesh.cell_measures.sum()


def stands(mesh: Mesh) -> bool:
    """Whether the body stands as it is on a floor below it: a base at least MIN_BASE of its size
    wide with the centre of mass over the base's middle (module constants)."""
    size = float(np.ptp(mesh.nodes, axis=0).max())
    x, y = mesh.nodes.T
    base = x[y <= y.min() + BASE_TOL * size]
    a, b = float(base.min()), float(base.max())
    c = float(centre_of_mass(mesh)[0])
    return b - a >= MIN_BASE * size and min(c - a, b - c) >= COM_MARGIN * (b - a)


def rest_pose(mesh: Mesh) -> Mesh:
    """The body as it is where it :func:`stands`; otherwise turned about its centre of mass so
    that the edge of its convex hull nearest the centre of mass faces down (the pose with the
    lowest centre of mass over a hull edge: the centre of mass always lies over that edge)."""
    turn = rest_turn(mesh)
    if turn is None:
        return mesh
    c = centre_of_mass(mesh)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    return Mesh((mesh.nodes - c) @ rotation.T + c, mesh.cells)


def rest_turn(mesh: Mesh) -> float | None:
    """The angle (radians, counter-clockwise, about the centre of mass) :func:`rest_pose` turns a 2D
    body by; None where it :func:`stands` as it is."""
    if stands(mesh):
        return None
    c = centre_of_mass(mesh)
    equations = ConvexHull(mesh.nodes).equations  # outward unit normal n and offset d: n.x + d <= 0 inside
    normal = equations[int(np.argmax(equations[:, :2] @ c + equations[:, 2])), :2]
    return -math.pi / 2 - math.atan2(normal[1], normal[0])


def _spacing(p: dict, area: float) -> float:
    """The body's mesh spacing: ``body_size``, or finer where a body of ``area`` would otherwise get
    fewer than ``min_nodes`` nodes (a triangulation of spacing s has about 1.15 area / s^2 nodes)."""
    if p["min_nodes"] <= 0:
        return p["body_size"]
    return min(p["body_size"], math.sqrt(1.15 * area / p["min_nodes"]))


def grid_spacing(p: dict, area: float) -> float:
    """The background mesh's spacing for a body of ``area``: ``mesh_size``, or ``grid_ratio`` times the
    body's own spacing (:func:`_spacing`) where that is finer (``grid_ratio`` 0: always ``mesh_size``).
    A body meshed finer because it is small or thin (``min_nodes``) then gets a grid as much finer, so
    that every body has about as many particles per cell and its contact with the indenter, which the
    solver resolves on the background nodes, is as well resolved across its thickness."""
    if p["grid_ratio"] <= 0:
        return p["mesh_size"]
    return min(p["mesh_size"], p["grid_ratio"] * _spacing(p, area))


def background_spacing(p: dict) -> float:
    """The background mesh's spacing :func:`build` uses for the resolved parameters ``p``."""
    return grid_spacing(p, float(body_mesh(p).cell_measures.sum()))


def indenter(p: dict, body: Mesh) -> Collider:
    """The indenter and its path: down along ``angle`` for press_time, hold, and back."""
    sizes = tuple(float(s) for s in p["indenter_size"])
    half_width = sizes[0]
    center = (body.nodes.min(0) + body.nodes.max(0)) / 2
    x = float(center[0] + p["indenter_x"])
    dx = body.nodes[:, 0] - x
    under = np.abs(dx) <= half_width
    # the lowest point may start as low as the body lets the indenter's underside come, less the gap
    top = float((body.nodes[under, 1] - underside(p["indenter"], sizes, dx[under])).max() if under.any()
                else body.nodes[:, 1].max())
    probe = Collider(p["indenter"], sizes, Path(np.zeros(1), np.zeros((1, 2))), p["indenter_friction"])
    start = np.array([x, top + p["gap"] - probe.lowest()])
    angle = math.radians(p["angle"])
    end = start + p["speed"] * p["press_time"] * np.array([math.sin(angle), -math.cos(angle)])
    t1, t2 = p["press_time"], p["press_time"] + p["hold_time"]
    times = np.array([0.0, t1, t2, t2 + t1]) if p["hold_time"] > 0 else np.array([0.0, t1, 2 * t1])
    points = np.stack([start, end, end, start]) if p["hold_time"] > 0 else np.stack([start, end, start])
    return Collider(p["indenter"], sizes, Path(times, points), p["indenter_friction"])


def underside(shape: str, sizes: tuple, dx: np.ndarray) -> np.ndarray:
    """Height of the indenter's lower surface above its lowest point at horizontal offsets dx
    (|dx| <= its half width) from its centre: box 0, disk r - sqrt(r^2 - dx^2), wedge |dx| h / w."""
    dx = np.abs(np.asarray(dx, float))
    if shape == "box":
        return np.zeros_like(dx)
    if shape == "disk":
        return sizes[0] - np.sqrt(np.maximum(sizes[0] ** 2 - dx**2, 0.0))
    return dx * sizes[1] / sizes[0]


def walls(base: str, friction: float) -> list[Wall]:
    """The box's walls: separating with ``friction`` everywhere, except a sticky floor (outward
    normal -y) under a ``bonded`` base, a sticky left wall (outward normal -x) for a ``clamped`` one."""
    if base == "resting":
        return [Wall("separating", lambda c, n: np.ones(len(c), bool), friction)]
    axis = 1 if base == "bonded" else 0
    return [Wall("sticky", lambda c, n: n[:, axis] < -0.5),
            Wall("separating", lambda c, n: n[:, axis] >= -0.5, friction)]


def refined(p: dict, body: Mesh) -> tuple[Mesh, np.ndarray | None]:
    """A given mesh (``mesh``) with ``refine``: ``body`` subdivided (:func:`datagen.refine.refine_to`)
    until its median edge is at most sqrt(2) times the spacing a polygon of its area would be meshed
    at (``body_size``, finer per ``min_nodes``), the resolution of the family's own bodies, its nodes
    first; and the given mesh's cells where it was subdivided (else None)."""
    if p["mesh"] is None or not p["refine"]:
        return body, None
    fine, times = refine_to(body, _spacing(p, float(body.cell_measures.sum())))
    return fine, body.cells if times else None


def build(p: dict) -> Scene:
    lower, upper = box_bounds(p["box"])
    given = body_mesh(p)
    spacing = grid_spacing(p, float(given.cell_measures.sum()))  # as background_spacing(p) says
    body, given_cells = refined(p, given)
    if p["base"] == "clamped":  # its leftmost points on the left wall, centred in height
        low, high = body.nodes.min(0), body.nodes.max(0)
        shift = np.array([lower[0] - low[0], (lower[1] + upper[1] - low[1] - high[1]) / 2 + p["lift"]])
    else:  # centred on the floor
        shift = np.array([(lower[0] + upper[0]) / 2, lower[1] + p["lift"] - body.nodes[:, 1].min()])
    body = Mesh(body.nodes + shift, body.cells)
    if np.any(body.nodes.max(0) > upper) or np.any(body.nodes.min(0) < lower - 1e-12):
        raise ConfigError(f"params.size: the body spans {np.round(np.ptp(body.nodes, axis=0), 6).tolist()}, "
                          f"more than params.box {p['box']} holds; make it smaller or the box larger")
    collider = indenter(p, body)
    domain = box_domain(lower, upper, spacing)
    walls_nodes, walls_facets = outline(domain)
    surface_nodes, surface_facets = collider.surface(p["body_size"])
    gravity = np.array([0.0, -p["gravity"]])
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    return Scene(
        domain=domain, body=body, x=body.nodes.copy(), v=np.zeros_like(body.nodes), volume=vertex_volumes(body),
        materials=[(material, None)], tracked=np.arange(body.n_nodes),
        walls=walls(p["base"], p["friction"]),
        gravity=gravity, grid_spacing=spacing,
        obstacle_nodes=np.concatenate([walls_nodes, surface_nodes]),
        obstacle_facets=np.concatenate([walls_facets, surface_facets + len(walls_nodes)]).astype(np.int64),
        colliders=[collider], collider_nodes=[len(surface_nodes)], damping=float(p["damping"]),
        settle=(p["settle_time"], p["settle_damping"]) if p["settle_time"] > 0 else None,
        given_cells=given_cells,
    )
