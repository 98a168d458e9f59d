"""graph.clearance: the container leaves the graph, its nearness becomes a node input."""

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from test_penetration import _scene

from bsms.config import ConfigError
from bsms.data import GraphOptions, NodeType, Scenario
from bsms.models.simulator import LearnedSimulator
from bsms.physics.penetration import Clearance, closest_points
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer


def test_the_clearance_is_the_vector_to_the_nearest_wall_within_the_radius():
    body, rest, facets, n_body, punch = _scene()  # a 1 x 1 body in a box [-1, 2]^2, a punch over its top
    free = np.arange(len(rest)) < n_body
    shifted = rest.copy()
    shifted[:n_body] += [-0.75, -0.6]  # the body's lower left corner at (-0.75, -0.6): 0.25 and 0.4 off the walls
    clearance = Clearance(rest, facets, n_body, radius=0.5)
    assert set(clearance.excluded) == set(range(n_body, n_body + 4)), "the box, not the punch"
    out = clearance(shifted, free)
    x, y = shifted[:n_body].T
    gaps = np.stack([x + 1.0, y + 1.0], 1)  # to the left wall and the floor; the others are > 0.5 away
    expected = np.where(gaps[:, :1] <= gaps[:, 1:], np.stack([-gaps[:, 0], 0 * x], 1), np.stack([0 * x, -gaps[:, 1]], 1))
    expected[gaps.min(1) > 0.5] = 0.0
    np.testing.assert_allclose(out[:n_body], expected, rtol=0, atol=1e-15)
    assert (np.linalg.norm(out[:n_body], axis=1) > 0).sum() >= 10 and not out[n_body:].any()
    assert np.array_equal(clearance(shifted, free), out), "asked again: the same answer"
    pressed, kept = shifted.copy(), clearance._last
    pressed[punch] += [0.0, -0.3]  # only the punch moves (frames from rest): the kept answer, not a new search
    assert np.array_equal(clearance(pressed, free), out) and clearance._last is kept
    moved = shifted + [0.3, -0.2]  # body and box moved together: the walls are read where they are
    np.testing.assert_allclose(clearance(moved, free), out, rtol=0, atol=1e-15)
    brute = closest_points(shifted[:n_body], rest[facets[:4, 0]], rest[facets[:4, 1]]) - shifted[:n_body]
    brute[np.linalg.norm(brute, axis=1) > 0.5] = 0.0
    np.testing.assert_allclose(out[:n_body], brute, rtol=0, atol=1e-15)


def _scenario(clearance: bool):
    body, rest, facets, n_body, punch = _scene()
    rest = rest.copy()
    rest[n_body:n_body + 4] = [[-0.5, 0.0], [1.5, 0.0], [1.5, 2.0], [-0.5, 2.0]]  # a floor under the body
    rest[:n_body, 1] += 1e-3
    options = GraphOptions(levels=2, from_rest=True, obstacle_spacing=0.1, contact_radius=1.5, clearance=clearance)
    return Scenario.build(body.__class__(rest[:n_body], body.cells), options, frame_dt=0.1,
                          node_type=np.full(n_body, NodeType.FREE), obstacle_nodes=rest[n_body:],
                          obstacle_facets=facets - n_body), n_body


def test_a_frame_with_clearance_holds_no_container_node_and_no_contact_to_one():
    with_walls, n_body = _scenario(False)
    scenario, _ = _scenario(True)
    container = scenario.clearance.excluded
    assert len(container) > 40 and container.min() >= n_body
    frame = scenario.frame(scenario.rest_pos, np.zeros_like(scenario.rest_pos))
    plain = with_walls.frame(with_walls.rest_pos, np.zeros_like(with_walls.rest_pos))
    held = frame.nodes["scenario_nodes"]
    assert not np.isin(container, held).any() and (held >= n_body).any(), "the punch stays, the box goes"
    assert np.isin(container, plain.nodes["scenario_nodes"]).any()
    for level in frame.contacts:  # local indices of the frame's nodes
        assert level.shape[1] > 0
    contacts = held[frame.contacts[0]]
    plain_contacts = plain.nodes["scenario_nodes"][plain.contacts[0]]
    to_punch = ~np.isin(plain_contacts, container).any(axis=0)
    np.testing.assert_array_equal(contacts, plain_contacts[:, to_punch])  # the same contacts, less the walls'
    assert frame.contacts[0].shape[1] < plain.contacts[0].shape[1]
    height = scenario.rest_pos[held, 1]  # the side walls are 0.5 away, beyond the radius (0.15)
    expected = np.where((held < n_body)[:, None] & (height <= scenario.contact_radius)[:, None],
                        np.stack([0 * height, -height], 1), 0.0)
    assert (expected[:, 1] < 0).sum() >= 20
    np.testing.assert_allclose(frame.nodes["clearance"], expected, rtol=0, atol=1e-15)


def test_the_model_reads_the_clearance_and_the_option_needs_obstacles():
    model = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8, clearance=True)
    plain = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8)
    assert model.node_normalizer.total.shape[-1] == plain.node_normalizer.total.shape[-1] + 2
    scenario, _ = _scenario(False)
    graph = scenario.graph(scenario.rest_pos, np.zeros_like(scenario.rest_pos))
    with pytest.raises(ValueError, match=r"^the model reads where the container's walls are \('clearance', "
                                         r"graph.clearance\), which this graph lacks; build it with graph.clearance: "
                                         r"true$"):
        model(graph)
    scenario, _ = _scenario(True)
    assert torch.isfinite(model(scenario.graph(scenario.rest_pos, np.zeros_like(scenario.rest_pos)))).all()
    with pytest.raises(ConfigError, match=r"^config key 'graph.clearance' stands in for the container's obstacle "
                                          r"nodes; set 'graph.obstacles: true' too, or 'graph.clearance: false'$"):
        GraphOptions(clearance=True, obstacles=False).validate()


def test_training_with_clearance_runs(tiny_dataset, tmp_path, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, graph={"clearance": True},
                                         train={"steps": 4, "valid_every": 4}))
    summary = Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    assert np.isfinite(summary["loss"])
