"""A stiff plate swinging on a fixed pin through a hole in it, under gravity (2D).

The body is a polygon (``polygon``: its vertices, any units) scaled so that its largest
bounding-box extent is ``size``, with a round hole at ``pivot`` (a point in the polygon's own
units) of radius ``pin_radius + hole_gap``, meshed at spacing ``body_size``. Or a given plate
(``mesh``: a 2D triangle mesh file or an inline ``{nodes, cells}``, one piece with a hole;
``polygon`` unused), scaled the same way and with ``refine`` subdivided to ``body_size`` (its
own nodes first, :func:`datagen.refine.refine_to`): its hole that holds ``pivot`` (a point in
the mesh's own units) takes the pin, the largest disk centred in it with no node of the plate
inside (:func:`datagen.holes.largest_disk`; for a round hole the hole itself) less ``hole_gap``
in radius (``pin_radius`` unused). ``mesh`` and ``refine`` are in the resolved params only where
given (drawn plates resolve as they always have).

The pin is a fixed rigid disk at the origin (:class:`~datagen.mpm.colliders.Collider` on a
path that never moves): it acts on the background nodes as separating contact with Coulomb
friction ``pin_friction``. With the hole as large as the pin (``hole_gap`` 0, the default) every
background node inside the pin that the plate's particles reach may not move into it, and a
rigid turn about the pin's centre moves no node into it: a frictionless revolute joint, free of
any model of one.

The plate starts turned so that the line from the pin to its centre of mass lies ``angle``
degrees counter-clockwise from straight down, turning about the pin at ``spin`` rad/s
(counter-clockwise positive) or, where ``amplitude`` (degrees) is not 0, at the rate that makes a
rigid plate of its mass and inertia turn back at ``amplitude`` (:func:`start_spin`), in the sense
``direction`` (1 counter-clockwise, -1 clockwise), and swings under gravity (-y) from there: a
compound pendulum. The hole's centre sits ``hole_gap`` from the pin's towards the centre of mass,
so a hole larger than the pin starts resting on it. No damping: the swing is the physics. The
background is the square centred on the pin that holds the plate in every orientation with
``room`` to spare, rounded up to whole ``mesh_size`` cells (so that plates a hair apart get the
same background), meshed at ``mesh_size``; its walls (separating, friction ``friction``) are
never reached, so the obstacle geometry a model sees is the pin's surface alone.

``kind`` names the outline's kind (the family records it; the scene does not use it).
Per-frame diagnostics: ``hole_offset`` (m, how far the centroid of the hole's boundary nodes is
from the pin's centre: the pivot staying put; for a given plate, how far the point of the plate
that started at the pin's centre is from it, carried by the best rigid fit of the hole's nodes,
which is the same for a round hole and holds for a hole of any shape) and ``swing`` (degrees, the
direction from the pin to the plate's centre of mass, counter-clockwise from straight down,
unwrapped over frames by the caller if it turns over).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .. import shapes
from ..config import ConfigError
from ..holes import clearance, holes, largest_disk
from ..mesh import Mesh
from ..mpm.boundary import Wall
from ..mpm.colliders import Collider, Path
from ..refine import refine_to
from .base import Scene, box_domain, check_params, make_material, vertex_volumes
from .bodies import read_body

NAME = "pendulum"
DEFAULTS = {
    "kind": "bar", "polygon": [[0.0, 0.0], [1.0, 0.0], [1.0, 0.3], [0.0, 0.3]], "pivot": [0.15, 0.15],
    "size": 0.12, "pin_radius": 0.007, "hole_gap": 0.0, "pin_friction": 0.0, "angle": 45.0, "amplitude": 0.0,
    "direction": 1.0, "spin": 0.0,
    "E": 5e7, "nu": 0.35, "density": 1200.0, "gravity": 9.81, "material": "neo_hookean", "friction": 0.0,
    "body_size": 0.0025, "mesh_size": 0.00375, "room": 0.0075,
}
OUTPUT = {"frames": 100, "frame_interval": 0.01}
SOLVER = {"transfer": "flip"}
# a given plate (params.mesh, params.refine): keys that appear in the resolved params only where given,
# so that the configs of drawn plates resolve as they always have
OPTIONAL = {"mesh": None, "refine": False}
# the hole's wall: at least this many body spacings of plate between the hole and the outline
HOLE_WALL = 1.0


def params(given: dict) -> dict:
    if not isinstance(given, dict):
        raise ConfigError(f"params must be a mapping of {NAME} parameters, got {type(given).__name__}")
    optional = {k: given[k] for k in OPTIONAL if k in given}
    given = {k: v for k, v in given.items() if k not in OPTIONAL}
    p = check_params(NAME, DEFAULTS, given,
                     positive=("size", "pin_radius", "E", "density", "body_size", "mesh_size", "room"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"}})
    for key in ("hole_gap", "pin_friction", "friction", "gravity"):
        if not p[key] >= 0:
            raise ConfigError(f"params.{key} must be >= 0, got {p[key]!r}")
    ring = np.asarray(p["polygon"], float)
    if ring.ndim != 2 or ring.shape[1] != 2 or len(ring) < 3 or not np.isfinite(ring).all():
        raise ConfigError(f"params.polygon must list at least 3 [x, y] vertices, got {p['polygon']!r}")
    pivot = np.asarray(p["pivot"], float)
    if pivot.shape != (2,) or not np.isfinite(pivot).all():
        raise ConfigError(f"params.pivot must be one [x, y] point in the polygon's units, got {p['pivot']!r}")
    for key in ("angle", "spin"):
        if not math.isfinite(p[key]):
            raise ConfigError(f"params.{key} must be a finite number, got {p[key]!r}")
    if p["direction"] not in (1.0, -1.0):
        raise ConfigError(f"params.direction must be 1 (counter-clockwise) or -1, got {p['direction']!r}")
    if not 0.0 <= p["amplitude"] < 180.0 or (p["amplitude"] > 0 and abs(p["angle"]) > p["amplitude"] * (1 + 1e-9)):
        raise ConfigError(f"params.amplitude must be 0 (start with params.spin) or in (0, 180) degrees and at least "
                          f"|params.angle| ({abs(p['angle'])}), got {p['amplitude']!r}")
    if optional.get("mesh") is not None:
        if not isinstance(optional.get("refine", False), bool):
            raise ConfigError(f"params.refine must be true or false, got {optional['refine']!r}")
        p.update(optional)
    elif "refine" in optional:
        raise ConfigError("params.refine subdivides a given plate (params.mesh); give params.mesh or leave it out")
    return p


def hole_radius(p: dict) -> float:
    """The hole's radius (m): the pin's and the play around it."""
    return p["pin_radius"] + p["hole_gap"]


def plate(p: dict) -> tuple[Mesh, np.ndarray]:
    """The plate meshed where it is drawn (scaled to ``size``) and its hole's centre (2,), in metres."""
    ring = np.asarray(p["polygon"], float)
    scale = p["size"] / float(np.ptp(ring, axis=0).max())
    ring, pivot = ring * scale, np.asarray(p["pivot"], float) * scale
    radius = hole_radius(p)
    if clearance(ring, pivot[None])[0] < radius + HOLE_WALL * p["body_size"]:
        raise ConfigError(f"params.pivot {p['pivot']}: a hole of radius {radius:.4g} m there leaves less than "
                          f"{HOLE_WALL} x params.body_size of the plate around it (or lies outside the polygon); "
                          "move the pivot inward, or make params.pin_radius smaller or params.size larger")
    count = max(12, math.ceil(2 * math.pi * radius / p["body_size"]))
    turn = 2 * math.pi * np.arange(count) / count
    hole = pivot + radius * np.stack([np.cos(turn), np.sin(turn)], 1)
    return shapes.polygon(ring, [hole], size=p["body_size"]), pivot


