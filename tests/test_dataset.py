"""datagen.dataset: the trajectory file format round-trips, is deterministic, and reports bad files."""


import h5py
import numpy as np
import pytest

from datagen import simulate
from datagen.dataset import FORMAT_VERSION, DatasetError, content_digest, is_complete, load, save
from datagen.trajectory import NodeType

CONFIG = {"scene": "vibrating_bar", "params": {"n_cells": 20}, "output": {"frames": 6}}


@pytest.fixture(scope="module")
def trajectory():
    t = simulate(CONFIG)
    t.node_type = np.full(t.mesh.n_nodes, NodeType.FREE)
    t.node_type[0] = NodeType.CLAMPED
    t.obstacle_nodes = np.array([[-1.0], [30.0]])
    t.obstacle_facets = np.array([[0], [1]])
    return t


def test_round_trip(tmp_path, trajectory):
    path = save(tmp_path / "train" / "00000.h5", trajectory)
    back = load(path)
    np.testing.assert_array_equal(back.positions, trajectory.positions)
    np.testing.assert_array_equal(back.velocities, trajectory.velocities)
    np.testing.assert_array_equal(back.times, trajectory.times)
    np.testing.assert_array_equal(back.mesh.nodes, trajectory.mesh.nodes)
    np.testing.assert_array_equal(back.mesh.cells, trajectory.mesh.cells)
    np.testing.assert_array_equal(back.node_type, trajectory.node_type)
    np.testing.assert_array_equal(back.body_id, np.zeros(trajectory.mesh.n_nodes))
    np.testing.assert_array_equal(back.obstacle_nodes, trajectory.obstacle_nodes)
    np.testing.assert_array_equal(back.frame_wall_times, trajectory.frame_wall_times)
    assert back.config == trajectory.config and back.substeps == trajectory.substeps
    assert back.kernel_rebuilds == trajectory.substeps * 6
    assert set(back.diagnostics) == set(trajectory.diagnostics)
    np.testing.assert_array_equal(back.diagnostics["kinetic_energy"], trajectory.diagnostics["kinetic_energy"])
    assert list(back.diagnostics["probe_names"]) == list(trajectory.diagnostics["probe_names"])
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".")]  # no temporary left
    assert is_complete(path)


def test_same_config_gives_same_file_apart_from_timing(tmp_path):
    a = save(tmp_path / "a.h5", simulate(CONFIG))
    b = save(tmp_path / "b.h5", simulate(CONFIG))
    assert content_digest(a) == content_digest(b)
    # The only byte differences are the timing values: zero them and the files are identical.
    for path in (a, b):
        with h5py.File(path, "r+") as f:
            f.attrs["wall_time"] = 0.0
            f["frames/wall_time"][...] = 0.0
    assert a.read_bytes() == b.read_bytes()


def test_bad_files_are_named(tmp_path, trajectory):
    with pytest.raises(DatasetError, match="does not exist"):
        load(tmp_path / "missing.h5")
    good = save(tmp_path / "good.h5", trajectory)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(DatasetError, match=r"truncated\.h5 is truncated or corrupt"):
        load(truncated)
    assert not is_complete(truncated)
    (tmp_path / "junk.h5").write_text("not hdf5")
    with pytest.raises(DatasetError, match=r"junk\.h5 is not a trajectory file \(not HDF5 at all\)"):
        load(tmp_path / "junk.h5")


def test_schema_errors(tmp_path, trajectory):
    path = save(tmp_path / "t.h5", trajectory)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = FORMAT_VERSION + 1
    with pytest.raises(DatasetError, match=f"has format version {FORMAT_VERSION + 1}, this reader reads versions 1, "
                       f"{FORMAT_VERSION}"):
        load(path)
    path = save(tmp_path / "t.h5", trajectory)
    with h5py.File(path, "r+") as f:
        del f["frames/velocities"]
    with pytest.raises(DatasetError, match="lacks 'frames/velocities'"):
        load(path)
    path = save(tmp_path / "t.h5", trajectory)
    with h5py.File(path, "r+") as f:
        positions = f["frames/positions"][()]
        del f["frames/positions"]
        f["frames/positions"] = positions[:, :-1]
    with pytest.raises(DatasetError, match="'frames/positions' has shape"):
        load(path)
    path = save(tmp_path / "t.h5", trajectory)
    with h5py.File(path, "r+") as f:
        f["mesh/cells"][0] = f["mesh/cells"][0][::-1]
    with pytest.raises(DatasetError, match="its body mesh is invalid: inverted cells"):
        load(path)


def test_written_files_get_ordinary_permissions(tmp_path, trajectory):
    import os

    umask = os.umask(0)
    os.umask(umask)
    path = save(tmp_path / "p.h5", trajectory)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    trajectory.mesh.write(tmp_path / "m.vtu")
    assert (tmp_path / "m.vtu").stat().st_mode & 0o777 == 0o666 & ~umask


def test_a_failed_write_leaves_nothing(tmp_path, trajectory):
    from datagen.atomic import atomic_path

    with pytest.raises(RuntimeError, match="boom"), atomic_path(tmp_path / "x.h5") as tmp:
        tmp.write_text("partial")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
