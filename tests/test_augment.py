"""bsms.augment and train.mirror: training trajectories also seen reflected by x -> -x."""

import dataclasses

import numpy as np
import pytest
from conftest import tiny_run_config

from bsms.augment import mirrored
from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType
from bsms.run import load_config, prepare_dataset, split_files
from bsms.training.trainer import Trainer
from datagen.dataset import load

FLIP = {2: np.array([-1.0, 1.0]), 3: np.array([-1.0, 1.0, 1.0])}


@pytest.fixture(scope="module", params=["2d", "3d"])
def files(request, tiny_dataset, tiny_dataset_3d, tmp_path_factory):
    tiny = tiny_dataset if request.param == "2d" else tiny_dataset_3d
    config = load_config(tiny_run_config(tiny, tmp_path_factory.mktemp("runs")))
    return split_files(prepare_dataset(config, progress=False), "train")


def test_the_mirror_image_reflects_everything_and_keeps_orientation(files):
    trajectory = load(files[0])
    image = mirrored(trajectory)
    flip = FLIP[trajectory.mesh.dim]
    np.testing.assert_array_equal(image.mesh.nodes, trajectory.mesh.nodes * flip)
    np.testing.assert_array_equal(image.positions, trajectory.positions * flip)
    np.testing.assert_array_equal(image.velocities, trajectory.velocities * flip)
    # the same cells, still positively oriented (Mesh refuses inverted cells), with equal measures
    np.testing.assert_array_equal(np.sort(image.mesh.cells, axis=1), np.sort(trajectory.mesh.cells, axis=1))
    np.testing.assert_allclose(image.mesh.cell_measures, trajectory.mesh.cell_measures, rtol=1e-14)
    assert trajectory.obstacle_nodes is not None, "the tiny scenes have walls"
    np.testing.assert_array_equal(image.obstacle_nodes, trajectory.obstacle_nodes * flip)
    # facets keep their outward sense: the reflected normal of a facet is the facet's own normal reflected
    for source, target in ((trajectory, image), (image, trajectory)):
        normal_a = _facet_normals(source.obstacle_nodes, source.obstacle_facets) * flip
        normal_b = _facet_normals(target.obstacle_nodes, target.obstacle_facets)
        np.testing.assert_allclose(normal_a, normal_b, atol=1e-15)
    assert mirrored(image).positions.tobytes() == trajectory.positions.tobytes(), "reflecting twice is the identity"


def _facet_normals(nodes, facets):
    corners = nodes[facets]
    if facets.shape[1] == 2:
        edge = corners[:, 1] - corners[:, 0]
        return np.stack([edge[:, 1], -edge[:, 0]], 1)
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def test_mirrored_samples_are_the_reflected_samples(files):
    options = GraphOptions(levels=2)
    plain = FrameDataset(files[:1], options)
    both = FrameDataset(files[:1], options, mirror=True)
    assert len(both) == 2 * len(plain) and len(both.scenarios) == 2
    n, flip = plain.scenarios[0].n_body, FLIP[plain.dim]
    for t in range(len(plain)):
        a, b = plain.sample_state(0, t), both.sample_state(1, t)
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(y[:n], x[:n] * flip)
        assert (both.scenarios[1].node_type == NodeType.OBSTACLE).sum() == \
               (plain.scenarios[0].node_type == NodeType.OBSTACLE).sum()
    if plain.dim == 2:  # a reversed segment subdivides alike (3D triangles may be split differently)
        graphs = plain[len(plain) - 1], both[2 * len(plain) - 1]
        assert graphs[0].num_nodes == graphs[1].num_nodes
        keys = [k for k in graphs[0].keys() if k.startswith(("edge_index_", "contact_index_", "n_nodes_"))]
        assert len(keys) >= 6
        for key in keys:
            assert np.shape(graphs[0][key]) == np.shape(graphs[1][key]), key


def test_train_mirror_doubles_the_training_set_only(tiny_dataset, tmp_path):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, train={"mirror": True, "steps": 2}))
    trainer = Trainer(config)
    files = split_files(trainer.dataset_folder, "train")
    assert len(trainer.train_set.scenarios) == 2 * len(files)
    assert len(trainer.train_set) == 2 * len(FrameDataset(files, config.graph))
    assert len(trainer.valid_set.scenarios) == len(split_files(trainer.dataset_folder, "valid"))


def test_what_cannot_be_mirrored(files):
    trajectory = load(files[0])
    with pytest.raises(ConfigError) as info:
        mirrored(dataclasses.replace(trajectory, fields={"velocity": np.zeros(1)}), "t.h5")
    assert str(info.value) == ("config key 'train.mirror': t.h5 holds a converted dataset's fields; mirroring "
                               "applies to the solver's trajectories")
    config = {**trajectory.config, "params": {**trajectory.config["params"], "gravity": [1.0, -9.81]}}
    with pytest.raises(ConfigError) as info:
        mirrored(dataclasses.replace(trajectory, config=config), "t.h5")
    assert str(info.value) == ("config key 'train.mirror': t.h5 has gravity [1.0, -9.81] with an x part, so its "
                               "scene is not symmetric under x -> -x; train without it")
