"""Family ``press3d``: a stiff elastic solid bonded to a floor, pressed by a moving indenter (3D).

The 3D counterpart of the ``press`` family (:mod:`datagen.scenes.press3d` is its scene). Bodies of
engineering stiffness (E log-uniform, 10-200 MPa by default) meshed as 1,000-5,000-node tetrahedra,
bonded at the base to the floor (``params.base: bonded``, a sticky floor), so that what the indenter
makes is deformation. Each split draws a kind uniformly from its list, then the kind's shape:

- ``ranges.train_kinds`` (train and valid; default ``letter``, ``holed_block``, ``l_section``);
- ``ranges.test_kinds`` (test; default ``letter``, ``polygon``, ``t_section``, ``cylinder``);
- ``ranges.final_kinds`` (the held-out ``final`` split, with probability ``ranges.final_novel``;
  default ``digit``, ``slotted_block``, ``stroke``), else a new draw of the test kinds.

A kind belongs to one list only, but for ``letter``, whose characters do instead: train and valid
letters from ``ranges.train_chars``, test ones from ``ranges.test_chars`` (T is left out of the
default training letters: a T section is a test kind), a ``digit`` from ``ranges.final_chars``, so
test and final bodies are of kinds training never saw. The kinds:

- ``letter``, ``digit``: a character's outline extruded by ``ranges.depth`` x size;
- ``polygon``: a random star-shaped polygon, ``stroke``: a random thick bent bar (both as the 2D
  press draws them, each afresh), extruded by ``ranges.depth``;
- ``l_section``, ``t_section``: an angle or a tee (legs ``ranges.section_leg`` thick, height
  ``ranges.section_aspect`` x width) extruded by ``ranges.section_depth``;
- ``holed_block``, ``slotted_block``: a block 1 x ``ranges.block_height`` x ``ranges.block_depth``
  (x size) with a round through hole (radius ``ranges.hole`` x the face's shorter side) or a
  round-ended through slot (width ``ranges.slot_width`` x that side, length ``ranges.slot_length``
  x the width, at most 80% of the face's first side in cyclic order) along a random axis;
- ``cylinder``: a round bar standing on its end, diameter ``ranges.cylinder_diameter`` and height
  ``ranges.cylinder_height`` x size.

Every draw records its kind (``params.kind``). Extruded profiles stand on their most stable side
(``params.pose: stable``). The indenter (sphere, box, or a square bar lying across the body along z
-- the stand-in for a roller: the solver has no cylinder collider) of half width
``ranges.indenter_scale`` x size starts just above the body, offset by ``ranges.indenter_offset`` x
the body's extent in x and in z, and moves at ``ranges.speed`` along a line tilted up to
``ranges.angle`` degrees from the vertical towards a random azimuth for ``ranges.press_time`` s,
then back.

:func:`place` presses a given tetrahedral mesh (a user's part) as the family presses its bodies:
mid-range size, material, gap and speed, a sphere of mid-range scale straight down over its middle;
the indenter and its path chosen by its ``overrides`` (docs/press3d.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import ConfigError
from ..mesh import Mesh
from ..scenes import press3d as scene
from ..shapes3d import section_outline
from ..simulation import resolve_config
from .base import check_ranges, choice, integer, log_midpoint, log_uniform, midpoint, split_kinds, uniform
from .glyphs import _alphabet
from .placement import _dataset_config, _mesh_entry
from .press import _final_chars, _fraction, random_polygon, random_stroke

NAME = "press3d"
SCENE = "press3d"
DIM, CONTACT, OBSTACLES, CLAMPED = 3, True, True, False
DRIVEN = True  # the indenter moves as prescribed and does work on the body
FINAL = True  # the final split is drawn its own way (module docstring)
KINDS = ("letter", "digit", "polygon", "stroke", "l_section", "t_section", "holed_block", "slotted_block", "cylinder")
RANGES = {
    "train_kinds": ["letter", "holed_block", "l_section"], "test_kinds": ["letter", "polygon", "t_section", "cylinder"],
    "final_kinds": ["digit", "slotted_block", "stroke"], "final_novel": 0.5,
    "train_chars": "ABCDEFHKLMNPRVWXYZ", "test_chars": "GJQSU", "final_chars": "0123456789",
    "polygon_vertices": [5, 9], "stroke_segments": [1, 3], "stroke_width": [0.2, 0.35],
    "depth": [0.25, 0.6], "section_leg": [0.15, 0.3], "section_aspect": [0.6, 1.0], "section_depth": [0.5, 1.0],
    "block_height": [0.4, 0.8], "block_depth": [0.4, 0.8], "hole": [0.15, 0.3], "slot_width": [0.2, 0.35],
    "slot_length": [1.5, 3.0], "cylinder_diameter": [0.4, 0.8], "cylinder_height": [0.6, 1.0],
    "size": [0.1, 0.13], "nodes": [1500, 3000], "E": [1e7, 2e8], "nu": [0.3, 0.4], "density": [1000.0, 1500.0],
    "indenters": ["sphere", "box", "bar"], "indenter_scale": [0.15, 0.3], "indenter_aspect": [0.4, 1.0],
    "indenter_offset": [-0.2, 0.2], "speed": [0.14, 0.18], "angle": [0.0, 15.0], "gap": [0.014, 0.018],
    "press_time": 0.15, "hold_time": 0.0,
}
# scene parameters that make the body: a placed mesh (:func:`place`) is the body, so none of them is overridden
BODY_KEYS = ("kind", "body", "mesh", "char", "polygon", "holes", "depth", "block", "feature", "hole", "slot",
             "feature_axis", "cylinder")
# placement options that are no scene parameter: the indenter's size as the family's ranges give it
PLACE_KEYS = ("indenter_scale", "indenter_aspect")


def _kinds(r: dict, split: str) -> list[str]:
    """The kinds ``split`` draws from, checked (:func:`~.base.split_kinds`; letters in several splits)."""
    kinds = split_kinds(r, split, KINDS, shared_ok="letter")
    if "letter" in r["final_kinds"]:
        raise ConfigError("ranges.final_kinds may not hold 'letter' (the final split's characters are 'digit')")
    return kinds


def _body(kind: str, r: dict, rng: np.random.Generator, chars: str) -> dict:
    """The press3d scene parameters of one body of ``kind``, drawn from ``rng``."""
    if kind in ("letter", "digit"):
        return {"body": "extrusion", "char": chars[int(rng.integers(len(chars)))], "depth": uniform(r, "depth", rng)}
    if kind == "polygon":
        ring = random_polygon(rng, integer(r, "polygon_vertices", rng, minimum=3))
        return {"body": "extrusion", "polygon": ring, "depth": uniform(r, "depth", rng)}
    if kind == "stroke":
        ring = random_stroke(rng, integer(r, "stroke_segments", rng), uniform(r, "stroke_width", rng))
        return {"body": "extrusion", "polygon": ring, "depth": uniform(r, "depth", rng)}
    if kind in ("l_section", "t_section"):
        flange, web = uniform(r, "section_leg", rng), uniform(r, "section_leg", rng)
        ring = section_outline(kind[0].upper(), 1.0, uniform(r, "section_aspect", rng), flange, web)
        return {"body": "extrusion", "polygon": ring, "depth": uniform(r, "section_depth", rng)}
    if kind == "cylinder":
        return {"body": "cylinder",
                "cylinder": [uniform(r, "cylinder_diameter", rng), uniform(r, "cylinder_height", rng)]}
    block = [1.0, uniform(r, "block_height", rng), uniform(r, "block_depth", rng)]
    axis = int(rng.integers(3))
    a, b = block[(axis + 1) % 3], block[(axis + 2) % 3]  # the face the feature goes through (a: the slot's length)
    if kind == "holed_block":
        return {"body": "block", "block": block, "feature": "hole", "feature_axis": axis,
                "hole": uniform(r, "hole", rng) * min(a, b)}
    width = uniform(r, "slot_width", rng) * min(a, b)
    length = min(uniform(r, "slot_length", rng) * width, 0.8 * a)
    return {"body": "block", "block": block, "feature": "slot", "feature_axis": axis, "slot": [width, length]}


def _depth(body: dict) -> float:
    """The body's extent along z as a fraction of its size."""
    if body["body"] == "extrusion":
        return body["depth"]
    return body["block"][2] if body["body"] == "block" else body["cylinder"][0]


