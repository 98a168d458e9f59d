"""graph.drive: a model that predicts from rest also reads how far the drive has moved the obstacles."""

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from test_penetration import _scene

from bsms.config import ConfigError
from bsms.data import GraphOptions, NodeType, Scenario
from bsms.models.simulator import LearnedSimulator
from bsms.run import load_config, load_model, prepare_dataset
from bsms.training.trainer import Trainer


def _scenario():
    body, rest, facets, n_body, punch = _scene()
    options = GraphOptions(levels=2, from_rest=True, obstacle_spacing=0.1, contact_radius=1.5, drive=True)
    scenario = Scenario.build(body.__class__(rest[:n_body], body.cells), options, frame_dt=0.1,
                              node_type=np.full(n_body, NodeType.FREE), obstacle_nodes=rest[n_body:],
                              obstacle_facets=facets - n_body)
    return scenario, n_body


def test_the_drive_input_is_each_obstacle_nodes_travel_and_zero_on_free_nodes():
    """The punch pushed 0.3 into the body (further than its 0.2 width): its nodes read (0, -0.3),
    the free nodes (at rest, as every from-rest graph has them) and the still box 0; the model's
    node inputs end with exactly that column pair."""
    scenario, n_body = _scenario()
    _, rest, _, _, _ = _scene()
    stored = rest[n_body:].copy()
    stored[4:] += [0.0, -0.3]  # the punch's four corners; the box's stay
    pos = scenario.positions(rest[:n_body], stored)  # through the subdivision of the obstacle outlines
    punch = np.flatnonzero(np.abs(pos - scenario.rest_pos).max(1) > 0)
    assert punch.min() >= n_body
    model = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8, drive=True)
    plain = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8)
    assert model.node_normalizer.total.shape[-1] == plain.node_normalizer.total.shape[-1] + 2
    graph = scenario.graph(pos, np.zeros_like(pos))
    features = model.node_features(graph)
    np.testing.assert_array_equal(features[:, :-2].numpy(), plain.node_features(graph).numpy())
    held = scenario.frame(pos, np.zeros_like(pos)).nodes["scenario_nodes"]
    expected = np.where(np.isin(held, punch)[:, None], [0.0, -0.3], 0.0)
    assert np.isin(held, punch).sum() >= 8
    np.testing.assert_allclose(features[:, -2:].numpy(), expected, rtol=0, atol=1e-6)
    assert torch.isfinite(model(graph)).all()


def test_the_option_needs_a_model_that_predicts_from_rest():
    with pytest.raises(ConfigError, match=r"^config key 'graph.drive' tells a model that predicts from rest how far "
                                          r"the drive has moved the obstacles; set 'graph.from_rest: true' too, or "
                                          r"'graph.drive: false'$"):
        GraphOptions(drive=True).validate()
    GraphOptions(drive=True, from_rest=True).validate()


def test_training_with_the_drive_runs_and_saves_the_option(tiny_dataset, tmp_path, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, graph={"drive": True, "from_rest": True},
                                         noise={"position": 0.0, "velocity": 0.0},
                                         train={"steps": 4, "valid_every": 4, "unroll": 1}))
    summary = Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    assert np.isfinite(summary["loss"])
    model, saved, _ = load_model(tmp_path / "tiny", "latest")  # the saved run rebuilds its wider inputs
    assert saved.graph.drive is True and model.drive is True
