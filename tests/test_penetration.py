"""graph.penetration: how far moving obstacles reach into a body, as a node input."""

import numpy as np
import pytest
import torch
from conftest import tiny_run_config

from bsms.config import ConfigError
from bsms.data import GraphOptions, NodeType, Scenario
from bsms.models.simulator import LearnedSimulator
from bsms.physics import penetration
from bsms.physics.penetration import (
    Penetration,
    closest_points,
    closest_points_3d,
    inside_outline,
    solid_winding_numbers,
    winding_numbers,
)
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer
from datagen import shapes


def square(x0, y0, x1, y1, reverse=False):
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)
    a = corners if not reverse else corners[::-1]
    return a, np.roll(a, -1, axis=0)


@pytest.mark.parametrize("reverse", [False, True])
def test_winding_numbers_are_one_inside_and_zero_outside(reverse):
    a, b = square(0, 0, 1, 1, reverse)
    points = np.array([[0.5, 0.5], [0.01, 0.99], [1.5, 0.5], [-0.2, -0.2], [0.5, 1.0001]])
    w = winding_numbers(points, a, b)
    np.testing.assert_allclose(np.abs(w), [1, 1, 0, 0, 0], atol=1e-12)
    assert inside_outline(points, a, b).tolist() == [True, True, False, False, False]


def test_the_even_odd_rule_agrees_with_winding_numbers_on_a_star():
    rng = np.random.default_rng(0)
    angles = np.linspace(0, 2 * np.pi, 25)[:-1]
    radius = np.where(np.arange(24) % 2 == 0, 1.0, 0.45)  # a 12-point star: concave corners
    a = np.stack([radius * np.cos(angles), radius * np.sin(angles)], 1)
    b = np.roll(a, -1, axis=0)
    points = np.concatenate([rng.uniform(-1.1, 1.1, (2000, 2)), a[:3] * [1.0, 0.5], [[0.0, 0.0], [2.0, 0.0]]])
    expected = np.abs(winding_numbers(points, a, b)) > 0.5
    assert 300 < expected.sum() < 1700
    assert np.array_equal(inside_outline(points, a, b), expected)
    assert np.array_equal(inside_outline(points, a[::-1], b[::-1]), expected), "either orientation"


def test_long_outlines_are_pruned_to_the_same_nearest_points():
    rng = np.random.default_rng(1)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 300))
    radius = 0.02 * (1 + 0.3 * np.sin(5 * angles))  # a wavy outline of uneven segments
    a = np.stack([radius * np.cos(angles), radius * np.sin(angles)], 1)
    b = np.roll(a, -1, axis=0)
    points = np.concatenate([rng.uniform(-0.03, 0.03, (500, 2)), a[:20], 0.5 * (a[:20] + b[:20])])
    found = closest_points(points, a, b)
    assert len(a) > penetration.PRUNE_SEGMENTS
    whole = penetration._on_segments(points[:, None, :], a, b)  # every segment, the unpruned rule
    expected = whole[np.arange(len(points)), ((whole - points[:, None]) ** 2).sum(-1).argmin(1)]
    assert np.array_equal(found, expected), "bit for bit the nearest point of the unpruned search"


def test_closest_points_on_segments_in_closed_form():
    a, b = square(0, 0, 1, 1)
    points = np.array([[0.3, 0.5], [0.5, 0.9], [2.0, 2.0], [0.5, -1.0]])
    np.testing.assert_allclose(closest_points(points, a, b), [[0, 0.5], [0.5, 1.0], [1, 1], [0.5, 0]], atol=1e-15)


def _scene(spacing=0.1, top=1.15):
    """A 1 x 1 body meshed at ``spacing`` (rest nodes), a container box around it and a square
    punch over its top middle (0.4-0.6 by 0.95-``top``), as scenario arrays: (body, rest, facets,
    n_body, punch node indices)."""
    body = shapes.rectangle(1.0, 1.0, spacing)
    body_nodes = body.nodes - body.nodes.min(0)
    n_body = len(body_nodes)
    box = np.array([[-1, -1], [2, -1], [2, 2], [-1, 2]], float)
    punch = np.array([[0.4, 0.95], [0.6, 0.95], [0.6, top], [0.4, top]], float)
    rest = np.concatenate([body_nodes, box, punch])
    ring = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    facets = np.concatenate([ring + n_body, ring + n_body + 4])
    return body, rest, facets, n_body, np.arange(n_body + 4, n_body + 8)


def test_the_punch_counts_and_the_container_does_not():
    body, rest, facets, n_body, punch = _scene()
    penetration = Penetration(rest, facets, n_body)
    assert len(penetration.outlines) == 1 and set(penetration.outlines[0].ravel()) == set(punch)
    coming = rest.copy()
    coming[punch] += [0.0, -0.12]  # the punch's underside at y = 0.83, 0.17 into the body
    free = np.arange(len(rest)) < n_body
    out = penetration(rest, coming, free)
    x, y = rest[:n_body].T
    inside = (x > 0.4 + 1e-9) & (x < 0.6 - 1e-9) & (y > 0.83 + 1e-9)
    assert inside.sum() > 3 and not out[~free].any() and not out[:n_body][~inside].any()
    # inside an axis-aligned box the nearest boundary point is across its nearest side
    gaps = np.stack([x - 0.4, 0.6 - x, y - 0.83, 1.03 - y], 1)[inside]
    side = gaps.argmin(1)
    expected = np.zeros((inside.sum(), 2))
    expected[side == 0, 0] = -gaps[side == 0, 0]
    expected[side == 1, 0] = gaps[side == 1, 1]
    expected[side == 2, 1] = -gaps[side == 2, 2]
    expected[side == 3, 1] = gaps[side == 3, 3]
    np.testing.assert_allclose(out[:n_body][inside], expected, rtol=0, atol=1e-14)


