"""train.rotate: a training sample turned by a random angle is the sample of the turned scene."""

import dataclasses

import numpy as np
import pytest
from conftest import tiny_run_config

from bsms.augment import ROTATED_FIELDS, random_rotation, rotated
from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions
from bsms.run import load_config, prepare_dataset, split_files
from datagen.dataset import load
from datagen.mesh import Mesh


@pytest.fixture(scope="module", params=["2d", "3d"])
def files(request, tiny_dataset, tiny_dataset_3d, tmp_path_factory):
    tiny = tiny_dataset if request.param == "2d" else tiny_dataset_3d
    config = load_config(tiny_run_config(tiny, tmp_path_factory.mktemp("runs")))
    return split_files(prepare_dataset(config, progress=False), "train")


@pytest.mark.parametrize("dim", [2, 3])
def test_random_rotations_are_rotations_within_the_angle(dim):
    rng = np.random.default_rng(0)
    angles = []
    for _ in range(200):
        r = random_rotation(dim, 30.0, rng)
        np.testing.assert_allclose(r @ r.T, np.eye(dim), atol=1e-15)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-14)
        angles.append(np.degrees(np.arccos(np.clip((np.trace(r) - (dim - 2)) / 2, -1, 1))))
    assert max(angles) <= 30.0 + 1e-9 and max(angles) > 28.0  # the whole range is drawn
    assert np.array_equal(random_rotation(dim, 0.0, rng), np.eye(dim))


def _turned(trajectory, rotation):
    """The trajectory with every position, velocity and obstacle turned about the origin."""
    turn = rotation.T
    obstacles = {}
    if trajectory.obstacle_nodes is not None:
        obstacles["obstacle_nodes"] = np.asarray(trajectory.obstacle_nodes) @ turn
    if trajectory.obstacle_positions is not None:
        obstacles["obstacle_positions"] = np.asarray(trajectory.obstacle_positions) @ turn
    return dataclasses.replace(trajectory, mesh=Mesh(trajectory.mesh.nodes @ turn, trajectory.mesh.cells),
                               positions=trajectory.positions @ turn, velocities=trajectory.velocities @ turn,
                               diagnostics={}, step_diagnostics=None, **obstacles)


def test_a_turned_sample_is_the_sample_of_the_turned_scene(files, tmp_path, monkeypatch):
    trajectory = load(files[0])
    rotation = random_rotation(trajectory.mesh.dim, 180.0, np.random.default_rng(3))
    turned_file = tmp_path / "turned.h5"
    monkeypatch.setattr("bsms.augment.load", lambda path: _turned(load(files[0]), rotation)
                        if str(path) == str(turned_file) else load(path))
    options = GraphOptions(levels=2, clearance=True)
    plain = FrameDataset(files[:1], options)
    turned = FrameDataset([turned_file], options)
    near_walls = 0
    for t in range(len(plain)):
        a, b = rotated(plain[t], rotation), turned[t]
        near_walls += int(b.clearance.abs().max() > 0)
        for key in ROTATED_FIELDS:
            if key in b:
                np.testing.assert_allclose(a[key].numpy(), b[key].numpy(), rtol=0, atol=2e-6 * max(1.0, abs(b[key]).max()))
        for level in range(2):
            np.testing.assert_array_equal(a[f"edge_index_{level}"].numpy(), b[f"edge_index_{level}"].numpy())
            np.testing.assert_array_equal(a[f"contact_index_{level}"].numpy(), b[f"contact_index_{level}"].numpy())
    assert near_walls > 0  # frames where the walls' vectors (graph.clearance) turn too


def test_samples_are_turned_by_their_seed_only(files):
    options = GraphOptions(levels=2)
    plain = FrameDataset(files[:1], options)
    turning = FrameDataset(files[:1], options, rotate=180.0)
    first, again, other = turning[(1, (0, 5, 1))], turning[(1, (0, 5, 1))], turning[(1, (0, 6, 1))]
    assert np.array_equal(first.pos.numpy(), again.pos.numpy())  # a sample is a function of its seed
    assert not np.allclose(first.pos.numpy(), other.pos.numpy())
    base = plain[1]
    for key in ("pos", "target"):  # turned, not changed: lengths kept
        np.testing.assert_allclose(np.linalg.norm(first[key].numpy(), axis=1), np.linalg.norm(base[key].numpy(), axis=1),
                                   rtol=1e-5, atol=1e-7)
    assert np.array_equal(turning[1].pos.numpy(), base.pos.numpy())  # without a seed (validation): as stored
    kept = FrameDataset(files[:1], options, rotate=0.0)[(1, (0, 5, 1))]
    assert np.array_equal(kept.pos.numpy(), base.pos.numpy())


def test_what_cannot_be_turned(tiny_dataset, tmp_path):
    for value, message in ((-1.0, r"config key 'train.rotate' must lie in \[0, 180\] degrees, got -1.0"),
                           (181.0, r"must lie in \[0, 180\] degrees, got 181.0")):
        with pytest.raises(ConfigError, match=message):
            load_config(tiny_run_config(tiny_dataset, tmp_path, train={"rotate": value}))
    with pytest.raises(ConfigError, match=r"config key 'train.rotate' turns one-step samples; set 'train.unroll: 1'"):
        load_config(tiny_run_config(tiny_dataset, tmp_path, train={"rotate": 10.0, "unroll": 2}))
