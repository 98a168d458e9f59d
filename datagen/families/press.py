"""Family ``press``: a stiff elastic body on a floor, pressed by a moving indenter and released.

Bodies of engineering stiffness (E log-uniform in megapascals) shaped as letters: the train
and valid splits draw from ``ranges.train_chars`` or, with probability ``ranges.train_polygons``
(default 0), a random star-shaped polygon, or with probability ``ranges.train_strokes``
(default 0) a random stroke (:func:`random_stroke`: a thick bent bar, the primitive letters
and brackets are made of); the test split from ``ranges.test_chars`` or, with probabilities
``ranges.test_polygons`` and ``ranges.test_strokes``, a polygon or a stroke -- shapes never seen
in training (every polygon and stroke is drawn afresh, so a test one is never a training one). The
``final`` split (held out, evaluated once per published model) draws, with probability
``ranges.final_novel``, a character of ``ranges.final_chars`` (digits: a kind of shape no other split
holds), else a new draw of the test kinds. The
indenter (disk, box or wedge, sized relative to the body) starts just above the body at a
random offset and moves along a random line near the vertical at a few cm/s, then back
(:mod:`datagen.scenes.press`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..config import ConfigError, Retired
from ..mesh import Mesh
from ..scenes import press as press_scene
from ..simulation import resolve_config
from .base import check_ranges, choice, integer, log_midpoint, log_uniform, midpoint, uniform
from .glyphs import _alphabet
from .placement import _dataset_config, _mesh_entry

NAME = "press"
SCENE = "press"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, True, True, False
DRIVEN = True  # the indenter moves as prescribed and does work on the body
FINAL = True  # the final split is drawn its own way (module docstring)
RANGES = {
    "train_chars": "ABCDEFHKLMNPRTVWXYZ", "test_chars": "GJQSU", "test_polygons": 0.5, "train_polygons": 0.0,
    "final_chars": "0123456789", "final_novel": 0.5,
    "polygon_vertices": [5, 9], "train_strokes": 0.0, "test_strokes": 0.0, "stroke_segments": [1, 4],
    "stroke_width": [0.15, 0.35],
    "size": [0.1, 0.13], "E": [1e6, 2e7], "nu": [0.3, 0.45], "density": [1000.0, 1500.0],
    "indenters": ["disk", "box", "wedge"], "indenter_scale": [0.12, 0.25], "indenter_aspect": [0.4, 1.0],
    "indenter_offset": [-0.25, 0.25], "speed": [0.03, 0.06], "angle": [-10.0, 10.0], "gap": [0.001, 0.003],
    "press_time": 0.2, "hold_time": 0.0,
}
# ranges measured and not adopted (docs/experiments.md)
RETIRED = {"train_body_size": Retired("the train and valid bodies meshed at a spacing drawn for each", "null",
                                      "0417dad", lambda value, ranges: value is None)}


def random_polygon(rng: np.random.Generator, vertices: int) -> list[list[float]]:
    """A star-shaped polygon of ``vertices`` corners around the origin (radii 0.55-1, angles jittered)."""
    base = np.sort(rng.uniform(-0.3, 0.3, vertices) + np.arange(vertices)) * (2 * math.pi / vertices)
    radius = rng.uniform(0.55, 1.0, vertices)
    return np.round(np.stack([radius * np.cos(base), radius * np.sin(base)], 1), 6).tolist()


def _simple(ring: np.ndarray) -> bool:
    """Whether a closed ring (K, 2) has no two non-adjacent edges that cross."""
    a, b = ring, np.roll(ring, -1, axis=0)
    k = len(ring)
    for i in range(k):
        for j in range(i + 2, k - (i == 0)):
            d1, d2 = b[i] - a[i], b[j] - a[j]
            den = d1[0] * d2[1] - d1[1] * d2[0]
            if abs(den) < 1e-14:
                continue
            r = a[j] - a[i]
            t, u = (r[0] * d2[1] - r[1] * d2[0]) / den, (r[0] * d1[1] - r[1] * d1[0]) / den
            if 0.0 <= t <= 1.0 and 0.0 <= u <= 1.0:
                return False
    return True


def random_stroke(rng: np.random.Generator, segments: int, width: float) -> list[list[float]]:
    """The outline of a thick bent bar: a centreline of ``segments`` straight or curved pieces
    (each 0.6-1.4 units long, turning by up to 135 degrees, a curved one as an arc sampled every
    15 degrees), offset by ``width`` / 2 to both sides with mitred joins and square ends;
    redrawn until the outline does not cross itself. Bars, L and V brackets, hooks and arcs."""
    for _ in range(100):
        heading = rng.uniform(0, 2 * math.pi)
        line = centreline(rng, [np.zeros(2)], heading, segments, lambda r: r.uniform(-0.75, 0.75) * math.pi)
        ring = mitred_outline(line, width)
        if _simple(ring):
            ring -= (ring.max(0) + ring.min(0)) / 2
            return np.round(ring / np.ptp(ring, axis=0).max(), 6).tolist()
    raise RuntimeError("no simple stroke outline in 100 draws")  # not reached for the default ranges


def centreline(rng: np.random.Generator, points: list, heading: float, pieces: int, turn) -> np.ndarray:
    """``points`` continued by ``pieces`` straight or curved pieces from ``heading`` (radians): each
    0.6-1.4 units long and turning by ``turn(rng)`` radians, half of them (at random) a corner and a
    straight piece, the others an arc sampled every 15 degrees. (K, 2)."""
    points = list(points)  # the caller's list stays as given
    for _ in range(pieces):
        length, bend = rng.uniform(0.6, 1.4), turn(rng)
        if rng.uniform() < 0.5:  # a corner, then a straight piece
            heading += bend
            points.append(points[-1] + length * np.array([math.cos(heading), math.sin(heading)]))
        else:  # an arc turning by ``bend`` over ``length``
            steps = max(1, int(abs(bend) / math.radians(15)))
            for _ in range(steps):
                heading += bend / steps
                points.append(points[-1] + length / steps * np.array([math.cos(heading), math.sin(heading)]))
    return np.array(points)


def mitred_outline(line: np.ndarray, width: float) -> np.ndarray:
    """The closed outline (2K, 2) of a bar of thickness ``width`` along the centreline ``line`` (K, 2):
    offset by ``width`` / 2 to both sides with mitred joins (the offset that keeps both neighbouring
    edges at width / 2, at most 1 / 0.35 times that) and square ends; the left side first."""
    tangent = np.diff(line, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], 1)
    joins = [normal[0]] + [n1 + n2 for n1, n2 in zip(normal[:-1], normal[1:], strict=True)] + [normal[-1]]
    offsets = []
    for k, join in enumerate(joins):
        n = normal[min(k, len(normal) - 1)]
        join = join / np.linalg.norm(join)
        offsets.append(join * (0.5 * width / max(float(join @ n), 0.35)))
    offsets = np.array(offsets)
    return np.concatenate([line + offsets, (line - offsets)[::-1]])


def _indenter(r: dict, rng: np.random.Generator, size: float) -> dict:
    shape = choice(r, "indenters", rng)
    if shape not in press_scene.INDENTER_SIZES:
        raise ConfigError(f"ranges.indenters may hold {sorted(press_scene.INDENTER_SIZES)}, got {shape!r}")
    half = uniform(r, "indenter_scale", rng) * size
    aspect = uniform(r, "indenter_aspect", rng)
    sizes = {"disk": [half], "box": [half, half * aspect], "wedge": [half, 2 * half * aspect]}[shape]
    return {"indenter": shape, "indenter_size": [round(s, 6) for s in sizes]}


def _fraction(r: dict, key: str) -> float:
    value = r[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
        what = "of novel kinds" if key == "final_novel" else f"that are random {key.split('_')[1]}"
        raise ConfigError(f"ranges.{key} is the fraction of bodies {what}: a number from 0 to 1, got {value!r}")
    return float(value)


def _final_chars(r: dict) -> str:
    chars = r["final_chars"]
    if not isinstance(chars, str) or not chars.strip():
        raise ConfigError(f"ranges.final_chars must be a non-empty string of characters, got {chars!r}")
    seen = set(chars) & (set(r["train_chars"]) | set(r["test_chars"]))
    if seen:
        raise ConfigError(f"ranges.final_chars shares {''.join(sorted(seen))!r} with ranges.train_chars or "
                          "ranges.test_chars; the final split's novel characters must be of no other split")
    return chars.replace(" ", "")


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges, RETIRED)
    novel = False
    if split == "final":  # a novel kind with probability final_novel, else drawn as the test split
        final_chars = _final_chars(r)
        novel = rng.uniform() < _fraction(r, "final_novel")
        split = "test"
    chars = final_chars if novel else _alphabet(r, split)
    size = uniform(r, "size", rng)
    body: dict = {"char": chars[int(rng.integers(len(chars)))]}
    polygons = _fraction(r, "test_polygons" if split == "test" else "train_polygons")
    strokes = _fraction(r, "test_strokes" if split == "test" else "train_strokes")
    if polygons + strokes > 1.0:
        prefix = "test" if split == "test" else "train"
        raise ConfigError(f"ranges.{prefix}_polygons + ranges.{prefix}_strokes is {polygons + strokes:g}: the "
                          "fractions of polygons and strokes may add up to 1 at most (the rest are letters)")
    # a train/valid draw takes no extra random number when both fractions are 0: older datasets replay
    kind = rng.uniform() if split == "test" or polygons + strokes > 0 else 1.0
    if novel:
        kind = 1.0  # the novel character drawn above
    if kind < polygons:
        body = {"polygon": random_polygon(rng, integer(r, "polygon_vertices", rng, minimum=3))}
    elif kind < polygons + strokes:
        width = uniform(r, "stroke_width", rng)
        body = {"polygon": random_stroke(rng, integer(r, "stroke_segments", rng, minimum=1), width)}
    drawn = {
        **body, "size": size, "E": log_uniform(r, "E", rng), "nu": uniform(r, "nu", rng),
        "density": uniform(r, "density", rng), **_indenter(r, rng, size),
        "indenter_x": uniform(r, "indenter_offset", rng) * size, "speed": uniform(r, "speed", rng),
        "angle": uniform(r, "angle", rng), "gap": uniform(r, "gap", rng),
        "press_time": uniform(r, "press_time", rng), "hold_time": uniform(r, "hold_time", rng),
    }
    return drawn


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``press`` config pressing one mesh (2D) like this family's bodies: mid-range size,
    stiffness, density and speed, a disk indenter of mid-range size straight down over the
    body's centre, the mesh subdivided where it is coarser than the family's bodies (``refine``).
    ``overrides`` replace any press scene parameter (e.g. the indenter and its path: ``indenter``,
    ``indenter_size``, ``indenter_x``, ``speed``, ``angle``, ``press_time``; ``refine``)."""
    return placed_config(NAME, RANGES, "presses", meshes, dconfig, overrides, lambda r, size: {})


