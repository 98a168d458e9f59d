"""train.loss_weight: motion weighs each training trajectory by 1 / (its at-rest error)^2."""

import numpy as np
import pytest
import torch
from conftest import tiny_run_config

from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType
from bsms.level_graph import level_graph
from bsms.run import build_model, load_config, prepare_dataset, split_files
from bsms.training.trainer import Trainer

OPTIONS = GraphOptions(levels=2)


@pytest.fixture(scope="module")
def files(tiny_dataset, tmp_path_factory):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path_factory.mktemp("runs")))
    return split_files(prepare_dataset(config, progress=False), "train")


def _at_rest(positions, scenario) -> float:
    free = scenario.node_type == NodeType.FREE
    return float(np.sqrt(np.mean(np.sum((positions[1:, free] - positions[:1, free]) ** 2, axis=-1))))


def test_weights_are_one_over_the_squared_at_rest_error_averaging_one(files):
    data = FrameDataset(files, OPTIONS, loss_weight="motion", mirror=True)
    scales = np.array([_at_rest(p, s) for p, s in zip(data.positions, data.scenarios, strict=True)])
    expected = 1.0 / np.maximum(scales, np.median(scales) / 4) ** 2
    counts = np.diff(data._starts)
    expected *= counts.sum() / (expected * counts).sum()
    weights = np.array([s.loss_weight for s in data.scenarios])
    np.testing.assert_allclose(weights, expected, rtol=1e-12)
    assert weights[0] == weights[1] and weights[2] == weights[3], "a mirrored trajectory moves as far as its source"
    # every node of a sample's graph carries its trajectory's weight
    for index in (0, len(data) - 1):
        k, _ = data.locate(index)
        graph = data[index]
        assert torch.equal(graph.loss_weight, torch.full((graph.num_nodes,), np.float32(weights[k])))
    assert "loss_weight" not in FrameDataset(files, OPTIONS)[0], "uniform: no weights, the plain loss"


def test_twice_the_motion_weighs_a_quarter(files):
    data = FrameDataset([files[0], files[0]], OPTIONS)
    free = data.scenarios[1].node_type == NodeType.FREE
    data.positions[1][:, free] = data.positions[1][:1, free] + 2.0 * (data.positions[1][:, free] -
                                                                     data.positions[1][:1, free])
    data._weigh_by_motion()
    # the median (1.5 s) floors nothing; 1/s^2 and 1/(4 s^2) scaled to mean 1: 1.6 and 0.4
    np.testing.assert_allclose([s.loss_weight for s in data.scenarios], [1.6, 0.4], rtol=1e-12)


def test_a_body_that_hardly_moves_is_floored_at_a_quarter_of_the_median(files):
    data = FrameDataset([files[0]] * 3, OPTIONS)
    free = data.scenarios[0].node_type == NodeType.FREE
    for k, factor in enumerate((1e-6, 1.0, 2.0)):
        data.positions[k][:, free] = data.positions[k][:1, free] + factor * (data.positions[k][:, free] -
                                                                             data.positions[k][:1, free])
    data._weigh_by_motion()
    # scales (~0, s, 2 s): median s, the first floored to s / 4: weights 16, 1, 1/4 over s^2, mean 1
    raw = np.array([16.0, 1.0, 0.25])
    np.testing.assert_allclose([s.loss_weight for s in data.scenarios], raw * 3 / raw.sum(), rtol=1e-9)


def test_the_weighted_loss_sums_each_graphs_error_times_its_weight(files, tiny_dataset, tmp_path):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path))
    data = FrameDataset(files, config.graph, loss_weight="motion")
    plain = FrameDataset(files, config.graph)
    torch.manual_seed(0)
    model = build_model(config, data.dim)
    last = len(data) - 1
    graphs = [level_graph([data.scenarios[k].frame(*data.sample_state(k, t))]) for k, t in (data.locate(0),
                                                                                           data.locate(last))]
    assert data.locate(0)[0] != data.locate(last)[0], "two trajectories, two weights"
    with torch.no_grad():
        parts = [float(model.loss(g, reduction="sum")) for g in graphs]
        weighted = float(model.loss(level_graph([data.scenarios[k].frame(*data.sample_state(k, t))
                                                 for k, t in (data.locate(0), data.locate(last))]), reduction="sum"))
        unweighted = [float(model.loss(plain[i], reduction="sum")) for i in (0, last)]
    w = [s.loss_weight for s in data.scenarios]
    np.testing.assert_allclose(weighted, w[0] * unweighted[0] + w[-1] * unweighted[1], rtol=1e-5)
    np.testing.assert_allclose(parts, [w[0] * unweighted[0], w[-1] * unweighted[1]], rtol=1e-6)


def test_motion_weights_train_from_the_config(tiny_dataset, tmp_path, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, train={"loss_weight": "motion", "steps": 2,
                                                                        "valid_every": 2, "checkpoint_every": 2}))
    trainer = Trainer(config)
    assert all(s.loss_weight is not None for s in trainer.train_set.scenarios)
    assert all(s.loss_weight is None for s in trainer.valid_set.scenarios), "validation is not weighted"
    assert np.isfinite(trainer.fit()["loss"])


def test_what_motion_weights_refuse(files, tiny_dataset, tmp_path):
    with pytest.raises(ConfigError) as bad:
        load_config(tiny_run_config(tiny_dataset, tmp_path, train={"loss_weight": "speed"}))
    assert "train.loss_weight" in str(bad.value) and "'motion'" in str(bad.value)
    with pytest.raises(ConfigError, match=r"^config key 'train.loss_weight' must be 'uniform' or 'motion', got 'x'$"):
        FrameDataset(files, OPTIONS, loss_weight="x")
    data = FrameDataset(files, OPTIONS)
    data.states = [np.zeros((2, 1, 1))]  # as Eulerian data holds its fields
    with pytest.raises(ConfigError, match=r"^config key 'train.loss_weight' 'motion' needs Lagrangian data; .* "
                                          r"\(use 'uniform'\)$"):
        data._weigh_by_motion()
