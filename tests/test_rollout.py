"""bsms.rollouts.rollout: metrics against a direct computation, instability detection, kinematic nodes."""

import numpy as np
import pytest
import torch

from bsms.data import GraphOptions, NodeType, Scenario
from bsms.rollouts.rollout import body_size, rollout, rollout_metrics, summarize
from datagen import shapes


def test_metrics_match_a_direct_computation():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(61, 7, 2))
    predicted = truth + rng.normal(scale=0.01, size=truth.shape) * np.arange(61)[:, None, None]
    predicted[0] = truth[0]
    mask = np.array([True, True, False, True, True, True, False])
    size = 2.5
    m = rollout_metrics(predicted, truth, mask, size, bound=10.0)
    per_step = [np.sqrt(np.mean(np.sum((predicted[t, mask] - truth[t, mask]) ** 2, axis=1))) for t in range(1, 61)]
    # the same float64 sums in another order: a few ulps
    np.testing.assert_allclose(m["error_curve"], per_step, rtol=1e-15)
    assert m["rmse_1"] == pytest.approx(per_step[0], rel=1e-15)
    assert m["rmse_50"] == pytest.approx(per_step[49], rel=1e-15)
    everything = (predicted[1:, mask] - truth[1:, mask]) ** 2
    assert m["rmse_all"] == pytest.approx(np.sqrt(everything.sum(-1).mean()), rel=2e-15)
    assert m["rel_all"] == pytest.approx(m["rmse_all"] / size, rel=1e-15)
    assert m["unstable_step"] is None
    assert body_size(np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 4.0]])) == 5.0
    summary = summarize([m, {**m, "rmse_all": m["rmse_all"] + 2, "unstable_step": 7}])
    assert summary["rmse_all"] == pytest.approx(m["rmse_all"] + 1, rel=1e-15)
    assert summary["rmse_all_std"] == pytest.approx(1, rel=1e-15)
    assert summary["unstable"] == 1 and summary["first_unstable_step"] == 7


def test_instability_step_and_non_finite_states():
    truth = np.zeros((21, 3, 2))
    predicted = np.zeros_like(truth)
    predicted[:, :, 0] = 0.01 * np.arange(21)[:, None] ** 2  # error 0.01 t^2
    m = rollout_metrics(predicted, truth, np.ones(3, bool), size=1.0, bound=0.5)
    assert m["unstable_step"] == 8  # 0.01 * 8^2 = 0.64 is the first error above 0.5
    predicted[12:, 1] = np.nan
    m = rollout_metrics(predicted[:13], truth, np.ones(3, bool), size=1.0, bound=100.0)
    assert m["unstable_step"] == 12 and np.isinf(m["error_curve"][11:]).all() and np.isinf(m["rmse_all"])


