"""Trajectory files: one HDF5 file per trajectory, versioned, written atomically, read with checks.

Layout (format version 2)::

    /                    attrs: format_version, scene, config (JSON), params (JSON), frame_dt,
                                solver_dt, substeps, n_particles, wall_time, kernel_rebuilds
    /mesh/nodes          (N, d) float64  rest positions of the tracked body vertices
    /mesh/cells          (C, d+1) int64
    /mesh/node_type      (N,) int8       NodeType codes
    /mesh/body_id        (N,) int32
    /obstacles/nodes     (M, d) float64  wall / container geometry at frame 0 (M may be 0)
    /obstacles/facets    (F, d) int64    its segments (2D) or triangles (3D)
    /frames/positions    (T, N, d) float64
    /frames/velocities   (T, N, d) float64
    /frames/times        (T,) float64
    /frames/wall_time    (T,) float64    solver seconds spent reaching each frame (0 for frame 0)
    /frames/obstacle_positions (T, M, d) float64  optional: the obstacle nodes at each frame, where
                                         obstacles move (kinematic); absent: they stay at /obstacles/nodes
    /diagnostics/<name>  (T, ...)        per-frame solver diagnostics
    /fields/<name>       (...)           optional: a converted source dataset's own fields, exactly

Version 1 is the same layout without ``/frames/obstacle_positions``; the reader reads both.
Files are written under a temporary name in the target folder and renamed when complete, so a
crash never leaves a partial file under the final name. Object timestamps are off, so the same
trajectory gives the same bytes apart from the timing fields (wall times).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from datagen.atomic import atomic_path
from datagen.mesh import Mesh, MeshError
from datagen.trajectory import NodeType, Trajectory

__all__ = ["FORMAT_VERSION", "DatasetError", "save", "load", "is_complete", "content_digest"]

FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)  # version 1: no /frames/obstacle_positions (static obstacles only)
TIMING_FIELDS = ("wall_time", "frames/wall_time")


class DatasetError(ValueError):
    """A trajectory file or dataset folder that cannot be used; the message names the file."""


def _json(value) -> str:
    return json.dumps(value, sort_keys=True, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


def _put(group, name: str, array) -> None:
    group.create_dataset(name, data=np.asarray(array), track_times=False)


def save(path, trajectory) -> Path:
    """Write ``trajectory`` (a :class:`datagen.trajectory.Trajectory`) to ``path`` atomically; returns the path."""
    import h5py

    path = Path(path)
    t = trajectory
    n, d = t.mesh.nodes.shape
    node_type = np.zeros(n, np.int8) if t.node_type is None else np.asarray(t.node_type, np.int8)
    body_id = np.zeros(n, np.int32) if t.body_id is None else np.asarray(t.body_id, np.int32)
    obstacle_nodes = np.zeros((0, d)) if t.obstacle_nodes is None else np.asarray(t.obstacle_nodes, float)
    obstacle_facets = np.zeros((0, d), np.int64) if t.obstacle_facets is None else np.asarray(t.obstacle_facets)
    frame_wall = np.zeros(len(t.times)) if t.frame_wall_times is None else np.asarray(t.frame_wall_times, float)
    moving = None if t.obstacle_positions is None else _obstacle_positions(t, obstacle_nodes)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            attrs = {
                "format_version": FORMAT_VERSION, "scene": str(t.config.get("scene", "")),
                "config": _json(t.config), "params": _json(t.config.get("params", {})),
                "frame_dt": float(np.diff(t.times).mean()) if len(t.times) > 1 else 0.0,
                "solver_dt": float(t.dt), "substeps": int(t.substeps), "n_particles": int(t.n_particles),
                "wall_time": float(t.wall_time), "kernel_rebuilds": int(t.kernel_rebuilds or 0),
            }
            for key, value in attrs.items():
                f.attrs[key] = value
            mesh = f.create_group("mesh", track_order=True)
            for name, array in (("nodes", t.mesh.nodes), ("cells", t.mesh.cells), ("node_type", node_type),
                                ("body_id", body_id)):
                _put(mesh, name, array)
            obstacles = f.create_group("obstacles", track_order=True)
            _put(obstacles, "nodes", obstacle_nodes)
            _put(obstacles, "facets", obstacle_facets)
            frames = f.create_group("frames", track_order=True)
            for name, array in (("positions", t.positions), ("velocities", t.velocities), ("times", t.times),
                                ("wall_time", frame_wall)):
                _put(frames, name, array)
            if moving is not None:
                _put(frames, "obstacle_positions", moving)
            diagnostics = f.create_group("diagnostics", track_order=True)
            for name, array in sorted(t.diagnostics.items()):
                array = np.asarray(array)
                _put(diagnostics, name, array.astype("S") if array.dtype.kind == "U" else array)
            if t.fields:
                fields = f.create_group("fields", track_order=True)
                for name, array in t.fields.items():
                    _put(fields, name, array)
    return path


def _obstacle_positions(t, obstacle_nodes: np.ndarray) -> np.ndarray:
    """The trajectory's (T, M, d) float64 obstacle positions, checked against its frames and obstacle nodes."""
    moving = np.asarray(t.obstacle_positions, np.float64)
    expected = (len(t.times), *obstacle_nodes.shape)
    if moving.shape != expected:
        raise ValueError(f"Trajectory.obstacle_positions has shape {moving.shape}, expected {expected} "
                         "(one row of obstacle_nodes per frame); give obstacle_nodes with the moving obstacles")
    return moving


