"""User meshes dropped into a box: any 2D or 3D simplex meshes as elastic bodies.

``meshes`` lists the bodies, each a mesh file path (any format ``Mesh.read`` reads; relative
paths are taken from the working directory) or an inline mapping ``{nodes, cells}``. Body
``k`` is scaled uniformly so that the largest extent of its bounding box is ``sizes[k]``
(null: its own size) and moved so that its bounding-box centre is ``centers[k]`` (null: where
it is). Its vertices are the tracked material points, as in the other box scenes. The box
(2D ``[x0, y0, x1, y1]`` or 3D ``[x0, y0, z0, x1, y1, z1]``; null: the unit square or cube)
is the background mesh; its whole boundary is a separating wall with friction and the
obstacle geometry a model sees. Gravity points along -y (y is up) in 2D and 3D.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import torch

from ..config import ConfigError
from ..mesh import Mesh, MeshError
from ..mpm.locate import CellLocator, LocateStatus, locate
from .base import Scene, box_bounds, box_domain, check_params, contained_bodies, merge_bodies

NAME = "bodies"
DEFAULTS = {
    "meshes": [], "centers": None, "sizes": None, "velocities": None, "box": None, "E": 2e4, "nu": 0.3,
    "density": 1000.0, "gravity": 9.81, "friction": 0.2, "mesh_size": 0.1, "material": "neo_hookean",
}
OUTPUT = {"frames": 40, "frame_interval": 0.05}
SOLVER = {"transfer": "flip"}
PER_BODY = ("centers", "sizes", "velocities")  # null or one entry per mesh
_FIT_TOL = 1e-9  # relative to the box extent: a body may touch the walls


@functools.lru_cache(maxsize=32)
def _read_file(path: str, mtime_ns: int, size: int) -> Mesh:  # keyed on the file's state: edits invalidate
    return Mesh.read(path)


def read_body(entry, k: int) -> Mesh:
    """Mesh ``k`` of params.meshes: a file path or an inline ``{nodes, cells}`` mapping."""
    key = f"params.meshes[{k}]"
    if isinstance(entry, dict):
        if set(entry) != {"nodes", "cells"}:
            raise ConfigError(f"{key} must be a mesh file path or a mapping with keys nodes and cells, "
                              f"got keys {sorted(entry)}")
        try:
            return Mesh(np.asarray(entry["nodes"], float), np.asarray(entry["cells"], np.int64))
        except (MeshError, ValueError, TypeError) as exc:
            raise ConfigError(f"{key} is not a usable mesh: {exc}") from None
    if not isinstance(entry, (str, Path)) or not str(entry):
        raise ConfigError(f"{key} must be a mesh file path or a mapping with keys nodes and cells, got {entry!r}")
    path = Path(entry).expanduser()
    if not path.is_file():
        raise ConfigError(f"{key}: mesh file {path} does not exist (relative paths start from the working "
                          "directory)")
    stat = path.stat()
    try:
        return _read_file(str(path), stat.st_mtime_ns, stat.st_size)
    except MeshError as exc:
        raise ConfigError(f"{key}: {exc}") from None


def _describe(entry, k: int) -> str:
    return f"body {k} ({entry})" if isinstance(entry, (str, Path)) else f"body {k} (inline mesh)"


def _per_body(p: dict, key: str, n: int) -> list:
    value = p[key]
    if value is None:
        return [None] * n
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(f"params.{key} must be null or list one entry per mesh ({n}), got {value!r}")
    return list(value)


def _vector(value, key: str, d: int) -> list[float]:
    ok = isinstance(value, (list, tuple)) and len(value) == d and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in value)
    if not ok:
        raise ConfigError(f"{key} must be a {d}D vector (the box's dimension), got {value!r}")
    return [float(x) for x in value]


def _check_dimensions(meshes: list[Mesh], given_box) -> int:
    if given_box is None and meshes[0].dim not in (2, 3):
        raise ConfigError(f"params.meshes[0] holds a {meshes[0].dim}D mesh; the {NAME} scene needs 2D or 3D meshes")
    d = len(given_box) // 2 if given_box is not None else meshes[0].dim
    for k, mesh in enumerate(meshes):
        if mesh.dim == d:
            continue
        if given_box is None:
            raise ConfigError(f"params.meshes[{k}] holds a {mesh.dim}D mesh but params.meshes[0] is {d}D; "
                              "all bodies must have the same dimension")
        raise ConfigError(f"params.meshes[{k}] holds a {mesh.dim}D mesh but params.box {given_box} is {d}D; "
                          f"give a {mesh.dim}D box or a {d}D mesh")
    return d


def params(given: dict) -> dict:
    if not isinstance(given, dict):
        raise ConfigError(f"params must be a mapping of {NAME} parameters, got {type(given).__name__}")
    optional = {k: v for k, v in given.items() if k in DEFAULTS and DEFAULTS[k] is None}  # checked below
    p = check_params(NAME, DEFAULTS, {k: v for k, v in given.items() if k not in optional},
                     positive=("E", "density", "mesh_size"),
                     choices={"material": {"linear", "neo_hookean", "fixed_corotated"}})
    p.update(optional)
    if not p["meshes"]:
        raise ConfigError("params.meshes must list at least one body: mesh file paths (or {nodes, cells} mappings)")
    meshes = [read_body(entry, k) for k, entry in enumerate(p["meshes"])]
    if p["box"] is not None:
        box_bounds(p["box"])
    d = _check_dimensions(meshes, p["box"])
    box = p["box"] if p["box"] is not None else [0.0] * d + [1.0] * d
    n = len(meshes)
    sizes = _per_body(p, "sizes", n)
    for k, s in enumerate(sizes):
        if s is not None and (isinstance(s, bool) or not isinstance(s, (int, float)) or not s > 0
                              or not math.isfinite(s)):
            raise ConfigError(f"params.sizes[{k}] must be a positive number or null (keep the mesh's size), got {s!r}")
    centers = [_vector(c, f"params.centers[{k}]", d) if c is not None else _middle(meshes[k]).tolist()
               for k, c in enumerate(_per_body(p, "centers", n))]
    velocities = [_vector(v, f"params.velocities[{k}]", d) if v is not None else [0.0] * d
                  for k, v in enumerate(_per_body(p, "velocities", n))]
    p = {**p, "box": [float(b) for b in box], "sizes": sizes, "centers": centers, "velocities": velocities}
    placed = [place_body(m, c, s) for m, c, s in zip(meshes, centers, sizes, strict=True)]
    _check_fit(placed, p)
    _check_apart(placed, p)
    return p


def _middle(mesh: Mesh) -> np.ndarray:
    return (mesh.nodes.min(0) + mesh.nodes.max(0)) / 2


def place_body(mesh: Mesh, center, size: float | None) -> Mesh:
    """``mesh`` scaled so that its largest bounding-box extent is ``size`` (None: kept), centred at ``center``."""
    scale = 1.0 if size is None else size / np.ptp(mesh.nodes, axis=0).max()
    return Mesh((mesh.nodes - _middle(mesh)) * scale + np.asarray(center, float), mesh.cells)


def _check_fit(placed: list[Mesh], p: dict) -> None:
    lower, upper = box_bounds(p["box"])
    tol = _FIT_TOL * (upper - lower).max()
    for k, mesh in enumerate(placed):
        lo, hi = mesh.nodes.min(0), mesh.nodes.max(0)
        what = _describe(p["meshes"][k], k)
        if np.any(hi - lo > upper - lower + tol):
            how = "shrink it with params.sizes" if p["sizes"][k] is None else "make params.sizes smaller"
            raise ConfigError(f"params.sizes: {what} spans {np.round(hi - lo, 6).tolist()}, larger than params.box "
                              f"{p['box']}; {how}")
        if np.any(lo < lower - tol) or np.any(hi > upper + tol):
            raise ConfigError(f"params.centers: {what} centred at {p['centers'][k]} spans {np.round(lo, 6).tolist()} "
                              f"to {np.round(hi, 6).tolist()}, outside params.box {p['box']}; move it inside")


def _pieces(placed: list[Mesh], p: dict) -> list[tuple[Mesh, int, str]]:
    """Every connected component of every body: (mesh, body index, words naming it)."""
    pieces = []
    for k, mesh in enumerate(placed):
        what = _describe(p["meshes"][k], k)
        if mesh.n_components == 1:
            pieces.append((mesh, k, what))
            continue
        for c in range(mesh.n_components):
            cells = mesh.cells[mesh.component_labels[mesh.cells[:, 0]] == c]
            pieces.append((Mesh.from_arrays(mesh.nodes, cells, drop_unused=True), k, f"piece {c} of {what}"))
    return pieces


def _check_apart(placed: list[Mesh], p: dict) -> None:
    """No vertex of one body, or of one piece of a body, may start inside another: they would
    be stuck together (two overlapping copies in one mesh file are refused like two placed bodies)."""
    pieces = _pieces(placed, p)
    for i, (a, a_body, a_what) in enumerate(pieces):
        locator = None
        for j, (b, b_body, b_what) in enumerate(pieces):
            disjoint = np.any(b.nodes.min(0) > a.nodes.max(0)) or np.any(b.nodes.max(0) < a.nodes.min(0))
            if i == j or disjoint:
                continue
            if locator is None:
                locator = CellLocator.build(a)
            status = locate(locator, torch.tensor(b.nodes)).status
            if not bool((status == LocateStatus.INSIDE).any()):
                continue
            if a_body == b_body:
                raise ConfigError(f"params.meshes[{a_body}]: {b_what} overlaps {a_what}: the mesh holds "
                                  "overlapping bodies; remove the copy, or mesh them as one body")
            raise ConfigError(f"params.centers: {b_what} starts inside {a_what}; move them apart")


def build(p: dict) -> Scene:
    meshes = [read_body(entry, k) for k, entry in enumerate(p["meshes"])]
    placed = [place_body(m, c, s) for m, c, s in zip(meshes, p["centers"], p["sizes"], strict=True)]
    body, body_id = merge_bodies(placed)
    v = np.asarray(p["velocities"], float)[body_id]
    domain = box_domain(*box_bounds(p["box"]), p["mesh_size"])
    return contained_bodies(domain, body, v, p, body_id)
