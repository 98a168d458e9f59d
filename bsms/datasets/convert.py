"""Convert a source dataset into the project's trajectory files.

``python -m bsms.datasets convert deepmind SRC DST`` (DeepMind's meta.json + TFRecords) and
``python -m bsms.datasets convert authors SRC DST`` (the BSMS-GNN authors' h5 files) write
``DST/<split>/<index:05d>.h5`` in the format of :mod:`datagen.dataset`, atomically; complete
files are skipped, so an interrupted conversion resumes. Every source field is kept exactly in
``Trajectory.fields``. The body mesh is the first frame's ``mesh_pos`` and ``cells``;
positions are ``world_pos`` where the data has it in the mesh's dimension (Lagrangian solids)
and the fixed ``mesh_pos`` otherwise (Eulerian flows; cloth, whose 3D ``world_pos`` lives on a
2D material mesh, keeps its world positions in the field); velocities are their backward
differences over ``dt``. Each connected part of the mesh is a body of its own (``body_id``:
the plate and its actuator touch through contact edges). DeepMind's node types keep their
meaning in ``fields['node_type']``; the trajectory's ``node_type`` gives each node's role:
NORMAL and OUTFLOW nodes are integrated (FREE), OBSTACLE nodes are obstacles, and the rest
(airfoil, handle, inflow, wall boundary) are prescribed (CLAMPED). What a learned simulator
reads and writes is stored in the config as ``field_spec`` (:func:`bsms.fields.infer_spec`).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bsms.datasets import authors, deepmind
from bsms.datasets.errors import SourceError
from bsms.fields import infer_spec
from datagen.config import output_folder
from datagen.dataset import is_complete, save
from datagen.mesh import Mesh, MeshError
from datagen.trajectory import NodeType, Trajectory

__all__ = ["DEEPMIND_NODE_TYPES", "to_trajectory", "convert"]

DEEPMIND_NODE_TYPES = {"NORMAL": 0, "OBSTACLE": 1, "AIRFOIL": 2, "HANDLE": 3, "INFLOW": 4, "OUTFLOW": 5,
                       "WALL_BOUNDARY": 6}
_ROLE = {0: NodeType.FREE, 5: NodeType.FREE, 1: NodeType.OBSTACLE}


def _first(array: np.ndarray) -> np.ndarray:
    return array[0] if array.ndim == 3 else array


def to_trajectory(fields: dict, dt: float, source: str, where: tuple, collision_radius: float | None = None
                  ) -> Trajectory:
    """A :class:`Trajectory` of one source trajectory ``{field: array}``; ``where`` = (path, record);
    collision_radius: meta.json's world-edge radius, kept in the config where given."""
    for name in ("mesh_pos", "cells", "node_type"):
        if name not in fields:
            raise SourceError(where[0], "the trajectory lacks this field, which every mesh dataset has",
                              record=where[1], field=name)
    if any(name.startswith("length_") for name in fields):
        raise SourceError(where[0], "dynamic_varlen fields (datasets that remesh every frame) do not fit the "
                                    "trajectory format yet", record=where[1])
    try:
        mesh = Mesh.from_arrays(_first(fields["mesh_pos"]).astype(np.float64), _first(fields["cells"]), orient=True)
    except MeshError as exc:
        raise SourceError(where[0], f"its mesh is not usable: {exc}", record=where[1], field="cells") from None
    frames = max(a.shape[0] for a in fields.values() if a.ndim == 3)
    try:
        spec = infer_spec(fields, mesh.dim)
    except ValueError as exc:
        raise SourceError(where[0], str(exc), record=where[1]) from None
    world = fields.get("world_pos")
    if world is not None and (world.ndim != 3 or world.shape[1] != mesh.n_nodes or not mesh.dim <= world.shape[2] <= 3):
        raise SourceError(where[0], f"world_pos has shape {world.shape[1:]} per frame but the mesh has "
                                    f"{mesh.n_nodes} nodes in {mesh.dim}D", record=where[1], field="world_pos")
    if world is not None and not spec.positions:
        positions = world.astype(np.float64)
    else:
        positions = np.broadcast_to(mesh.nodes, (frames, *mesh.nodes.shape)).copy()
    velocities = np.zeros_like(positions)
    velocities[1:] = np.diff(positions, axis=0) / dt
    velocities[0] = velocities[1] if len(positions) > 1 else 0.0
    codes = _first(fields["node_type"]).reshape(-1)
    node_type = np.array([_ROLE.get(int(c), NodeType.CLAMPED) for c in codes], dtype=np.int64)
    return Trajectory(
        mesh=mesh, positions=positions, velocities=velocities, times=np.arange(len(positions)) * dt,
        diagnostics={}, wall_time=0.0, dt=dt,
        config={"source": source, "record": int(where[1]), "dt": dt, "field_spec": spec.to_dict(),
                **({} if collision_radius is None else {"collision_radius": collision_radius})},
        substeps=1, n_particles=mesh.n_nodes, frame_wall_times=np.zeros(len(positions)), node_type=node_type,
        body_id=mesh.component_labels.astype(np.int64), fields=dict(fields),
    )


def _sources(kind: str, src, split: str) -> Iterator[tuple[int, dict, Path]]:
    if kind == "deepmind":
        path = Path(src) / f"{split}.tfrecord"
        for index, fields in deepmind.read_split(src, split):
            yield index, fields, path
    elif kind == "authors":
        for index, fields in authors.read_split(src, split):
            yield index, fields, Path(src) / split / f"{index}.h5"
    else:
        raise ValueError(f"kind must be deepmind or authors, got {kind!r}")


def convert(kind: str, src, dst, *, splits=("train", "valid", "test"), dt: float = 1.0,
            progress: bool = True) -> dict[str, int]:
    """Write ``dst/<split>/<index:05d>.h5`` for every trajectory of ``splits`` found in ``src``;
    returns the number of trajectories per split (complete files are kept, not rewritten)."""
    from tqdm import tqdm

    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    radius = None
    if kind == "deepmind":  # a missing or bad meta.json is named before anything is written
        radius = deepmind.Meta.read(src).collision_radius
    dst = output_folder(dst, "DST")
    counts = {}
    for split in splits:
        if kind == "deepmind" and not (Path(src) / f"{split}.tfrecord").is_file():
            continue
        if kind == "authors" and not (Path(src) / split).is_dir():
            continue
        counts[split] = 0
        for index, fields, path in tqdm(_sources(kind, src, split), desc=split, unit="traj", disable=not progress):
            target = dst / split / f"{index:05d}.h5"
            if not (target.exists() and is_complete(target)):
                save(target, to_trajectory(fields, dt, f"{kind}:{path}", (path, index), radius))
            counts[split] += 1
    if not counts:
        wanted = "{train,valid,test}.tfrecord" if kind == "deepmind" else "train/, valid/ or test/ folders of .h5 files"
        raise SourceError(src, f"no split found: expected {wanted}")
    return counts
