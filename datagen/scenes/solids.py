"""The 3D press scene's bodies (:mod:`datagen.scenes.press3d`): extruded profiles, blocks with a hole
or a slot, cylinders, meshed by :mod:`datagen.shapes3d` to about ``params.nodes`` nodes; or a given
tetrahedral mesh (``body: mesh``), set on its most stable side (:func:`rest_pose`) and scaled."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .. import shapes, shapes3d
from ..config import ConfigError
from ..holes import signed_area
from ..mesh import Mesh
from .base import merge_bodies
from .bodies import place_body, read_body
from .press import BASE_TOL, COM_MARGIN, MIN_BASE, centre_of_mass, rest_turn

__all__ = ["BODIES", "FEATURES", "body_mesh", "given_body", "profile", "profile_area", "rest_pose", "stands"]

BODIES = ("extrusion", "block", "cylinder", "mesh")
FEATURES = ("hole", "slot", "none")
_GLYPH_SPACING = 0.02  # of the em height: the outline's resolution for measuring and posing a letter


def _fractions(p: dict, key: str, count: int) -> list[float]:
    value = [p[key]] if count == 1 and isinstance(p[key], (int, float)) else p[key]
    ok = isinstance(value, (list, tuple)) and len(value) == count and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in value)
    if not ok:
        what = "a positive fraction" if count == 1 else f"{count} positive fractions"
        raise ConfigError(f"params.{key} must be {what} of params.size, got {p[key]!r}")
    return [float(v) for v in value]


def _polygon_rings(p: dict) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    ring = np.asarray(p["polygon"], float)
    if ring.ndim != 2 or ring.shape[1] != 2 or len(ring) < 3 or not np.isfinite(ring).all():
        raise ConfigError(f"params.polygon must list at least 3 [x, y] vertices, got {p['polygon']!r}")
    holes = []
    for k, hole in enumerate(p["holes"] or []):
        hole = np.asarray(hole, float)
        if hole.ndim != 2 or hole.shape[1] != 2 or len(hole) < 3 or not np.isfinite(hole).all():
            raise ConfigError(f"params.holes[{k}] must list at least 3 [x, y] vertices, got {p['holes'][k]!r}")
        holes.append(hole)
    return [(ring, holes)]


def profile(p: dict, spacing: float | None = None) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """The extruded body's profile as (outer, holes) rings in the x-y plane: the letter ``char`` or
    the ``polygon`` with ``holes``, turned as ``pose`` says and scaled so that its largest extent is
    ``size``; a letter's curves resampled to ``spacing`` (None: finely)."""
    if p["polygon"] is None:
        if not isinstance(p["char"], str) or len(p["char"].strip()) != 1:
            raise ConfigError(f"params.char must be a single visible character, got {p['char']!r}")
        coarse = shapes3d.glyph_rings(p["char"], _GLYPH_SPACING)
        extent = np.ptp(np.concatenate([outer for outer, _ in coarse]), axis=0).max()
        rings = coarse if spacing is None else shapes3d.glyph_rings(p["char"], spacing * extent / p["size"])
    else:
        rings = coarse = _polygon_rings(p)
    turn, centre = 0.0, np.zeros(2)
    if p["pose"] == "stable":
        flat = _flat(coarse)
        turn, centre = rest_turn(flat) or 0.0, centre_of_mass(flat)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    turned = [((o - centre) @ rotation.T, [(h - centre) @ rotation.T for h in hs]) for o, hs in rings]
    outers = np.concatenate([o for o, _ in turned])
    low, scale = outers.min(0), p["size"] / float(np.ptp(outers, axis=0).max())
    return [((o - low) * scale, [(h - low) * scale for h in hs]) for o, hs in turned]


def _flat(rings) -> Mesh:
    """A coarse triangulation of the profile (its pose is found on it), each piece meshed alone."""
    spacing = 0.05 * float(np.ptp(np.concatenate([o for o, _ in rings]), axis=0).max())
    return merge_bodies([shapes.polygon(outer, holes, spacing) for outer, holes in rings])[0]


def profile_area(rings) -> float:
    """The area of (outer, holes) rings (shoelace)."""
    def area(r):
        return abs(signed_area(np.asarray(r, float)))

    return sum(area(o) - sum(area(h) for h in hs) for o, hs in rings)


def _block(p: dict):
    """(make(spacing), volume) of the block with its hole or slot."""
    extent = [f * p["size"] for f in _fractions(p, "block", 3)]
    axis, volume = p["feature_axis"], float(np.prod(extent))
    if p["feature"] == "none":
        return (lambda s: shapes.box(extent, s)), volume
    if p["feature"] == "hole":
        radius = _fractions(p, "hole", 1)[0] * p["size"]
        def make(s):
            return shapes3d.holed_block(extent, radius, s, axis=axis)
        return make, volume - math.pi * radius**2 * extent[axis]
    width, length = (f * p["size"] for f in _fractions(p, "slot", 2))
    def make(s):
        return shapes3d.slotted_block(extent, width, length, s, axis=axis)
    return make, volume - (width * (length - width) + math.pi * width**2 / 4) * extent[axis]