def given_plate(p: dict) -> tuple[Mesh, np.ndarray, float, np.ndarray, np.ndarray | None]:
    """A given plate (``mesh``) scaled to ``size`` (and with ``refine`` subdivided to ``body_size``, its
    nodes first), in metres; the centre (2,) and radius of the largest disk in the hole that holds
    ``pivot`` (:func:`datagen.holes.largest_disk`); the hole's nodes; the given cells where refined."""
    mesh = read_body(p["mesh"], 0)
    if mesh.dim != 2:
        raise ConfigError(f"params.mesh holds a {mesh.dim}D mesh; the {NAME} scene swings a 2D plate")
    scale = p["size"] / float(np.ptp(mesh.nodes, axis=0).max())
    mesh, given_cells = Mesh(mesh.nodes * scale, mesh.cells), None
    if p.get("refine"):
        fine, times = refine_to(mesh, p["body_size"])
        mesh, given_cells = fine, (mesh.cells if times else None)
    if mesh.n_components != 1:
        raise ConfigError(f"params.mesh holds {mesh.n_components} separate pieces; the {NAME} scene swings one "
                          "plate: give a mesh of one piece")
    try:
        loops = holes(mesh)
    except ConfigError as exc:
        raise ConfigError(f"params.mesh: {exc}") from None
    if not loops:
        raise ConfigError("params.mesh has no hole for the pin: the plate hangs on a pin through a hole in it; "
                          "give a mesh with a hole (an inner boundary) where it should turn")
    pivot = np.asarray(p["pivot"], float) * scale
    inside = [loop for loop in loops if clearance(mesh.nodes[loop], pivot[None])[0] > 0]
    if not inside:
        centres = [np.round(largest_disk(mesh, loop)[0] / scale, 6).tolist() for loop in loops]
        raise ConfigError(f"params.pivot {p['pivot']} lies in none of the {len(loops)} hole(s) of params.mesh (the "
                          f"pin would fit at {centres}, in the mesh's own units); give a point inside the hole the "
                          "pin goes through")
    centre, radius = largest_disk(mesh, inside[0])
    return mesh, centre, radius, inside[0], given_cells


