"""DeepMind's MeshGraphNets datasets, read without TensorFlow.

A dataset folder holds ``meta.json`` and ``{train,valid,test}.tfrecord``. ``meta.json`` gives
``field_names``, ``features`` (per field: ``type`` static | dynamic | dynamic_varlen, ``shape``
with at most one -1, ``dtype``), ``trajectory_length`` and optionally ``collision_radius``.
Each record is one trajectory: a ``tf.train.Example`` whose feature per field is the raw bytes
of the array. Static fields have shape ``(1, N, F)`` (one copy for every frame), dynamic ones
``(T, N, F)``, and a dynamic_varlen field ``(sum of N_t, F)`` with a companion int32 feature
``length_<field>`` holding the T row counts N_t.

Records are parsed with the ``tfrecord`` package's protobuf schema and framed by
:mod:`bsms.datasets.tfrecord`, which checks every CRC32C; memory stays that of one record.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bsms.datasets.errors import SourceError
from bsms.datasets.tfrecord import read_records

__all__ = ["MetaField", "Meta", "parse_example", "read_split", "SPLITS", "KINDS"]

SPLITS = ("train", "valid", "test")
KINDS = ("static", "dynamic", "dynamic_varlen")


@dataclass(frozen=True)
class MetaField:
    """One field of meta.json: kind (static, dynamic or dynamic_varlen), shape, dtype."""

    name: str
    kind: str
    shape: tuple[int, ...]
    dtype: np.dtype


def _field(path: Path, name: str, spec) -> MetaField:
    if not isinstance(spec, dict) or not {"type", "shape", "dtype"} <= set(spec):
        raise SourceError(path, "each entry of 'features' needs type, shape and dtype", field=name)
    if spec["type"] not in KINDS:
        raise SourceError(path, f"type {spec['type']!r} is not one of {', '.join(KINDS)}", field=name)
    shape = spec["shape"]
    if not isinstance(shape, list) or not all(isinstance(s, int) and (s > 0 or s == -1) for s in shape) \
            or shape.count(-1) > 1:
        raise SourceError(path, f"shape {shape!r} must be a list of positive sizes with at most one -1", field=name)
    try:
        dtype = np.dtype(str(spec["dtype"]))
    except TypeError:
        raise SourceError(path, f"dtype {spec['dtype']!r} is not a numpy dtype name (e.g. float32, int32); fix "
                                "meta.json", field=name) from None
    return MetaField(name, spec["type"], tuple(shape), dtype)


@dataclass(frozen=True)
class Meta:
    """A dataset's checked ``meta.json``."""

    path: Path
    fields: dict[str, MetaField]
    trajectory_length: int
    collision_radius: float | None = None

    @classmethod
    def read(cls, folder) -> Meta:
        path = Path(folder) / "meta.json"
        if not path.is_file():
            raise SourceError(path, "the file does not exist: a DeepMind dataset folder holds meta.json and "
                                    "{train,valid,test}.tfrecord (download them together)")
        try:
            meta = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise SourceError(path, f"not valid JSON ({exc})") from None
        missing = [k for k in ("field_names", "features", "trajectory_length") if k not in meta]
        if missing:
            raise SourceError(path, f"lacks {', '.join(missing)}")
        features = meta["features"]
        unlisted = [name for name in meta["field_names"] if name not in features and not name.startswith("length_")]
        if unlisted:
            raise SourceError(path, "the field is in field_names but has no entry in features", field=unlisted[0])
        length = meta["trajectory_length"]
        if isinstance(length, bool) or not isinstance(length, int) or length < 1:
            raise SourceError(path, f"trajectory_length must be a positive integer, got {length!r}")
        fields = {name: _field(path, name, spec) for name, spec in features.items()}
        radius = meta.get("collision_radius")
        return cls(path, fields, length, None if radius is None else float(radius))


def _feature_bytes(example, name: str, path: Path, index: int) -> bytes:
    feature = example.features.feature
    if name not in feature:
        raise SourceError(path, "the record lacks this field that meta.json lists", record=index, field=name)
    values = feature[name].bytes_list.value
    if not values:
        raise SourceError(path, "the field holds no raw bytes (DeepMind stores each field as one bytes value)",
                          record=index, field=name)
    return b"".join(values)


def _array(raw: bytes, dtype: np.dtype, shape: tuple[int, ...], path: Path, index: int, name: str) -> np.ndarray:
    if len(raw) % dtype.itemsize:
        raise SourceError(path, f"{len(raw)} bytes are not a whole number of {dtype} values", record=index, field=name)
    values = np.frombuffer(raw, dtype=dtype)
    known = int(np.prod([s for s in shape if s != -1]))
    if (-1 in shape and values.size % known) or (-1 not in shape and values.size != known):
        raise SourceError(path, f"{values.size} {dtype} values do not fit shape {list(shape)} from meta.json",
                          record=index, field=name)
    return values.reshape(shape).copy()


def parse_example(data: bytes, meta: Meta, path, index: int) -> dict:
    """One record -> ``{field: array}``: static (1, N, F), dynamic (T, N, F), and for a
    dynamic_varlen field its rows of every frame, (sum of N_t, F), with ``length_<field>`` (T,)
    (split them with ``numpy.split(values, numpy.cumsum(lengths)[:-1])``)."""
    from google.protobuf.message import DecodeError
    from tfrecord import example_pb2

    path = Path(path)
    try:
        example = example_pb2.Example.FromString(data)
    except DecodeError as exc:
        raise SourceError(path, f"the record is not a tf.train.Example ({exc})", record=index) from None
    out = {}
    for name, spec in meta.fields.items():
        array = _array(_feature_bytes(example, name, path, index), spec.dtype, spec.shape, path, index, name)
        if spec.kind == "dynamic" and array.shape[0] != meta.trajectory_length:
            raise SourceError(path, f"{array.shape[0]} frames, but trajectory_length is {meta.trajectory_length}",
                              record=index, field=name)
        if spec.kind == "dynamic_varlen":
            lengths = _array(_feature_bytes(example, f"length_{name}", path, index), np.dtype(np.int32), (-1,),
                             path, index, f"length_{name}")
            if lengths.sum() != len(array) or (lengths < 0).any() or len(lengths) != meta.trajectory_length:
                raise SourceError(path, f"length_{name} gives {len(lengths)} frames summing to {int(lengths.sum())} "
                                        f"rows; the field has {len(array)} rows and trajectory_length is "
                                        f"{meta.trajectory_length}", record=index, field=name)
            out[f"length_{name}"] = lengths
        out[name] = array
    return out


def read_split(folder, split: str) -> Iterator[tuple[int, dict]]:
    """(record index, trajectory) of ``split`` in a DeepMind dataset folder, one at a time."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    meta = Meta.read(folder)
    path = Path(folder) / f"{split}.tfrecord"
    for index, data in enumerate(read_records(path)):
        yield index, parse_example(data, meta, path, index)