def test_a_scenario_frame_carries_the_penetration_of_the_coming_frame():
    body, rest, facets, n_body, punch = _scene()
    node_type = np.full(n_body, NodeType.FREE)
    options = GraphOptions(levels=2, from_rest=True, penetration=True, obstacle_spacing=0.0, contact_radius=1.5)
    scenario = Scenario.build(body.__class__(rest[:n_body], body.cells), options, frame_dt=0.1, node_type=node_type,
                              obstacle_nodes=rest[n_body:], obstacle_facets=facets - n_body)
    velocity = np.zeros_like(scenario.rest_pos)
    moving = n_body + 4 + np.arange(4)  # with obstacle_spacing 0 the stored obstacle nodes keep their order
    velocity[moving] = [0.0, -1.2]  # 0.12 down over the coming frame
    frame = scenario.frame(scenario.rest_pos, velocity)
    got = np.zeros_like(scenario.rest_pos)
    got[frame.nodes["scenario_nodes"]] = frame.nodes["penetration"]
    coming = scenario.rest_pos + 0.1 * velocity
    expected = Penetration(scenario.rest_pos, facets, n_body)(scenario.rest_pos, coming, scenario.node_type == 0)
    np.testing.assert_array_equal(got[frame.nodes["scenario_nodes"]], expected[frame.nodes["scenario_nodes"]])
    depth = np.linalg.norm(got[:n_body], axis=1)
    assert (depth > 0).sum() >= 2 and depth.max() <= 0.1 + 1e-12  # never more than the punch's half width


CUBE_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])  # outward


def cube(low, high):
    (x0, y0, z0), (x1, y1, z1) = low, high
    return np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                     [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], float)


def test_solid_winding_numbers_and_closest_points_in_3d():
    corners = cube((0, 0, 0), (1, 1, 1))
    a, b, c = (corners[CUBE_FACES[:, i]] for i in range(3))
    points = np.array([[0.5, 0.5, 0.5], [0.9, 0.1, 0.2], [1.5, 0.5, 0.5], [0.5, 0.5, -0.01]])
    np.testing.assert_allclose(np.abs(solid_winding_numbers(points, a, b, c)), [1, 1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(solid_winding_numbers(points, a, c, b), -solid_winding_numbers(points, a, b, c),
                               atol=1e-12)
    near = closest_points_3d(np.array([[0.5, 0.5, 0.3], [0.9, 0.1, 0.5], [2.0, 2.0, 2.0], [0.5, 0.5, 1.4]]), a, b, c)
    np.testing.assert_allclose(near, [[0.5, 0.5, 0.0], [1.0, 0.1, 0.5], [1, 1, 1], [0.5, 0.5, 1.0]], atol=1e-15)


def test_a_3d_punch_counts_and_its_container_does_not():
    body = shapes.box((1.0, 1.0, 1.0), 0.25)
    nodes = body.nodes - body.nodes.min(0)
    n_body = len(nodes)
    box, punch = cube((-1, -1, -1), (2, 2, 2)), cube((0.3, 0.3, 0.9), (0.7, 0.7, 1.3))
    rest = np.concatenate([nodes, box, punch])
    facets = np.concatenate([CUBE_FACES + n_body, CUBE_FACES + n_body + 8])
    penetration = Penetration(rest, facets, n_body)
    assert len(penetration.outlines) == 1
    coming = rest.copy()
    coming[n_body + 8:] += [0.0, 0.0, -0.2]  # underside at z = 0.7
    out = penetration(rest, coming, np.arange(len(rest)) < n_body)
    x, y, z = nodes.T
    inside = (x > 0.3) & (x < 0.7) & (y > 0.3) & (y < 0.7) & (z > 0.7)
    assert inside.sum() >= 1 and not out[n_body:].any() and not out[:n_body][~inside].any()
    gaps = np.stack([x - 0.3, 0.7 - x, y - 0.3, 0.7 - y, z - 0.7, 1.1 - z], 1)[inside]
    np.testing.assert_allclose(np.linalg.norm(out[:n_body][inside], axis=1), gaps.min(1), rtol=0, atol=1e-14)


def test_facets_that_do_not_fit_the_dimension_are_a_config_error():
    body, rest, facets, n_body, _ = _scene()
    with pytest.raises(ConfigError, match=r"graph.penetration needs closed obstacle outlines of 2-node facets in a "
                                          r"2D scene \(segments in 2D, triangles in 3D\), got facets of 3 nodes"):
        Scenario.build(body.__class__(rest[:n_body], body.cells), GraphOptions(levels=2, penetration=True),
                       frame_dt=0.1, obstacle_nodes=rest[n_body:], obstacle_facets=np.array([[0, 1, 2]]))


def test_the_model_reads_it_and_says_when_it_is_missing():
    model = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8, penetration=True)
    plain = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8)
    assert model.node_normalizer.total.shape[-1] == plain.node_normalizer.total.shape[-1] + 2
    body, rest, facets, n_body, _ = _scene()
    scenario = Scenario.build(body.__class__(rest[:n_body], body.cells), GraphOptions(levels=2), frame_dt=0.1,
                              obstacle_nodes=rest[n_body:], obstacle_facets=facets - n_body)
    graph = scenario.graph(scenario.rest_pos, np.zeros_like(scenario.rest_pos))
    with pytest.raises(ValueError, match=r"^the model reads how far obstacles reach into the body"):
        model(graph)
    assert torch.isfinite(plain(graph)).all()


def test_training_with_penetration_runs(tiny_dataset, tmp_path, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, graph={"penetration": True},
                                         train={"steps": 4, "valid_every": 4}))
    summary = Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    assert np.isfinite(summary["loss"])
