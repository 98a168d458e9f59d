"""bsms.datasets: DeepMind's MeshGraphNets layout (files written by the separate ``tfrecord``
package's writer) and the BSMS-GNN authors' h5 files are read without TensorFlow, checked
(CRC32C, meta.json, shapes) and converted into the project's trajectory files exactly."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from tfrecord import TFRecordWriter

from bsms.datasets import SourceError, authors, deepmind
from bsms.datasets.__main__ import main
from bsms.datasets.convert import convert
from bsms.datasets.tfrecord import frame_record, read_records
from datagen import shapes
from datagen.dataset import load

T = 5


def _cylinder_flow(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    mesh = shapes.rectangle(1.6, 0.4, 0.1)
    n = mesh.n_nodes
    node_type = np.where(mesh.boundary_node_mask, 6, 0).astype(np.int32)
    node_type[np.isclose(mesh.nodes[:, 0], 0.0)] = 4
    node_type[np.isclose(mesh.nodes[:, 0], 1.6)] = 5
    return {
        "cells": mesh.cells.astype(np.int32)[None], "mesh_pos": mesh.nodes.astype(np.float32)[None],
        "node_type": node_type[None, :, None],
        "velocity": rng.normal(size=(T, n, 2)).astype(np.float32),
        "pressure": rng.normal(size=(T, n, 1)).astype(np.float32),
    }


def _plate(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    mesh = shapes.box((0.4, 0.1, 0.4), 0.1)
    n = mesh.n_nodes
    world = mesh.nodes[None] + np.cumsum(rng.normal(scale=1e-3, size=(T, n, 3)), axis=0)
    return {
        "cells": mesh.cells.astype(np.int32)[None], "mesh_pos": mesh.nodes.astype(np.float32)[None],
        "node_type": np.where(mesh.nodes[:, 1] > 0.09, 3, 0).astype(np.int32)[None, :, None],
        "world_pos": world.astype(np.float32), "stress": rng.normal(size=(T, n, 1)).astype(np.float32),
    }


def _spec(array: np.ndarray, kind: str) -> dict:
    shape = list(array.shape)
    shape[1] = -1
    return {"type": kind, "shape": shape, "dtype": str(array.dtype)}


def _write_deepmind(folder, make, counts=(("train", 2), ("test", 1))) -> dict:
    """A dataset folder in DeepMind's layout; returns the trajectories written, by split."""
    folder.mkdir(parents=True, exist_ok=True)
    written = {}
    for split, count in counts:
        writer = TFRecordWriter(str(folder / f"{split}.tfrecord"))
        written[split] = [make(10 * len(written) + k) for k in range(count)]
        for traj in written[split]:
            writer.write({name: (array.tobytes(), "byte") for name, array in traj.items()})
        writer.close()
    first = written[counts[0][0]][0]
    meta = {"field_names": list(first), "trajectory_length": T,
            "features": {name: _spec(a, "static" if a.shape[0] == 1 else "dynamic") for name, a in first.items()}}
    (folder / "meta.json").write_text(json.dumps(meta))
    return written


@pytest.mark.parametrize("make", [_cylinder_flow, _plate])
def test_deepmind_files_read_and_convert_exactly(tmp_path, make):
    written = _write_deepmind(tmp_path / "src", make)
    for split, trajectories in written.items():
        read = list(deepmind.read_split(tmp_path / "src", split))
        assert [i for i, _ in read] == list(range(len(trajectories)))
        for (_, fields), source in zip(read, trajectories, strict=True):
            assert fields.keys() == source.keys()
            for name, array in source.items():
                assert fields[name].dtype == array.dtype and np.array_equal(fields[name], array), name
    assert convert("deepmind", tmp_path / "src", tmp_path / "dst", progress=False) == {"train": 2, "test": 1}
    back = load(tmp_path / "dst" / "train" / "00001.h5")
    source = written["train"][1]
    for name, array in source.items():
        assert back.fields[name].dtype == array.dtype and np.array_equal(back.fields[name], array), name
    assert back.positions.shape == (T, source["mesh_pos"].shape[1], source["mesh_pos"].shape[2])
    if "world_pos" in source:
        np.testing.assert_array_equal(back.positions, source["world_pos"].astype(np.float64))
        np.testing.assert_allclose(back.velocities[1:], np.diff(source["world_pos"].astype(np.float64), axis=0),
                                   rtol=0, atol=0)
    else:
        assert (back.positions == back.mesh.nodes).all() and (back.velocities == 0).all()
    codes = source["node_type"][0, :, 0]
    assert ((back.node_type == 0) == np.isin(codes, [0, 5])).all(), "NORMAL and OUTFLOW nodes are integrated"