def indenter_sizes(shape: str, half: float, aspect: float) -> list[float]:
    """The scene's ``indenter_size`` of a ``shape`` of half width ``half``: a sphere's radius, a box
    ``aspect`` x half as high as it is wide and deep, a bar ``aspect`` x half wide (along x)."""
    sizes = {"sphere": [half], "box": [half, half * aspect, half], "bar": [half * aspect, half]}[shape]
    return [round(s, 6) for s in sizes]


def _indenter(r: dict, rng: np.random.Generator, size: float) -> dict:
    shape = choice(r, "indenters", rng)
    if shape not in scene.INDENTER_SIZES:
        raise ConfigError(f"ranges.indenters may hold {sorted(scene.INDENTER_SIZES)}, got {shape!r}")
    half = uniform(r, "indenter_scale", rng) * size
    aspect = uniform(r, "indenter_aspect", rng)
    return {"indenter": shape, "indenter_size": indenter_sizes(shape, half, aspect)}


def sample(ranges: dict, rng: np.random.Generator, split: str) -> dict:
    r = check_ranges(NAME, RANGES, ranges)
    if split == "final":  # a novel kind with probability final_novel, else drawn as the test split
        novel = rng.uniform() < _fraction(r, "final_novel")
        kinds, chars = (_kinds(r, "final"), _final_chars(r)) if novel else (_kinds(r, "test"), _alphabet(r, "test"))
    else:
        kinds, chars = _kinds(r, "test" if split == "test" else "train"), _alphabet(r, split)
    kind = kinds[int(rng.integers(len(kinds)))]
    body = {"kind": kind, **_body(kind, r, rng, chars)}
    size = uniform(r, "size", rng)
    nodes = integer(r, "nodes", rng, minimum=100)
    return {
        **body, "size": size, "nodes": nodes, "E": log_uniform(r, "E", rng), "nu": uniform(r, "nu", rng),
        "density": uniform(r, "density", rng), **_indenter(r, rng, size),
        "indenter_x": uniform(r, "indenter_offset", rng) * size,
        "indenter_z": uniform(r, "indenter_offset", rng) * _depth(body) * size,
        "speed": uniform(r, "speed", rng), "angle": uniform(r, "angle", rng), "azimuth": rng.uniform(0.0, 360.0),
        "gap": uniform(r, "gap", rng), "press_time": uniform(r, "press_time", rng),
        "hold_time": uniform(r, "hold_time", rng),
    }