def pinned(p: dict) -> tuple[Mesh, np.ndarray, float, np.ndarray, np.ndarray | None]:
    """The plate where it is drawn or given (metres), its hole's centre (2,), the pin's radius, the
    hole's nodes (indices) and, for a given plate refined, the given cells (else None)."""
    if p.get("mesh") is None:
        mesh, pivot = plate(p)
        rim = np.flatnonzero(np.abs(np.linalg.norm(mesh.nodes - pivot, axis=1) - hole_radius(p)) < 1e-6 * p["size"])
        return mesh, pivot, p["pin_radius"], rim, None
    mesh, centre, radius, rim, given_cells = given_plate(p)
    if radius <= p["hole_gap"]:
        raise ConfigError(f"params.hole_gap {p['hole_gap']} m leaves no pin in the hole of params.mesh (its largest "
                          f"disk is {radius:.4g} m in radius); make it smaller")
    return mesh, centre, radius - p["hole_gap"], rim, given_cells


def centre_of_mass(mesh: Mesh) -> np.ndarray:
    """(2,) the centroid of the plate's area (uniform density)."""
    return mesh.cell_measures @ mesh.nodes[mesh.cells].mean(1) / mesh.cell_measures.sum()


def posed(p: dict) -> tuple[Mesh, np.ndarray, float, np.ndarray | None]:
    """The plate turned about its hole so that its centre of mass lies ``angle`` degrees from straight
    down of the pin, and moved so that the pin is at the origin and the hole's centre ``hole_gap``
    from it towards the centre of mass; the hole's boundary nodes (indices), the pin's radius and the
    given cells (:func:`pinned`)."""
    mesh, pivot, pin_radius, rim, given_cells = pinned(p)
    arm = centre_of_mass(mesh) - pivot
    now = math.atan2(arm[0], -arm[1])  # counter-clockwise from straight down
    turn = math.radians(p["angle"]) - (now if np.linalg.norm(arm) > 1e-9 * p["size"] else 0.0)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    down = np.array([math.sin(math.radians(p["angle"])), -math.cos(math.radians(p["angle"]))])
    nodes = (mesh.nodes - pivot) @ rotation.T + p["hole_gap"] * down
    return Mesh(nodes, mesh.cells), rim, pin_radius, given_cells