def test_conversion_resumes_and_the_cli_reports(tmp_path, capsys):
    _write_deepmind(tmp_path / "src", _cylinder_flow)
    assert main(["convert", "deepmind", str(tmp_path / "src"), str(tmp_path / "dst"), "--quiet"]) == 0
    assert "train: 2 trajectories, test: 1 trajectories" in capsys.readouterr().out
    done = tmp_path / "dst" / "train" / "00000.h5"
    stamp = done.stat().st_mtime_ns
    (tmp_path / "dst" / "train" / "00001.h5").unlink()  # as if killed before it
    assert main(["convert", "deepmind", str(tmp_path / "src"), str(tmp_path / "dst"), "--quiet"]) == 0
    assert done.stat().st_mtime_ns == stamp and (tmp_path / "dst" / "train" / "00001.h5").is_file()


def test_dynamic_varlen_fields_come_with_their_lengths(tmp_path):
    folder = tmp_path / "src"
    folder.mkdir()
    rows = np.array([3, 5, 4, 4, 2], np.int32)
    values = np.arange(rows.sum() * 2, dtype=np.float32).reshape(-1, 2)
    writer = TFRecordWriter(str(folder / "train.tfrecord"))
    writer.write({"sizing": (values.tobytes(), "byte"), "length_sizing": (rows.tobytes(), "byte")})
    writer.close()
    (folder / "meta.json").write_text(json.dumps({
        "field_names": ["sizing", "length_sizing"], "trajectory_length": T,
        "features": {"sizing": {"type": "dynamic_varlen", "shape": [-1, 2], "dtype": "float32"}}}))
    (_, fields), = deepmind.read_split(folder, "train")
    np.testing.assert_array_equal(fields["length_sizing"], rows)
    frames = np.split(fields["sizing"], np.cumsum(fields["length_sizing"])[:-1])
    assert [len(f) for f in frames] == rows.tolist() and np.array_equal(np.concatenate(frames), values)


def _flip_byte(path, offset_from_end: int) -> None:
    data = bytearray(path.read_bytes())
    data[-offset_from_end] ^= 0x01
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(("damage", "words"), [
    (lambda p: _flip_byte(p, 40), r"test\.tfrecord, record 0: the data checksum does not match \(CRC32C\)"),
    (lambda p: p.write_bytes(p.read_bytes()[:-7]), r"test\.tfrecord, record 0: the file ends inside the record"),
    (lambda p: p.write_bytes(p.read_bytes()[:5]), r"test\.tfrecord, record 0: the file ends inside a record's length"),
    (lambda p: p.write_bytes(b"\x00" * 8 + p.read_bytes()[8:]), r"record 0: the length checksum does not match"),
])
def test_corrupt_records_name_the_file_and_record(tmp_path, damage, words):
    _write_deepmind(tmp_path / "src", _cylinder_flow)
    damage(tmp_path / "src" / "test.tfrecord")
    with pytest.raises(SourceError, match=words):
        list(deepmind.read_split(tmp_path / "src", "test"))
    assert len(list(deepmind.read_split(tmp_path / "src", "train"))) == 2, "the other split is untouched"


