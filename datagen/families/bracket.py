"""Family ``bracket``: a stiff bracket clamped at one end, bent far by a moving indenter.

The second driven family (issue 32): where the ``press`` family's bonded bodies move by about 1%
of their size, a bracket held only at its left end (``params.base: clamped``: the box's left wall
is sticky) bends by 10-25% of its length under the indenter. Bodies are random brackets
(:func:`random_bracket`: a thick bar leaving the wall straight, then straight or curved pieces
turning by up to 90 degrees: bars, L brackets, arcs, S and Z shapes), each drawn afresh, so that
no test bracket is a training one. The indenter (disk or box) starts just above the bracket's
outer part and moves down along a line near the vertical, holds and goes back
(:mod:`datagen.scenes.press`, whose scene this family samples).

The ``final`` split (held out, evaluated once per published model) draws, with probability
``ranges.final_novel``, a bracket of a kind no other split holds -- ``ranges.final_segments``
pieces, thinner (``ranges.final_width``) and turning by up to ``ranges.final_turn`` degrees --
else a new draw like the test split's.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import ConfigError
from .base import check_ranges, integer, log_uniform, midpoint, uniform
from .press import _fraction, _indenter, _simple, centreline, mitred_outline, placed_config

NAME = "bracket"
SCENE = "press"
DIM, CONTACT, OBSTACLES, CLAMPED = 2, True, True, False
DRIVEN = True  # the indenter moves as prescribed and does work on the body
FINAL = True  # the final split is drawn its own way (module docstring)
RANGES = {
    "segments": [1, 3], "width": [0.18, 0.3], "turn": 90.0,
    "final_novel": 0.5, "final_segments": [4, 4], "final_width": [0.12, 0.18], "final_turn": 120.0,
    "size": [0.1, 0.13], "E": [3e7, 3e8], "nu": [0.3, 0.45], "density": [1000.0, 1500.0],
    "indenters": ["disk", "box"], "indenter_scale": [0.08, 0.15], "indenter_aspect": [0.4, 1.0],
    "indenter_offset": [0.15, 0.4], "speed": [0.08, 0.15], "angle": [-15.0, 15.0], "gap": [0.001, 0.003],
    "press_time": 0.2, "hold_time": 0.1,
}


def random_bracket(rng: np.random.Generator, segments: int, width: float, turn: float = 90.0) -> list[list[float]]:
    """The outline of a bracket: a bar of thickness ``width`` whose centreline leaves x = 0 along +x
    with a straight first piece and goes on with ``segments`` - 1 straight or curved pieces (each
    0.6-1.4 units long, turning by up to ``turn`` degrees either way, a curved one as an arc sampled
    every 15 degrees), mitred joins, square ends; redrawn until the outline does not cross itself
    and only its first end (the clamped face, at x = 0) comes within ``width`` / 2 of x = 0.
    Scaled so that its largest extent is 1, the clamped face's middle at the origin."""
    limit = math.radians(turn)
    for _ in range(200):
        first = np.array([rng.uniform(0.6, 1.4), 0.0])  # the straight piece leaving the wall
        line = centreline(rng, [np.zeros(2), first], 0.0, segments - 1, lambda r: r.uniform(-limit, limit))
        ring = mitred_outline(line, width)
        if _simple(ring) and (ring[1:-1, 0] > 0.5 * width).all():  # all but the clamped face's corners
            return np.round(ring / np.ptp(ring, axis=0).max(), 6).tolist()
    raise RuntimeError("no bracket outline in 200 draws")  # not reached for the default ranges


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    prefix = ""
    if split == "final":  # a novel kind with probability final_novel, else drawn as the test split
        novel = _fraction(r, "final_novel")
        prefix = "final_" if rng.uniform() < novel else ""
    size = uniform(r, "size", rng)
    turn = float(r[f"{prefix}turn"])
    if not 0.0 <= turn <= 135.0:
        raise ConfigError(f"ranges.{prefix}turn is the largest turn between a bracket's pieces in degrees: 0 to 135, "
                          f"got {turn!r}")
    ring = random_bracket(rng, integer(r, f"{prefix}segments", rng, minimum=1), uniform(r, f"{prefix}width", rng),
                          turn)
    return {
        "polygon": ring, "size": size, "E": log_uniform(r, "E", rng), "nu": uniform(r, "nu", rng),
        "density": uniform(r, "density", rng), **_indenter(r, rng, size),
        "indenter_x": uniform(r, "indenter_offset", rng) * size, "speed": uniform(r, "speed", rng),
        "angle": uniform(r, "angle", rng), "gap": uniform(r, "gap", rng),
        "press_time": uniform(r, "press_time", rng), "hold_time": uniform(r, "hold_time", rng),
        "base": "clamped",
    }


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``press`` config clamping one mesh (2D) at its leftmost points to the box's left wall and
    bending it like this family's brackets: mid-range size, stiffness, density and speed, a disk
    indenter of mid-range size straight down over the outer part. ``overrides`` replace any press
    scene parameter (e.g. ``indenter_x``, ``speed``, ``lift``: how far above the box's middle)."""
    return placed_config(NAME, RANGES, "clamps", meshes, dconfig, overrides, lambda r, size: {
        "indenter_x": round(midpoint(r, "indenter_offset") * size, 6), "base": "clamped"})
