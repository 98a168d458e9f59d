"""Hostile inputs, as a new user makes them: each gives one clear error (its type or exit status
and the words that name the thing and the fix) or, where stated, a correct result.

API cases run in-process; CLI cases run the real entry points in a subprocess and also check
that no traceback reaches the user. Faults (signals during training) are in test_faults.py.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml

from datagen import shapes, simulate
from datagen.config import ConfigError
from datagen.dataset import DatasetError, load, save
from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.mesh import Mesh, MeshError
from datagen.simulation import resolve_config

TINY_BAR = {"scene": "vibrating_bar", "params": {"n_cells": 8}, "output": {"frames": 3}}


@pytest.fixture(scope="module")
def disk() -> Mesh:
    return shapes.disk(0.1, size=0.03)


@pytest.fixture(scope="module")
def trajectory_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("traj") / "good.h5"
    return save(path, simulate(TINY_BAR))


def _edited_copy(source, tmp_path, name: str, edit) -> str:
    """A copy of trajectory file ``source`` with ``edit(h5py.File)`` applied."""
    path = tmp_path / name
    path.write_bytes(source.read_bytes())
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def _replace(f, name: str, value) -> None:
    del f[name]
    f.create_dataset(name, data=value)


def _unmerged_halves() -> tuple[np.ndarray, np.ndarray]:
    """Two unit squares meshed apart and concatenated without merging their shared side: one
    rectangle as a mesher exports it when its seam nodes are not merged (it falls in two)."""
    left, right = shapes.rectangle(1.0, 1.0, 0.25), shapes.rectangle(1.0, 1.0, 0.25, origin=(1.0, 0.0))
    return np.vstack([left.nodes, right.nodes]), np.vstack([left.cells, right.cells + left.n_nodes])


# ----------------------------------------------------------------------------- meshes
def test_coincident_nodes_are_refused_and_can_be_merged(tmp_path):
    nodes, cells = _unmerged_halves()
    with pytest.raises(MeshError, match=r"coincident nodes: \d+ pairs of nodes lie at the same point .*merge them"):
        Mesh(nodes, cells)
    path = tmp_path / "seam.vtu"
    import meshio

    meshio.write(path, meshio.Mesh(np.c_[nodes, np.zeros(len(nodes))], [("triangle", cells)]))
    with pytest.raises(MeshError, match=r"seam\.vtu: coincident nodes.*merge_coincident=True"):
        Mesh.read(path)
    merged = Mesh.read(path, merge_coincident=True)
    seam = int((np.abs(nodes[:, 0] - 1.0) < 1e-12).sum()) // 2
    assert merged.n_components == 1 and merged.n_nodes == len(nodes) - seam
    np.testing.assert_allclose(merged.boundary_facet_measures.sum(), 6.0, rtol=1e-12)  # the 2 x 1 outline only
    np.testing.assert_allclose(merged.cell_measures.sum(), 2.0, rtol=1e-12)


def test_duplicate_cells_are_refused():
    with pytest.raises(MeshError, match=r"^duplicate cells: 1 cells repeat another over the same nodes \(cells 0 and 2\)"):
        Mesh([[0, 0], [1, 0], [0, 1], [1, 1]], [[0, 1, 2], [1, 3, 2], [1, 2, 0]])


@pytest.mark.parametrize(("suffix", "words"), [
    ("vtu", r"bad\.vtu: node indices out of range \[0, 3\) in cells \[0\]"),
    ("msh", r"cannot read mesh file .*bad\.msh: a cell refers to a node the file does not hold"),
])
def test_cell_index_out_of_range_in_a_file(tmp_path, suffix, words):
    import meshio

    path = tmp_path / f"bad.{suffix}"
    mesh = meshio.Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), [("triangle", np.array([[0, 1, 5]]))])
    meshio.write(path, mesh, file_format="gmsh22" if suffix == "msh" else None)
    with pytest.raises(MeshError, match=words):
        Mesh.read(path)


def test_overlapping_copies_in_one_mesh_file(disk, tmp_path):
    two = Mesh(np.vstack([disk.nodes, disk.nodes + 0.02]) + 0.5,
               np.vstack([disk.cells, disk.cells + disk.n_nodes]))
    path = tmp_path / "two.vtu"
    two.write(path)
    with pytest.raises(ConfigError, match=r"params.meshes\[0\]: piece 1 of body 0 .* overlaps piece 0 .*remove the copy"):
        resolve_config({"scene": "bodies", "params": {"meshes": [str(path)]}})
    apart = Mesh(np.vstack([disk.nodes, disk.nodes + 0.3]) + 0.3, two.cells)
    apart.write(path)  # two separate pieces in one file are fine
    assert resolve_config({"scene": "bodies", "params": {"meshes": [str(path)]}})["scene"] == "bodies"


# ----------------------------------------------------------------------------- trajectory files
@pytest.mark.parametrize(("name", "edit", "words"), [
    ("backwards.h5", lambda f: _replace(f, "frames/times", f["frames/times"][()][::-1]),
     r"'frames/times' must increase strictly, but frame 1 is at t = .* after t = "),
    ("nan_time.h5", lambda f: _replace(f, "frames/times", np.r_[f["frames/times"][:-1], np.nan]),
     r"'frames/times' holds NaN or inf at frame 3"),
    ("nan_positions.h5", lambda f: _replace(f, "frames/positions", np.where(
        np.arange(4)[:, None, None] >= 2, np.nan, f["frames/positions"][()])),
     r"'frames/positions' holds NaN or inf from frame 2 on; the simulation diverged"),
    ("inf_velocity.h5", lambda f: _replace(f, "frames/velocities", np.where(
        np.arange(4)[:, None, None] == 1, np.inf, f["frames/velocities"][()])),
     r"'frames/velocities' holds NaN or inf from frame 1 on"),
    ("node_type.h5", lambda f: _replace(f, "mesh/node_type", np.full(len(f["mesh/node_type"]), 7, np.int8)),
     r"'mesh/node_type' holds unknown codes \[7\]; the node types are 0 \(FREE\), 1 \(CLAMPED\), 2 \(OBSTACLE\)"),
    ("short.h5", lambda f: _replace(f, "frames/velocities", f["frames/velocities"][:2]),
     r"'frames/velocities' has shape \(2, 16, 1\), expected \(4, 16, 1\)"),
])
def test_bad_trajectory_values_name_the_file(trajectory_file, tmp_path, name, edit, words):
    path = _edited_copy(trajectory_file, tmp_path, name, edit)
    with pytest.raises(DatasetError, match=rf"trajectory file .*{name.replace('.', '[.]')}: {words}"):
        load(path)


def test_a_mesh_file_is_not_a_trajectory(disk, tmp_path):
    disk.write(tmp_path / "part.msh")
    with pytest.raises(DatasetError, match=r"part\.msh is not a trajectory file \(not HDF5 at all\)"):
        load(tmp_path / "part.msh")


# ----------------------------------------------------------------------------- dataset configs
def test_a_range_of_zero_bodies_names_the_range():
    dconfig = load_dataset_config("configs/datasets/disks_quick.yaml")
    dconfig["ranges"]["count"] = [0, 0]
    with pytest.raises(ConfigError, match=r"^ranges.count must be at least 1, got \[0, 0\]$"):
        trajectory_config(dconfig, "train", 0)


def test_extends_cycle_and_bad_yaml(tmp_path):
    (tmp_path / "a.yaml").write_text("extends: b.yaml\ndataset: a\n")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\ndataset: b\n")
    with pytest.raises(ConfigError, match=r"^dataset config .*a\.yaml: 'extends' forms a cycle$"):
        load_dataset_config(tmp_path / "a.yaml")
    (tmp_path / "c.yaml").write_text("dataset: [unclosed\n")
    with pytest.raises(ConfigError, match=r"^dataset config .*c\.yaml is not valid YAML"):
        load_dataset_config(tmp_path / "c.yaml")
    (tmp_path / "d.yaml").write_text(yaml.safe_dump(["a", "list"]))
    with pytest.raises(ConfigError, match=r"^dataset config .*d\.yaml must hold a mapping of keys to values, got list$"):
        load_dataset_config(tmp_path / "d.yaml")


# ----------------------------------------------------------------------------- API: solver, hierarchy
@pytest.mark.parametrize(("config", "words"), [
    ({**TINY_BAR, "solver": {"dt": 1e-9}},
     r"^solver.dt 1e-09 s makes 100,000,000 solver steps per 0.1 s frame \(limit solver.max_substeps: 100,000\), "
     r"about [\d.]+ hours per frame for \d+ particles on one core; use a larger solver.dt"),
    ({"scene": "disks", "params": {"E": 1e16}, "output": {"frames": 1}},
     r"^the CFL time step \(solver.cfl, material stiffness, mesh size\) [\d.e-]+ s makes [\d,]+ solver steps"),
    ({**TINY_BAR, "solver": {"max_substeps": 0}}, r"^config key 'solver.max_substeps' must be a positive integer"),
])
def test_absurd_solver_costs_are_refused_up_front(config, words):
    with pytest.raises(ConfigError, match=words):
        simulate(config)


def test_a_lower_limit_is_obeyed_and_a_higher_one_lets_the_run_go():
    frame = simulate({**TINY_BAR, "output": {"frames": 1}})
    with pytest.raises(ConfigError, match=rf"makes {frame.substeps:,} solver steps .*limit solver.max_substeps: "
                                          rf"{frame.substeps - 1:,}\)"):
        simulate({**TINY_BAR, "solver": {"max_substeps": frame.substeps - 1}})
    assert simulate({**TINY_BAR, "output": {"frames": 1}, "solver": {"max_substeps": frame.substeps}}).substeps \
        == frame.substeps


def test_a_hierarchy_cache_that_is_a_file(disk, tmp_path):
    from bsms.graph import bistride_levels

    (tmp_path / "cache").write_text("")
    with pytest.raises(ConfigError, match=r"^cache_dir .*cache: .*cache is a file, not a folder; give a folder path$"):
        bistride_levels(disk, cache_dir=tmp_path / "cache")
