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
"""

from __future__ import annotations

import math

import numpy as np

from ..config import ConfigError
from ..scenes.pendulum import clearance
from ..shapes3d import section_outline
from .base import check_ranges, integer, log_uniform, split_kinds, uniform
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
    """Not supported: the scene's plates are outlines with a hole drilled at a drawn pivot; raises
    ConfigError saying what to use instead."""
    raise ConfigError(f"zero-shot placement is not supported for family {NAME}: its plates are drawn as outlines "
                      "with a hole at a pivot; give a polygon outline and a pivot to the pendulum scene instead "
                      "(params.polygon, params.pivot), or use family glyphs or disks to drop your own mesh")