@pytest.mark.parametrize(("edit", "words"), [
    (lambda m: m["features"].update(wind={"type": "dynamic", "shape": [T, -1, 2], "dtype": "float32"}),
     r"train\.tfrecord, record 0, field 'wind': the record lacks this field that meta\.json lists"),
    (lambda m: m["features"]["velocity"].update(shape=[T, -1, 3]),
     r"train\.tfrecord, record 0, field 'velocity': \d+ float32 values do not fit shape \[5, -1, 3\]"),
    (lambda m: m["features"]["velocity"].update(shape=[T + 1, -1, 2]),
     r"record 0, field 'velocity': \d+ float32 values do not fit shape"),
    (lambda m: m["features"]["pressure"].update(type="dense"), r"meta\.json, field 'pressure': type 'dense' is not"),
    (lambda m: m["features"]["pressure"].update(dtype="<dtype: 'float32'>"), r"field 'pressure': dtype .* is not a numpy"),
    (lambda m: m["field_names"].append("density"), r"meta\.json, field 'density': the field is in field_names but"),
    (lambda m: m.pop("trajectory_length"), r"meta\.json: lacks trajectory_length"),
])
def test_meta_and_shape_errors_name_file_record_and_field(tmp_path, edit, words):
    _write_deepmind(tmp_path / "src", _cylinder_flow)
    meta = json.loads((tmp_path / "src" / "meta.json").read_text())
    edit(meta)
    (tmp_path / "src" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(SourceError, match=words):
        list(deepmind.read_split(tmp_path / "src", "train"))


def test_cli_errors_are_one_line(tmp_path, capsys):
    _write_deepmind(tmp_path / "src", _cylinder_flow)
    _flip_byte(tmp_path / "src" / "train.tfrecord", 40)
    assert main(["convert", "deepmind", str(tmp_path / "src"), str(tmp_path / "dst"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "train.tfrecord, record 1: the data checksum" in err
    assert main(["convert", "deepmind", str(tmp_path / "nothing"), str(tmp_path / "dst"), "--quiet"]) == 2
    assert "nothing/meta.json: the file does not exist" in capsys.readouterr().err


def test_framing_matches_the_independent_writer(tmp_path):
    writer = TFRecordWriter(str(tmp_path / "x.tfrecord"))
    writer.write({"a": (b"\x01\x02\x03", "byte")})
    writer.close()
    raw = (tmp_path / "x.tfrecord").read_bytes()
    (record,) = read_records(tmp_path / "x.tfrecord")
    assert frame_record(record) == raw


def test_authors_files_convert_exactly(tmp_path):
    written = {}
    for split, count in (("train", 2), ("valid", 1)):
        (tmp_path / "src" / split).mkdir(parents=True)
        for k in range(count):
            source = _cylinder_flow(k)
            tiled = {name: np.repeat(a, T, axis=0) if a.shape[0] == 1 else a for name, a in source.items()}
            with h5py.File(tmp_path / "src" / split / f"{k}.h5", "w") as f:
                for name, array in tiled.items():
                    f.create_dataset(name, data=array)
            written[(split, k)] = tiled
    assert convert("authors", tmp_path / "src", tmp_path / "dst", progress=False) == {"train": 2, "valid": 1}
    for (split, k), source in written.items():
        back = load(tmp_path / "dst" / split / f"{k:05d}.h5")
        for name, array in source.items():
            assert np.array_equal(back.fields[name], array) and back.fields[name].dtype == array.dtype
    with h5py.File(tmp_path / "src" / "train" / "0.h5", "a") as f:
        del f["pressure"]
    with pytest.raises(SourceError, match=r"0\.h5, field 'pressure': the file lacks this field"):
        authors.read_trajectory(tmp_path / "src" / "train" / "0.h5", ["mesh_pos", "pressure"])