def placed_config(family: str, defaults: dict, verb: str, meshes, dconfig, overrides: dict | None, placement) -> dict:
    """The ``press`` scene config of one mesh in the setting of ``family`` (ranges ``defaults``):
    the family's params, mid-range size, stiffness, density, speed and gap, a disk of mid-range
    size straight down over the body's centre, the mesh subdivided to the resolution of the family's
    own bodies where it is coarser (``refine``: a model is only as good as on the meshes it was
    trained on), then ``placement(ranges, size)`` (a dict of scene parameters the family sets its
    own way) and ``overrides`` (``refine=False`` keeps the mesh as given); ``verb`` names what the family
    does with the body in the error for anything but one mesh."""
    if isinstance(meshes, (str, Path, Mesh)) or not isinstance(meshes, (list, tuple)) or len(meshes) != 1:
        raise ConfigError(f"family {family!r} {verb} one body: give meshes as a list of exactly one Mesh or file path")
    overrides = dict(overrides or {})
    for key in overrides:
        if key not in press_scene.DEFAULTS or key in ("char", "polygon", "mesh"):
            known = ", ".join(k for k in sorted(press_scene.DEFAULTS) if k not in ("char", "polygon", "mesh"))
            raise ConfigError(f"overrides.{key} is not a press scene parameter that can be overridden; known: {known}")
    d = _dataset_config(dconfig, family)
    entry, _ = _mesh_entry(meshes[0], 0, DIM, family)
    r = check_ranges(family, defaults, d["ranges"], RETIRED)
    size = midpoint(r, "size")
    params = {key: value for key, value in d["params"].items() if key in press_scene.DEFAULTS}
    params.update(
        mesh=entry, size=size, E=log_midpoint(r, "E"), nu=midpoint(r, "nu"), density=midpoint(r, "density"),
        indenter="disk", indenter_size=[round(midpoint(r, "indenter_scale") * size, 6)], indenter_x=0.0,
        speed=midpoint(r, "speed"), angle=0.0, gap=midpoint(r, "gap"), press_time=midpoint(r, "press_time"),
        hold_time=midpoint(r, "hold_time"), refine=True,
    )
    params.update(placement(r, size))
    params.update(overrides)
    config = {"scene": SCENE, "params": params, "solver": d["solver"], "output": d["output"], "seed": d["seed"]}
    resolve_config(config)
    return config
