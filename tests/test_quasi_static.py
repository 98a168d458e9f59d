"""graph.quasi_static: first-order learning (no velocity input on free nodes, the output is
their whole velocity over the frame) in samples, multi-step training and rollouts alike."""

import numpy as np
import pytest
import torch
from test_unroll import K, Stub, oracle, whole_batch
from torch_geometric.data import Batch

from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType, NoiseOptions
from bsms.rollouts.rollout import rollout
from bsms.run import split_files
from bsms.training.unroll import UnrollSamples, collate, unrolled_loss


@pytest.fixture(scope="module")
def files(tiny_folder):
    return split_files(tiny_folder, "train")


@pytest.fixture(scope="module")
def frames(files):
    return FrameDataset(files, GraphOptions(levels=3, quasi_static=True))


def test_samples_have_no_free_velocity_and_their_target_lands_on_the_next_frame(files, frames):
    noisy = FrameDataset(files, GraphOptions(levels=3, quasi_static=True), NoiseOptions(position=1e-3))
    second_order = FrameDataset(files, GraphOptions(levels=3))
    for k, t in [(0, 0), (0, 3), (1, 5)]:
        free = frames.scenarios[k].node_type == NodeType.FREE
        x, dt = frames.positions[k], frames.scenarios[k].frame_dt
        for dataset, seed in ((frames, None), (noisy, (7, k, t))):
            pos, velocity, target = dataset.sample_state(k, t, seed)
            assert not velocity[free].any()
            np.testing.assert_allclose((pos + dt * target)[free], x[t + 1][free], rtol=0, atol=1e-14)
            if seed is not None:  # the noise moved the inputs by about its std
                assert 5e-4 < np.abs(pos - x[t])[free].std() < 2e-3
        # kinematic nodes see what the second-order model sees: the velocity of their coming step
        _, v2, _ = second_order.sample_state(k, t)
        _, v1, _ = frames.sample_state(k, t)
        assert np.array_equal(v1[~free], v2[~free])


def test_an_exact_model_unrolls_along_the_data(frames):
    model = Stub(oracle)
    model.output_normalizer.accumulate(torch.randn(50, 2))
    samples = UnrollSamples(frames, K)
    batch, located = whole_batch(samples)
    record = []
    assert float(unrolled_loss(model, batch, samples, K, "all", record=record)) == 0.0
    for k, (graph, _) in enumerate(record):
        expected = Batch.from_data_list([frames[int(frames._starts[j]) + t + k] for j, t in located])
        free = graph.node_type == NodeType.FREE
        assert not graph.velocity[free].any()
        for name in ("pos", "velocity", "target"):
            torch.testing.assert_close(graph[name], expected[name], rtol=0, atol=2e-6, msg=f"step {k}: {name}")


def _rule(model, graph):  # depends on the state, so any difference in the inputs shows
    return 0.3 * torch.tanh(graph.pos * 40.0) - 0.1


def unroll_and_roll_out(frames):
    """The last sample of ``frames`` unrolled over K steps as training does ("through") and the
    same start rolled out by a copy of the same stub; every step's model inputs must be equal.
    -> (the rolled stub, the rollout, the scenario, x_t, v_t)."""
    samples = UnrollSamples(frames, K)
    j, t = samples.locate(len(samples) - 1)
    unrolled = Stub(_rule)
    unrolled.output_normalizer.accumulate(torch.randn(50, 2))
    rolled = Stub(_rule)
    rolled.load_state_dict(unrolled.state_dict())
    unrolled_loss(unrolled, collate([samples[len(samples) - 1]]), samples, K, "through")
    x, v = frames.positions[j], frames.trajectory_velocities(j)
    result = rollout(rolled, frames.scenarios[j], x[t], v[t], K, known_positions=x[t:], warmup=0, precision="f32")
    for k, (a, b) in enumerate(zip(unrolled.seen, rolled.seen, strict=True)):
        for name, p, q in zip(("pos", "velocity", "nodes"), a, b, strict=True):
            assert torch.equal(p, q), f"step {k}: {name} differs from the rollout's"
    return rolled, result, frames.scenarios[j], x[t], v[t]


def assert_first_order(rolled, result, scenario, x, v):
    """Each step moves free nodes by dt times the model's output, not by v_t + dv."""
    free = scenario.node_type == NodeType.FREE
    change = rolled.output_normalizer.inverse(_rule(rolled, scenario.graph(x, v))).double().numpy()
    step = result.positions[1] - result.positions[0]
    nodes = rolled.seen[0][2].numpy()
    np.testing.assert_allclose(step[nodes][free[nodes]], scenario.frame_dt * change[free[nodes]], rtol=0, atol=1e-9)


def test_the_unroll_integrates_as_a_quasi_static_rollout(frames):
    rolled, result, scenario, x, v = unroll_and_roll_out(frames)
    free = scenario.node_type == NodeType.FREE
    for _, velocity, nodes in rolled.seen:
        assert not velocity[free[nodes.numpy()]].any(), "no free velocity reaches the model"
    assert_first_order(rolled, result, scenario, x, v)


def test_quasi_static_with_velocity_noise_is_a_config_error(files):
    with pytest.raises(ConfigError) as error:
        FrameDataset(files, GraphOptions(levels=3, quasi_static=True), NoiseOptions(velocity=0.01))
    assert str(error.value).startswith("config key 'graph.quasi_static' needs Lagrangian data and 'noise.velocity' 0 "
                                       "(free nodes have no velocity input)")