def is_complete(path) -> bool:
    """True when ``path`` is a trajectory file this reader reads (format version 1 or 2)."""
    try:
        load(path)
    except DatasetError:
        return False
    return True


def content_digest(path) -> str:
    """sha256 of every array and attribute of a trajectory file except the timing fields.

    Two files with the same digest hold the same trajectory (the same config and index give
    the same digest whatever machine, worker or shard generated them).
    """
    import hashlib

    import h5py

    digest = hashlib.sha256()
    with h5py.File(path, "r") as f:
        def visit(name, item):
            if isinstance(item, h5py.Dataset) and name not in TIMING_FIELDS:
                digest.update(name.encode() + item[()].tobytes())

        f.visititems(visit)
        for key in sorted(f.attrs):
            if key not in TIMING_FIELDS:
                digest.update(f"{key}={f.attrs[key]}".encode())
    return digest.hexdigest()


_REQUIRED = {
    "mesh/nodes": 2, "mesh/cells": 2, "mesh/node_type": 1, "mesh/body_id": 1, "obstacles/nodes": 2,
    "obstacles/facets": 2, "frames/positions": 3, "frames/velocities": 3, "frames/times": 1, "frames/wall_time": 1,
}


def _checked_arrays(f, path: Path) -> dict:
    version = f.attrs.get("format_version")
    if version not in READABLE_VERSIONS:
        raise DatasetError(f"trajectory file {path} has format version {version}, this reader reads versions "
                           f"{', '.join(map(str, READABLE_VERSIONS))}; regenerate it with python -m datagen")
    arrays = {}
    for name, ndim in _REQUIRED.items():
        if name not in f:
            raise DatasetError(f"trajectory file {path} lacks '{name}'; it is not a bsms trajectory or is damaged")
        arrays[name] = f[name][()]
        if arrays[name].ndim != ndim:
            raise DatasetError(f"trajectory file {path}: '{name}' has {arrays[name].ndim} dimensions, expected {ndim}")
    n, d = arrays["mesh/nodes"].shape
    t = arrays["frames/times"].shape[0]
    for name in ("frames/positions", "frames/velocities"):
        if arrays[name].shape != (t, n, d):
            raise DatasetError(f"trajectory file {path}: '{name}' has shape {arrays[name].shape}, expected "
                               f"({t}, {n}, {d}) from its times and mesh")
    for name in ("mesh/node_type", "mesh/body_id"):
        if arrays[name].shape != (n,):
            raise DatasetError(f"trajectory file {path}: '{name}' has shape {arrays[name].shape}, expected ({n},)")
    if arrays["frames/wall_time"].shape != (t,):
        raise DatasetError(f"trajectory file {path}: 'frames/wall_time' must have one entry per frame ({t})")
    if "frames/obstacle_positions" in f:
        arrays["frames/obstacle_positions"] = _moving_obstacles(f, arrays, int(version), path)
    _check_values(arrays, path)
    return arrays


def _moving_obstacles(f, arrays: dict, version: int, path: Path) -> np.ndarray:
    """The (T, M, d) obstacle positions of a version 2 file, checked against its frames and obstacle nodes."""
    moving = f["frames/obstacle_positions"][()]
    expected = (len(arrays["frames/times"]), *arrays["obstacles/nodes"].shape)
    if version < 2:
        raise DatasetError(f"trajectory file {path} holds 'frames/obstacle_positions' but says format version "
                           f"{version}, which has none; it is damaged: regenerate it with python -m datagen")
    if moving.shape != expected:
        raise DatasetError(f"trajectory file {path}: 'frames/obstacle_positions' has shape {moving.shape}, expected "
                           f"{expected} (one row of 'obstacles/nodes' per frame of 'frames/times'); regenerate it "
                           "with python -m datagen")
    return moving


