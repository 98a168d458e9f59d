"""Family ``pendulum``: stiff plates swinging on a fixed pin through a hole in them (issue 67).

A dynamic family where an explicit solver's step is set by what the frames need not resolve:
plates of engineering stiffness (E log-uniform, 10-200 MPa by default) swing under gravity about
a frictionless pin (:mod:`datagen.scenes.pendulum`) at a few hertz, while their elastic waves
cross them thousands of times a second, so the solver takes hundreds to thousands of substeps per
frame. A single compound pendulum is not chaotic: two runs from states 1e-6 apart stay close over
the rollout (docs/pendulum.md). Each split draws a kind uniformly from its list, then the kind's
outline afresh (so no test or final plate is a training one):

- ``ranges.train_kinds`` (train and valid; default ``polygon``, ``bar``, ``l_section``);
- ``ranges.test_kinds`` (test; default ``stroke``, ``t_section``, ``ellipse``);
- ``ranges.final_kinds`` (the held-out ``final`` split, with probability ``ranges.final_novel``;
  default ``cross``, ``gear``, ``u_section``), else a new draw of the test kinds.

A kind belongs to one list only. The kinds (outlines scaled so that their largest extent is 1):
``polygon`` a random star-shaped polygon (as the press family draws them), ``bar`` a rectangle
``ranges.bar_width`` wide, ``l_section``, ``t_section``, ``u_section`` an angle, a tee and a
channel with legs ``ranges.leg`` thick and height ``ranges.section_aspect`` x width, ``stroke``
a random thick bent bar (``ranges.stroke_segments`` pieces ``ranges.stroke_width`` thick),
``ellipse`` with axes 1 and ``ranges.ellipse_aspect``, ``cross`` a plus sign of arms ``ranges.leg``
thick, ``gear`` a disk with ``ranges.gear_teeth`` square teeth ``ranges.gear_depth`` deep.

The pivot (the hole's centre) is drawn among the points of the plate where a hole of the pin's
radius leaves at least ``ranges.hole_wall`` metres of plate around it, at ``ranges.arm`` x size
from the outline's centroid (the nearest such point where none is that far). The plate starts at
``angle`` (uniform within the swing's amplitude, ``ranges.amplitude`` degrees) moving either way
with the speed that makes it turn back at the amplitude.

:func:`place` hangs a user's plate (one 2D triangle mesh with a hole) on the pin for zero-shot
rollouts (``bsms infer --mesh``): the pin is the largest disk in its hole, the plate scaled and
started from the middle of the ranges (docs/pendulum.md, "Zero-shot").
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..config import ConfigError
from ..holes import clearance, holes, largest_disk, play
from ..mesh import Mesh
from ..scenes import pendulum as pendulum_scene
from ..scenes.bodies import read_body
from ..shapes3d import section_outline
from ..simulation import resolve_config
from .base import _bounds, check_ranges, integer, log_midpoint, log_uniform, midpoint, split_kinds, uniform
from .placement import _dataset_config
from .press import _fraction, random_polygon, random_stroke

NAME = "pendulum"
SCENE = "pendulum"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, True, True, False
FINAL = True  # the final split is drawn its own way (module docstring)
KINDS = ("polygon", "bar", "l_section", "stroke", "t_section", "ellipse", "cross", "gear", "u_section")
RANGES = {
    "train_kinds": ["polygon", "bar", "l_section"], "test_kinds": ["stroke", "t_section", "ellipse"],
    "final_kinds": ["cross", "gear", "u_section"], "final_novel": 0.5,
    "polygon_vertices": [5, 9], "bar_width": [0.3, 0.45], "leg": [0.3, 0.42], "section_aspect": [0.6, 1.0],
    "stroke_segments": [2, 3], "stroke_width": [0.32, 0.42], "ellipse_aspect": [0.45, 0.8], "gear_teeth": [6, 10],
    "gear_depth": [0.12, 0.2],
    "size": [0.08, 0.11], "pin_radius": [0.006, 0.0075], "hole_wall": 0.004, "arm": [0.15, 0.4],
    "E": [1e7, 2e8], "nu": [0.3, 0.4], "density": [1000.0, 1500.0], "amplitude": [20.0, 90.0],
}
GRID = 41  # candidate pivots per axis over the outline's bounding box
# a placed plate's pin may move about in its hole by MAX_PLAY background cells at most, counting the
# positions where it overlaps the plate's nodes by PLAY_OVERLAP cells at most (docs/pendulum.md, "Zero-shot")
MAX_PLAY, PLAY_OVERLAP = 0.5, 0.1


def _kinds(r: dict, split: str) -> list[str]:
    """The kinds ``split`` draws from, checked (:func:`~.base.split_kinds`)."""
    return split_kinds(r, split, KINDS)


def _ring(points) -> np.ndarray:
    """A closed outline (K, 2) scaled so that its largest extent is 1 and centred on its bounding box."""
    ring = np.asarray(points, float)
    ring = ring - (ring.max(0) + ring.min(0)) / 2
    return ring / float(np.ptp(ring, axis=0).max())


def _cross(leg: float) -> list:
    a = leg / 2
    return [[a, -0.5], [a, -a], [0.5, -a], [0.5, a], [a, a], [a, 0.5], [-a, 0.5], [-a, a], [-0.5, a], [-0.5, -a],
            [-a, -a], [-a, -0.5]]


def _gear(teeth: int, depth: float) -> np.ndarray:
    """A disk of radius 1 - depth with ``teeth`` square teeth reaching radius 1, each half a pitch wide."""
    points = []
    for k in range(teeth):
        for phase, radius in ((k, 1.0 - depth), (k + 0.5, 1.0 - depth), (k + 0.5, 1.0), (k + 1.0, 1.0)):
            turn = phase * 2 * math.pi / teeth
            points.append([radius * math.cos(turn), radius * math.sin(turn)])
    return np.array(points)


def outline(kind: str, r: dict, rng: np.random.Generator) -> np.ndarray:
    """The outline (K, 2) of a plate of ``kind``, drawn from ``rng``, largest extent 1."""
    if kind == "polygon":
        return _ring(random_polygon(rng, integer(r, "polygon_vertices", rng, minimum=3)))
    if kind == "bar":
        w = uniform(r, "bar_width", rng)
        return _ring([[0.0, 0.0], [1.0, 0.0], [1.0, w], [0.0, w]])
    if kind == "stroke":
        return _ring(random_stroke(rng, integer(r, "stroke_segments", rng), uniform(r, "stroke_width", rng)))
    if kind == "ellipse":
        b, turn = uniform(r, "ellipse_aspect", rng), 2 * math.pi * np.arange(48) / 48
        return _ring(np.stack([np.cos(turn), b * np.sin(turn)], 1))
    if kind == "cross":
        return _ring(_cross(uniform(r, "leg", rng)))
    if kind == "gear":
        return _ring(_gear(integer(r, "gear_teeth", rng, minimum=3), uniform(r, "gear_depth", rng)))
    aspect, flange, web = uniform(r, "section_aspect", rng), uniform(r, "leg", rng), uniform(r, "leg", rng)
    if kind == "u_section":  # a channel: a base ``flange`` thick, two legs ``web`` thick
        return _ring([[0, 0], [1, 0], [1, aspect], [1 - web, aspect], [1 - web, flange], [web, flange], [web, aspect],
                      [0, aspect]])
    return _ring(section_outline(kind[0].upper(), 1.0, aspect, flange, web))


def centroid(ring: np.ndarray) -> np.ndarray:
    """(2,) the area centroid of the closed polygon ``ring`` (shoelace)."""
    x, y = ring.T
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (3.0 * cross.sum())


def pivot(ring: np.ndarray, room: float, arm: float) -> np.ndarray | None:
    """A point of the outline at least ``room`` from its edge, as near ``arm`` from its centroid as any
    (units of the outline); None where no point has that room."""
    axes = [np.linspace(lo, hi, GRID) for lo, hi in zip(ring.min(0), ring.max(0), strict=True)]
    points = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], 1)
    points = points[clearance(ring, points) >= room]
    if not len(points):
        return None
    reach = np.linalg.norm(points - centroid(ring), axis=1)
    return points[int(np.argmin(np.abs(reach - arm)))]


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    if split == "final":  # a novel kind with probability final_novel, else drawn as the test split
        novel = rng.uniform() < _fraction(r, "final_novel")
        kinds = _kinds(r, "final" if novel else "test")
    else:
        kinds = _kinds(r, "test" if split == "test" else "train")
    kind = kinds[int(rng.integers(len(kinds)))]
    size, pin = uniform(r, "size", rng), uniform(r, "pin_radius", rng)
    arm = uniform(r, "arm", rng)
    for _ in range(50):  # a plate with room for the hole (every default kind has it at its first draw)
        ring = outline(kind, r, rng)
        point = pivot(ring, (pin + float(r["hole_wall"])) / size, arm)
        if point is not None:
            break
    else:
        raise ConfigError(f"ranges: no {kind} plate of size {size:.3g} m in 50 draws has room for a hole of radius "
                          f"{pin:.3g} m with ranges.hole_wall {r['hole_wall']} m around it; make the pin or the wall "
                          "smaller, or the plates larger or thicker")
    amplitude = uniform(r, "amplitude", rng)
    if not 0.0 < amplitude < 180.0:
        raise ConfigError(f"ranges.amplitude is the swing's amplitude in degrees: in (0, 180), got {amplitude!r}")
    return {
        "kind": kind, "polygon": np.round(ring, 6).tolist(), "pivot": np.round(point, 6).tolist(), "size": size,
        "pin_radius": pin, "E": log_uniform(r, "E", rng), "nu": uniform(r, "nu", rng),
        "density": uniform(r, "density", rng), "amplitude": amplitude,
        "angle": amplitude * rng.uniform(-1.0, 1.0), "direction": 1.0 if rng.uniform() < 0.5 else -1.0,
    }


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``pendulum`` config swinging one 2D triangle mesh (a Mesh or a file path: a user's plate) on a
    pin through a hole in it, as this family swings its plates (docs/pendulum.md, "Zero-shot"): the
    dataset config's params (background, body spacing, room), the mesh as the plate (``params.mesh``)
    scaled so that its largest extent is the mid-range size and subdivided where it is coarser than the
    family's plates (``refine``); the pin the largest disk in its hole (:func:`datagen.holes.largest_disk`:
    the hole itself for a round one) -- its only hole, or the largest, or with ``overrides.pivot`` (a
    point in the mesh's own units) the one holding that point; mid-range stiffness, Poisson ratio,
    density and amplitude, the plate starting straight down (``angle`` 0, the middle of the family's
    starts) turning counter-clockwise (``direction`` 1) at the rigid pendulum's rate for that amplitude.
    ``overrides`` replace any pendulum scene parameter but those that make the plate (:data:`FIXED`), e.g.
    ``size``, ``E``, ``nu``, ``density``, ``amplitude``, ``angle``, ``direction``, ``pivot``,
    ``mesh_size``, ``hole_gap``, ``refine``. ConfigError, naming the mesh, for anything but one 2D mesh
    of one piece with a hole, a pin under the family's size in background cells (:func:`check_pin`) or
    a hole the pin could move about in (:data:`MAX_PLAY`)."""
    if isinstance(meshes, (str, Path, Mesh)) or not isinstance(meshes, (list, tuple)) or len(meshes) != 1:
        raise ConfigError(_not_one(meshes))
    overrides = _overrides(overrides)
    d = _dataset_config(dconfig, NAME)
    r = check_ranges(NAME, RANGES, d["ranges"])
    name = _name(meshes[0])
    entry, mesh = _given(meshes[0], name)
    loop = _hole(mesh, name, overrides.get("pivot"), r)
    params = {key: value for key, value in d["params"].items() if key in pendulum_scene.DEFAULTS and key not in FIXED}
    params.update(
        kind="mesh", mesh=entry, size=midpoint(r, "size"),
        E=log_midpoint(r, "E"), nu=midpoint(r, "nu"), density=midpoint(r, "density"),
        amplitude=midpoint(r, "amplitude"), angle=0.0, direction=1.0, spin=0.0, refine=True,
    )
    params.update(overrides, pivot=largest_disk(mesh, loop)[0].tolist())  # the pin's centre, the mesh's units
    config = {"scene": SCENE, "params": params, "solver": d["solver"], "output": d["output"], "seed": d["seed"]}
    resolved = resolve_config(config)["params"]  # every value checked now, not when the run starts
    params["pin_radius"] = check_pin(resolved, r, d["params"], name)
    return config