class Exploding(torch.nn.Module):
    """A 'model' whose velocity change doubles the velocity of free nodes every step."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(()))

    def velocity_change(self, graph, precision="f32"):
        free = (graph.node_type == NodeType.FREE)[:, None]
        return torch.where(free, graph.velocity + 1.0, torch.zeros_like(graph.velocity))


def test_a_deliberately_unstable_model_is_reported_at_the_right_step():
    mesh = shapes.rectangle(1.0, 0.2, 0.1)
    clamped = np.where(mesh.nodes[:, 0] < 1e-9, NodeType.CLAMPED, NodeType.FREE)
    scenario = Scenario.build(mesh, GraphOptions(levels=2, contact=False), frame_dt=0.1, node_type=clamped)
    steps = 12
    result = rollout(Exploding(), scenario, mesh.nodes, np.zeros_like(mesh.nodes), steps, warmup=0)
    # free nodes: v_t = 2^t - 1 along both axes, x_t = x_0 + 0.1 * sum_{s<=t} v_s; clamped nodes stay put
    v = 2.0 ** np.arange(steps + 1) - 1.0
    x = 0.1 * np.cumsum(v)
    free = clamped == NodeType.FREE
    np.testing.assert_allclose(result.positions[:, free] - mesh.nodes[free], np.repeat(x[:, None], 2, -1)[:, None]
                               .repeat(free.sum(), 1), rtol=5e-15)
    assert (result.positions[:, ~free] == mesh.nodes[~free]).all()
    m = rollout_metrics(result.positions, np.repeat(mesh.nodes[None], steps + 1, 0), free, body_size(mesh.nodes),
                        bound=0.5)
    error = np.sqrt(2) * x[1:]
    expected = int(np.flatnonzero(error > 0.5 * body_size(mesh.nodes))[0]) + 1
    assert m["unstable_step"] == expected
    assert len(result.step_seconds) == steps and result.finite


def falling_scenes():
    """Three scenes of different sizes whose bodies fall onto the floor of their box, so that
    obstacle nodes enter their graphs part-way: (scenario, x0, v0) each."""
    from datagen.scenes import get_scene

    glyphs, disks = get_scene("glyphs"), get_scene("disks")
    scenes = [
        glyphs.build(glyphs.params({"chars": ["B"], "centers": [[0.4, 0.35]], "velocities": [[0.2, -1.5]],
                                    "height": 0.3, "body_size": 0.04, "mesh_size": 0.08})),
        glyphs.build(glyphs.params({"chars": ["L", "T"], "centers": [[0.25, 0.3], [0.7, 0.25]],
                                    "velocities": [[-0.5, -1.0], [0.0, -1.0]], "height": 0.25, "body_size": 0.05,
                                    "mesh_size": 0.1})),
        disks.build(disks.params({"radii": [0.15, 0.12], "centers": [[0.3, 0.3], [0.6, 0.2]],
                                  "velocities": [[0.0, -1.0], [0.5, -0.5]], "body_size": 0.05})),
    ]
    out = []
    for scene in scenes:
        scenario = Scenario.build(scene.body, GraphOptions(levels=3), frame_dt=0.02, node_type=scene.node_type,
                                  body_id=scene.body_id, obstacle_nodes=scene.obstacle_nodes,
                                  obstacle_facets=scene.obstacle_facets)
        out.append((scenario, scenario.full(scene.x[scene.tracked]), scenario.full(scene.v[scene.tracked][None],
                                                                                     0.0)[0]))
    return out


@pytest.mark.parametrize("core", ["bsms_gnn", "meshgraphnets"])
def test_a_batch_of_rollouts_equals_each_alone(core, one_thread):
    from bsms.models.simulator import LearnedSimulator
    from bsms.rollouts.rollout import rollouts

    scenes = falling_scenes()
    torch.manual_seed(0)
    model = LearnedSimulator(core, 2, n_levels=3, contact=True, latent=32, n_passes=3)
    graph = scenes[0][0].graph(scenes[0][1], scenes[0][2], target=0.05 * np.ones_like(scenes[0][1]))
    model.loss(graph, accumulate=True)  # normalisers that are not the identity
    steps = [12, 9, 12]
    known = [None, None, np.repeat(scenes[2][1][None], 13, axis=0)]
    together = rollouts(model, [s for s, _, _ in scenes], [x for _, x, _ in scenes], [v for _, _, v in scenes], steps,
                        known, precision="f32")
    for (scenario, x0, v0), n, k, batched in zip(scenes, steps, known, together, strict=True):
        alone = rollout(model, scenario, x0, v0, n, k, precision="f32")
        assert batched.positions.shape == alone.positions.shape == (n + 1, scenario.n_nodes, 2)
        assert np.array_equal(batched.graph_nodes, alone.graph_nodes)
        assert batched.graph_nodes.shape == (n, 3) and (batched.graph_nodes[:, 0] >= scenario.n_body).all()
        assert batched.graph_nodes[0, 0] < batched.graph_nodes[-1, 0], "obstacle nodes must come in"
        # float32 round-off of metre-sized positions (measured: bit-identical on one CPU thread)
        np.testing.assert_allclose(batched.positions, alone.positions, rtol=0, atol=1e-7)
    assert len(together[1].step_seconds) == 9 and len(together[0].step_seconds) == 12


class Poisoned(Exploding):
    """Exploding, except that free nodes moving faster than 100 m/s get a NaN velocity change."""

    def velocity_change(self, graph, precision="f32"):
        change = super().velocity_change(graph, precision)
        fast = (graph.velocity.norm(dim=-1, keepdim=True) > 100.0) & (graph.node_type == NodeType.FREE)[:, None]
        return torch.where(fast, torch.full_like(change, float("nan")), change)


def test_a_rollout_that_goes_non_finite_leaves_the_batch():
    from bsms.rollouts.rollout import rollouts

    mesh = shapes.rectangle(1.0, 0.2, 0.1)
    scenario = Scenario.build(mesh, GraphOptions(levels=2, contact=False), frame_dt=0.1)
    starts = [np.zeros_like(mesh.nodes), np.full_like(mesh.nodes, 200.0), np.zeros_like(mesh.nodes)]
    results = rollouts(Poisoned(), [scenario] * 3, [mesh.nodes] * 3, starts, [6, 6, 4], warmup=0)
    assert not results[1].finite and len(results[1].positions) == 2 and len(results[1].step_seconds) == 1
    for k, steps in ((0, 6), (2, 4)):
        alone = rollout(Poisoned(), scenario, mesh.nodes, starts[k], steps, warmup=0)
        assert results[k].finite and np.array_equal(results[k].positions, alone.positions)
    with pytest.raises(ValueError, match="one initial state, step count and known_positions"):
        rollouts(Poisoned(), [scenario] * 2, [mesh.nodes], starts[:2], 3)