def start_spin(p: dict, x: np.ndarray, volume: np.ndarray) -> float:
    """The plate's angular velocity at the start (rad/s): ``spin``, or where ``amplitude`` is not 0 the
    rate at which a rigid plate of particles ``x`` (pin at the origin) with ``volume`` (uniform density),
    at ``angle``, has the energy to reach ``amplitude``: w^2 = 2 g d (cos angle - cos amplitude) / k^2,
    d the distance from the pin to the centre of mass, k^2 the inertia about the pin over the mass."""
    if p["amplitude"] <= 0:
        return float(p["spin"])
    arm = float(np.linalg.norm(volume @ x / volume.sum()))
    k2 = float(volume @ (x**2).sum(1) / volume.sum())
    lift = math.cos(math.radians(p["angle"])) - math.cos(math.radians(p["amplitude"]))
    return p["direction"] * math.sqrt(max(2.0 * p["gravity"] * arm * lift, 0.0) / k2)


def hole_offset(rim: np.ndarray, x: np.ndarray, drawn: bool):
    """offset(xs) -> how far the plate's point that starts at the pin's centre (the origin) is from it
    with the plate's particles at ``xs``: for a drawn plate the centroid of the hole's nodes ``rim``
    (its hole is round); for a given one the origin carried by the hole's rigid motion from ``x``
    (the best-fit turn of its nodes about their centroid: a hole of any shape)."""
    rim_t = torch.as_tensor(rim, dtype=torch.int64)
    if drawn:
        return lambda xs: xs[rim_t.to(xs.device)].mean(0).norm()
    start = torch.as_tensor(x[rim])

    def offset(xs):
        now, first = xs[rim_t.to(xs.device)], start.to(xs)
        c, c0 = now.mean(0), first.mean(0)
        a, b = first - c0, now - c
        cos, sin = (a * b).sum(), (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()
        turn = torch.atan2(sin, cos)
        carried = torch.stack([torch.cos(turn) * c0[0] - torch.sin(turn) * c0[1],
                               torch.sin(turn) * c0[0] + torch.cos(turn) * c0[1]])
        return (c - carried).norm()

    return offset


def build(p: dict) -> Scene:
    body, rim, pin_radius, given_cells = posed(p)
    reach = float(np.linalg.norm(body.nodes, axis=1).max())
    half = p["mesh_size"] * math.ceil((reach + p["room"]) / p["mesh_size"])  # whole cells: the same
    # background for plates a hair apart (gmsh meshes a box a hair larger differently)
    domain = box_domain([-half, -half], [half, half], p["mesh_size"])
    pin = Collider("disk", (pin_radius,), Path(np.zeros(1), np.zeros((1, 2))), p["pin_friction"])
    pin_nodes, pin_facets = pin.surface(p["body_size"])
    x, volume = body.nodes.copy(), vertex_volumes(body)
    v = start_spin(p, x, volume) * np.stack([-x[:, 1], x[:, 0]], 1)
    material = make_material(p["material"], p["E"], p["nu"], p["density"])
    offset = hole_offset(rim, x, p.get("mesh") is None)

    def frame_diagnostics(sim, state) -> dict:
        xs = state.x
        m = state.mass
        com = (m[:, None] * xs).sum(0) / m.sum()
        return {"hole_offset": offset(xs), "swing": torch.rad2deg(torch.atan2(com[0], -com[1]))}

    return Scene(
        domain=domain, body=body, x=x, v=v, volume=volume, materials=[(material, None)],
        tracked=np.arange(body.n_nodes), walls=[Wall("separating", lambda c, n: np.ones(len(c), bool), p["friction"])],
        gravity=np.array([0.0, -p["gravity"]]), grid_spacing=p["mesh_size"],
        obstacle_nodes=pin_nodes, obstacle_facets=pin_facets.astype(np.int64), colliders=[pin],
        collider_nodes=[len(pin_nodes)], frame_diagnostics=frame_diagnostics, given_cells=given_cells,
    )