FIXED = ("kind", "polygon", "mesh", "pin_radius")
"""Scene parameters a placement sets itself: the plate is the mesh, the pin its hole's largest disk."""


def _not_one(meshes) -> str:
    """The error for ``meshes`` that are not a list of one mesh."""
    if not isinstance(meshes, (list, tuple)):
        got = repr(meshes)
    elif meshes:
        got = (f"{len(meshes)} meshes ({', '.join(_name(m, k) for k, m in enumerate(meshes))}); place each on its own "
               "(bsms infer --separately)")
    else:
        got = "none"
    return (f"family {NAME!r} swings one plate on its pin: give meshes as a list of exactly one Mesh or file path, "
            f"got {got}")


def _name(mesh, k: int = 0) -> str:
    """Mesh ``k`` as an error names it: its file, or ``meshes[k] (a Mesh)``."""
    return f"file {mesh}" if isinstance(mesh, (str, Path)) else f"meshes[{k}] (a {type(mesh).__name__})"


def _overrides(overrides: dict | None) -> dict:
    """``overrides`` checked: pendulum scene parameters but :data:`FIXED`, and ``refine``."""
    overrides = dict(overrides or {})
    known = sorted({*pendulum_scene.DEFAULTS, "refine"} - set(FIXED))
    for key in overrides:
        if key not in known:
            raise ConfigError(f"overrides.{key} is not a {NAME} scene parameter that can be overridden; "
                              f"known: {', '.join(known)}")
    return overrides