def body_mesh(p: dict) -> Mesh:
    """The body of the resolved parameters ``p``, meshed to about ``nodes`` nodes, or the given
    ``mesh`` posed and scaled (:func:`given_body`); anywhere: the scene places it."""
    if p["body"] == "mesh":
        return given_body(p)
    try:
        if p["body"] == "extrusion":
            depth = p["depth"] * p["size"]
            volume = profile_area(profile(p)) * depth
            def make(s):
                return shapes3d.extrude_rings(profile(p, s), depth, s)
        elif p["body"] == "block":
            make, volume = _block(p)
        else:
            diameter, height = (f * p["size"] for f in _fractions(p, "cylinder", 2))
            volume = math.pi * diameter**2 / 4 * height
            def make(s):
                return shapes3d.cylinder(diameter / 2, height, s)
        return shapes3d.with_nodes(make, volume, int(p["nodes"]))
    except ConfigError:
        raise
    except ValueError as exc:
        raise ConfigError(f"params: the {p['body']} body cannot be meshed: {exc}") from None


def given_body(p: dict) -> Mesh:
    """The tetrahedral mesh ``mesh`` (a file path or an inline ``{nodes, cells}``) set on its most
    stable side where ``pose`` is ``stable`` (:func:`rest_pose`), then scaled so that its largest
    extent is ``size`` (about the origin; the scene places it)."""
    try:
        mesh = read_body(p["mesh"], 0)
    except ConfigError as exc:  # read_body names the bodies scene's key
        raise ConfigError(str(exc).replace("params.meshes[0]", "params.mesh")) from None
    if mesh.dim != 3:
        raise ConfigError(f"params.mesh holds a {mesh.dim}D mesh; the press3d scene needs a tetrahedral (3D) mesh")
    return place_body(rest_pose(mesh) if p["pose"] == "stable" else mesh, np.zeros(3), p["size"])


def stands(mesh: Mesh) -> bool:
    """Whether a solid stands as it is on a floor below it (y up), as the 2D press's
    :func:`datagen.scenes.press.stands` says of a profile: its base (nodes within BASE_TOL x its size
    of its lowest point) is at least MIN_BASE x its size wide in every direction on the floor, and
    its centre of mass lies over the base at least COM_MARGIN x that width inside its outline."""
    size = float(np.ptp(mesh.nodes, axis=0).max())
    base = mesh.nodes[mesh.nodes[:, 1] <= mesh.nodes[:, 1].min() + BASE_TOL * size][:, [0, 2]]
    try:
        hull = ConvexHull(base)
    except (QhullError, ValueError):  # fewer than three points, or all on a line: no footing
        return False
    normals, offsets = hull.equations[:, :2], hull.equations[:, 2]  # n.x + d <= 0 inside
    # the base's width: across it at its narrowest, from each edge of its outline to its farthest point
    width = float(np.min(np.max(-(base @ normals.T + offsets), axis=0)))
    inside = -(normals @ centre_of_mass(mesh)[[0, 2]] + offsets)
    return width >= MIN_BASE * size and float(inside.min()) >= COM_MARGIN * width


def rest_pose(mesh: Mesh) -> Mesh:
    """A solid as it is where it :func:`stands`; otherwise turned about its centre of mass, by the
    smallest rotation that does it, so that the face of its convex hull nearest the centre of mass
    faces down (the 3D counterpart of :func:`datagen.scenes.press.rest_pose`: the centre of mass
    lies over that face)."""
    if stands(mesh):
        return mesh
    c = centre_of_mass(mesh)
    equations = ConvexHull(mesh.nodes).equations
    normal = equations[int(np.argmax(equations[:, :3] @ c + equations[:, 3])), :3]
    rotation = _turning(normal / np.linalg.norm(normal), np.array([0.0, -1.0, 0.0]))
    return Mesh((mesh.nodes - c) @ rotation.T + c, mesh.cells)


def _turning(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The proper rotation (3, 3) by the smallest angle that turns the unit vector ``a`` onto ``b``
    (Rodrigues; half a turn about an axis normal to both where they are opposite)."""
    axis, cosine = np.cross(a, b), float(a @ b)
    if cosine < -1.0 + 1e-12:
        other = np.eye(3)[int(np.argmin(np.abs(a)))]
        axis = np.cross(a, other) / np.linalg.norm(np.cross(a, other))
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + cosine)