def _check_values(arrays: dict, path: Path) -> None:
    """Values a trajectory must hold: finite, strictly increasing times, finite states, known node types."""
    times = arrays["frames/times"]
    if len(times) == 0:
        raise DatasetError(f"trajectory file {path} holds no frames")
    if not np.isfinite(times).all():
        frame = int(np.flatnonzero(~np.isfinite(times))[0])
        raise DatasetError(f"trajectory file {path}: 'frames/times' holds NaN or inf at frame {frame}; regenerate it")
    backwards = np.flatnonzero(np.diff(times) <= 0)
    if backwards.size:
        k = int(backwards[0]) + 1
        raise DatasetError(f"trajectory file {path}: 'frames/times' must increase strictly, but frame {k} is at "
                           f"t = {times[k]:.6g} after t = {times[k - 1]:.6g}; regenerate it or fix its times")
    for name in ("frames/positions", "frames/velocities", "frames/obstacle_positions"):
        if name not in arrays:
            continue
        finite = np.isfinite(arrays[name]).all(axis=(1, 2))
        if not finite.all():
            frame = int(np.flatnonzero(~finite)[0])
            raise DatasetError(f"trajectory file {path}: '{name}' holds NaN or inf from frame {frame} on; the "
                               "simulation diverged: regenerate it (smaller solver.dt or cfl), or drop the file")
    codes = np.unique(arrays["mesh/node_type"])
    unknown = sorted(set(codes.tolist()) - {int(t) for t in NodeType})
    if unknown:
        known = ", ".join(f"{int(t)} ({t.name})" for t in NodeType)
        raise DatasetError(f"trajectory file {path}: 'mesh/node_type' holds unknown codes {unknown}; "
                           f"the node types are {known}")


def load(path):
    """Read a trajectory file into a :class:`datagen.Trajectory`, checking the schema.

    Raises DatasetError naming the file for a missing, truncated or corrupt file, a different
    format version, missing or inconsistent arrays, or an invalid body mesh.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"trajectory file {path} does not exist")
    if not h5py.is_hdf5(path):
        raise DatasetError(f"{path} is not a trajectory file (not HDF5 at all); give a trajectory .h5 written "
                           "by python -m datagen (a mesh file goes to Mesh.read or bsms.infer --mesh)")
    try:
        with h5py.File(path, "r") as f:
            arrays = _checked_arrays(f, path)
            attrs = dict(f.attrs)
            diagnostics = {name: f["diagnostics"][name][()] for name in f.get("diagnostics", {})}
            fields = {name: f["fields"][name][()] for name in f["fields"]} if "fields" in f else None
    except DatasetError:
        raise
    except (OSError, KeyError, ValueError) as exc:
        raise DatasetError(f"trajectory file {path} is truncated or corrupt ({exc}); delete it and "
                           "regenerate it with python -m datagen (complete files are skipped)") from None
    try:
        mesh = Mesh(arrays["mesh/nodes"], arrays["mesh/cells"])
    except MeshError as exc:
        raise DatasetError(f"trajectory file {path}: its body mesh is invalid: {exc}") from None
    if "probe_names" in diagnostics:
        diagnostics["probe_names"] = diagnostics["probe_names"].astype(str)
    return Trajectory(
        mesh=mesh, positions=arrays["frames/positions"], velocities=arrays["frames/velocities"],
        times=arrays["frames/times"], diagnostics=diagnostics, wall_time=float(attrs["wall_time"]),
        config=json.loads(attrs["config"]), dt=float(attrs["solver_dt"]), substeps=int(attrs["substeps"]),
        n_particles=int(attrs["n_particles"]), frame_wall_times=arrays["frames/wall_time"],
        node_type=arrays["mesh/node_type"].astype(np.int64), body_id=arrays["mesh/body_id"].astype(np.int64),
        obstacle_nodes=arrays["obstacles/nodes"], obstacle_facets=arrays["obstacles/facets"],
        obstacle_positions=arrays.get("frames/obstacle_positions"), kernel_rebuilds=int(attrs["kernel_rebuilds"]),
        fields=fields,
    )