def _given(given, name: str) -> tuple:
    """(params.mesh entry, Mesh) of the given plate: one 2D triangle mesh of one piece."""
    if isinstance(given, Mesh):
        entry, mesh = {"nodes": given.nodes.tolist(), "cells": given.cells.tolist()}, given
    elif isinstance(given, (str, Path)):
        mesh, entry = read_body(given, 0), str(Path(given).expanduser().resolve())
    else:
        raise ConfigError(f"meshes[0] must be a Mesh or a mesh file path, got {type(given).__name__}")
    if mesh.dim != DIM:
        raise ConfigError(f"mesh {name} is a {mesh.dim}D mesh but family {NAME!r} swings 2D plates; give a 2D "
                          "triangle mesh (z = 0) of the plate")
    if mesh.n_components != 1:
        raise ConfigError(f"mesh {name} holds {mesh.n_components} separate pieces but family {NAME!r} swings one "
                          "plate; give a mesh of one piece")
    return entry, mesh


def _hole(mesh: Mesh, name: str, pivot, r: dict) -> np.ndarray:
    """The hole the pin goes through (node indices): the one holding ``pivot`` (mesh units) where
    given, else the only or the largest one."""
    try:
        loops = holes(mesh)
    except ConfigError as exc:
        raise ConfigError(f"mesh {name}: {exc}") from None
    if not loops:
        lo, hi = (100 * v / midpoint(r, "size") for v in _bounds(r, "pin_radius"))
        raise ConfigError(f"mesh {name} has no hole for the pin: family {NAME!r} hangs its plates on a fixed pin "
                          "through a round hole in them; mesh the plate with a round hole where it should turn (an "
                          f"inner boundary: in gmsh, cut a disk out of the surface; the family's holes are "
                          f"{lo:.1f}-{hi:.1f}% of the plate's largest extent in radius)")
    if pivot is None:
        return loops[0]
    point = np.asarray(pivot, float)
    if point.shape != (2,) or not np.isfinite(point).all():
        raise ConfigError(f"overrides.pivot must be one [x, y] point inside a hole of mesh {name}, in its own "
                          f"units, got {pivot!r}")
    for loop in loops:
        if clearance(mesh.nodes[loop], point[None])[0] > 0:
            return loop
    centres = [np.round(largest_disk(mesh, loop)[0], 6).tolist() for loop in loops]
    raise ConfigError(f"overrides.pivot {list(pivot)} lies in none of the {len(loops)} hole(s) of mesh {name}; give "
                      f"a point inside the hole the pin goes through, in the mesh's own units (the holes' pins "
                      f"would be centred at {centres})")


