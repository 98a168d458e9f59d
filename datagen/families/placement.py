"""Zero-shot placement: put any body meshes into a family's setting with the ``bodies`` scene.

A family's ``place(meshes, dconfig, overrides)`` chooses where the bodies go and how they
move (deterministically, from the middle of its ranges) and hands that choice to
:func:`bodies_config`, which adds what every family shares: the dataset config's material,
gravity, friction and background mesh size, its solver and output sections, and the
caller's overrides. The result is a ``datagen.simulate`` config.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config import ConfigError, read_yaml
from ..mesh import Mesh
from ..scenes import bodies as bodies_scene
from ..scenes import get_scene
from ..simulation import resolve_config

__all__ = ["bodies_config", "row_centers", "toward_axis", "SHARED_PARAMS"]

SHARED_PARAMS = ("nu", "gravity", "friction", "material", "mesh_size")
"""Scene parameters a family's dataset config fixes that the bodies scene takes as they are."""


def row_centers(n: int, lower, upper) -> np.ndarray:
    """(n, d) centres of ``n`` equal columns along x across [lower, upper], in the middle of the other axes."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    centers = np.tile((lower + upper) / 2, (n, 1))
    centers[:, 0] = lower[0] + (np.arange(n) + 0.5) * (upper[0] - lower[0]) / n
    return centers


def toward_axis(centers: np.ndarray, middle, speed: float, axes=(0, 1)) -> np.ndarray:
    """(n, d) velocities of ``speed`` pointing, within ``axes``, from each centre towards ``middle``.

    A centre already there moves along +axes[0]. Components outside ``axes`` are zero.
    """
    centers = np.asarray(centers, float)
    axes = list(axes)
    offset = np.asarray(middle, float)[axes] - centers[:, axes]
    length = np.linalg.norm(offset, axis=1, keepdims=True)
    direction = np.where(length > 1e-12, offset / np.maximum(length, 1e-300), np.eye(len(axes))[0])
    out = np.zeros_like(centers)
    out[:, axes] = speed * direction
    return out


def _dataset_config(dconfig, family: str) -> dict:
    if isinstance(dconfig, (str, Path)):
        dconfig = read_yaml(dconfig, what="dataset config")
    if not isinstance(dconfig, dict):
        raise ConfigError(f"dconfig must be a dataset config (a mapping or a YAML path), got {type(dconfig).__name__}")
    if dconfig.get("family", family) != family:
        raise ConfigError(f"dconfig is a config of family {dconfig['family']!r}, not {family!r}")
    out = {key: dict(dconfig.get(key) or {}) for key in ("ranges", "params", "solver", "output")}
    return {**out, "seed": dconfig.get("seed", 0)}


def _mesh_entry(mesh, k: int, dim: int, family: str):
    """(params.meshes entry, Mesh) for a Mesh or a mesh file path; the dimension must be the family's."""
    if isinstance(mesh, Mesh):
        entry, body = {"nodes": mesh.nodes.tolist(), "cells": mesh.cells.tolist()}, mesh
    elif isinstance(mesh, (str, Path)):
        body = bodies_scene.read_body(mesh, k)
        entry = str(Path(mesh).expanduser().resolve())
    else:
        raise ConfigError(f"meshes[{k}] must be a Mesh or a mesh file path, got {type(mesh).__name__}")
    if body.dim != dim:
        raise ConfigError(f"meshes[{k}] is a {body.dim}D mesh but family {family!r} is {dim}D; "
                          f"give a {dim}D mesh or pick a {body.dim}D family")
    return entry, body


def bodies_config(family: str, dim: int, scene: str, meshes, dconfig, overrides: dict | None,
                  choose: Callable[[dict, int], dict]) -> dict:
    """The ``bodies`` simulate() config of ``meshes`` in the setting of ``family`` (of dimension
    ``dim``, sampling scene ``scene``: its defaults give the shared parameters the dataset
    config does not fix).

    choose(ranges, n) -> the family's params for n bodies (box, centers, sizes, velocities,
    E, density, ...); ``overrides`` (bodies scene parameters) replace any chosen value.
    """
    if isinstance(meshes, (str, Path, Mesh)) or not isinstance(meshes, (list, tuple)) or not meshes:
        raise ConfigError("meshes must be a non-empty list of Mesh objects or mesh file paths")
    overrides = dict(overrides or {})
    for key in overrides:
        if key not in bodies_scene.DEFAULTS or key == "meshes":
            known = ", ".join(k for k in sorted(bodies_scene.DEFAULTS) if k != "meshes")
            raise ConfigError(f"overrides.{key} is not a bodies scene parameter that can be overridden; "
                              f"known: {known}")
    d = _dataset_config(dconfig, family)
    entries = [_mesh_entry(m, k, dim, family)[0] for k, m in enumerate(meshes)]
    scene_defaults = get_scene(scene).DEFAULTS
    params = {key: scene_defaults[key] for key in SHARED_PARAMS if key in scene_defaults}
    params.update({key: value for key, value in d["params"].items() if key in SHARED_PARAMS})
    params.update(choose(d["ranges"], len(entries)), meshes=entries)
    params.update(overrides)
    config = {"scene": bodies_scene.NAME, "params": params, "solver": d["solver"], "output": d["output"],
              "seed": d["seed"]}
    resolve_config(config)  # checks every value now, not when the run starts
    return config