def place(meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``press3d`` config pressing one tetrahedral mesh (a Mesh or a file path) as this family presses
    its bodies: the dataset config's params (background, box, base, pose, damping, settling), the mesh as
    the body (``body: mesh``) set on its most stable side and scaled to the mid-range size, subdivided
    where it is coarser than bodies of the mid-range node count (``refine``), bonded at its base as the
    config says, mid-range stiffness, Poisson ratio, density, speed and gap, and a sphere of mid-range
    scale straight down over the body's middle. ``overrides`` replace any press3d scene parameter but
    those that make the body (:data:`BODY_KEYS`): e.g. ``indenter`` (``sphere``, ``box``, ``bar``: sized
    by the family's mid-range scale and aspect unless ``indenter_size`` is given), ``indenter_x``,
    ``indenter_z``, ``speed``, ``angle``, ``azimuth``, ``press_time``, ``gap``, ``E``, ``size``,
    ``refine``; and ``indenter_scale``, ``indenter_aspect`` (the family's ranges' meaning: half width /
    size, and the box's height or the bar's width / its half width)."""
    if isinstance(meshes, (str, Path, Mesh)) or not isinstance(meshes, (list, tuple)) or len(meshes) != 1:
        raise ConfigError(f"family {NAME!r} presses one body: give meshes as a list of exactly one Mesh or file path")
    overrides = _placement_overrides(overrides)
    d = _dataset_config(dconfig, NAME)
    entry, _ = _mesh_entry(meshes[0], 0, DIM, NAME)
    r = check_ranges(NAME, RANGES, d["ranges"])
    params = {key: value for key, value in d["params"].items() if key in scene.DEFAULTS and key not in BODY_KEYS}
    params.update(
        kind="mesh", body="mesh", mesh=entry, size=midpoint(r, "size"), nodes=round(midpoint(r, "nodes")),
        E=log_midpoint(r, "E"), nu=midpoint(r, "nu"), density=midpoint(r, "density"), indenter_x=0.0,
        indenter_z=0.0, speed=midpoint(r, "speed"), angle=0.0, azimuth=0.0, gap=midpoint(r, "gap"),
        press_time=midpoint(r, "press_time"), hold_time=midpoint(r, "hold_time"), refine=True,
    )
    params.update({key: value for key, value in overrides.items() if key not in PLACE_KEYS})
    params.update(_placed_indenter(r, overrides, params["size"]))
    config = {"scene": SCENE, "params": params, "solver": d["solver"], "output": d["output"], "seed": d["seed"]}
    resolve_config(config)  # every value checked now, not when the run starts
    return config


def _placement_overrides(overrides: dict | None) -> dict:
    """``overrides`` checked: press3d scene parameters but :data:`BODY_KEYS`, and :data:`PLACE_KEYS`."""
    overrides = dict(overrides or {})
    known = sorted({*scene.DEFAULTS, *PLACE_KEYS} - set(BODY_KEYS))
    for key in overrides:
        if key not in known:
            raise ConfigError(f"overrides.{key} is not a {NAME} scene parameter that can be overridden; "
                              f"known: {', '.join(known)}")
    if "indenter_size" in overrides and {"indenter_scale", "indenter_aspect"} & set(overrides):
        raise ConfigError("overrides.indenter_size gives the indenter's half extents in metres; give it or "
                          "indenter_scale and indenter_aspect (fractions), not both")
    for key in ("indenter_scale", "indenter_aspect"):
        value = overrides.get(key, 1.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
            raise ConfigError(f"overrides.{key} must be a positive number, got {value!r}")
    return overrides


def _placed_indenter(r: dict, overrides: dict, size: float) -> dict:
    """The placed indenter: ``indenter`` (sphere by default) sized by ``indenter_size`` where given, else
    by the family's mid-range (or the given) ``indenter_scale`` x ``size`` and ``indenter_aspect``."""
    shape = overrides.get("indenter", "sphere")
    if shape not in scene.INDENTER_SIZES:
        raise ConfigError(f"overrides.indenter must be one of {sorted(scene.INDENTER_SIZES)}, got {shape!r}")
    if "indenter_size" in overrides:
        return {"indenter": shape, "indenter_size": overrides["indenter_size"]}
    half = float(overrides.get("indenter_scale", midpoint(r, "indenter_scale"))) * size
    aspect = float(overrides.get("indenter_aspect", midpoint(r, "indenter_aspect")))
    return {"indenter": shape, "indenter_size": indenter_sizes(shape, half, aspect)}