def _digits(value: float, sense: int) -> float:
    """``value`` to 4 significant digits, rounded up (``sense`` 1) or down (-1)."""
    unit = 10.0 ** (math.floor(math.log10(value)) - 3)
    return round((math.ceil(value / unit) if sense > 0 else math.floor(value / unit)) * unit, 12)


def check_pin(p: dict, r: dict, dataset_params: dict, name: str) -> float:
    """The pin's radius (m) of the resolved placement ``p``; ConfigError where it is under the family's
    smallest pin in background cells (``ranges.pin_radius`` low over the dataset's ``mesh_size``: a
    pin of too few cells lets the hole wander, docs/pendulum.md) or where it could move about in its
    hole by more than :data:`MAX_PLAY` of a background cell."""
    mesh, centre, radius, loop, _ = pendulum_scene.pinned(p)
    cells = _bounds(r, "pin_radius")[0] / dataset_params.get("mesh_size", pendulum_scene.DEFAULTS["mesh_size"])
    spacing = p["mesh_size"]
    if radius < cells * spacing * (1 - 1e-9):
        larger, finer = _digits(p["size"] * cells * spacing / radius, 1), _digits(radius / cells, -1)
        raise ConfigError(
            f"mesh {name}: the largest pin its hole takes is {1e3 * radius:.3g} mm in radius with the plate scaled to "
            f"{p['size']:g} m, {radius / spacing:.2f} background cells of {1e3 * spacing:g} mm; family {NAME!r}'s "
            f"pins are at least {cells:.2f} cells, and fewer let the hole wander off the pin (docs/pendulum.md); "
            f"mesh a larger hole, scale the plate up (overrides size={larger}) or refine the background (overrides "
            f"mesh_size={finer})")
    loose = 0.0 if p["hole_gap"] > 0 else play(mesh, loop, centre, radius, PLAY_OVERLAP * spacing)
    if loose > MAX_PLAY * spacing:  # a gap given on purpose (hole_gap) is the user's play
        raise ConfigError(
            f"mesh {name}: the largest pin its hole takes ({1e3 * radius:.3g} mm in radius with the plate scaled "
            f"to {p['size']:g} m) could move {1e3 * loose:.3g} mm about in it, {loose / spacing:.2f} background cells "
            f"of {1e3 * spacing:g} mm, and family {NAME!r}'s joint is a pin that fills its hole (at most {MAX_PLAY} "
            "cells of play); mesh a round hole, or one the pin touches all round (a square, a regular polygon)")
    return radius
