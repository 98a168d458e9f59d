"""graph.from_rest: every frame predicted from the rest shape and the drive (no state carried
from frame to frame) in samples, rollouts and training."""

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from test_unroll import Stub

import bsms.rollouts.rollout as rollout_module
from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType, NoiseOptions
from bsms.models.blocks import compiled_message_passing
from bsms.models.simulator import LearnedSimulator
from bsms.rollouts.rollout import rollout
from bsms.run import load_config, split_files
from bsms.training.trainer import Trainer

OPTIONS = GraphOptions(levels=3, from_rest=True)


@pytest.fixture(scope="module")
def folder(tiny_folder):
    return tiny_folder


@pytest.fixture(scope="module")
def frames(folder):
    return FrameDataset(split_files(folder, "train"), OPTIONS)


def test_samples_put_free_nodes_at_rest_and_target_the_next_frame(folder, frames):
    second_order = FrameDataset(split_files(folder, "train"), GraphOptions(levels=3))
    for k, t in [(0, 0), (0, 3), (1, 5)]:
        scenario = frames.scenarios[k]
        free = scenario.node_type == NodeType.FREE
        x, dt, rest = frames.positions[k], scenario.frame_dt, scenario.rest_pos
        pos, velocity, target = frames.sample_state(k, t)
        assert np.array_equal(pos[free], rest[free]) and not velocity[free].any()
        np.testing.assert_allclose((rest + dt * target)[free], x[t + 1][free], rtol=0, atol=1e-14)
        assert np.abs(x[t + 1] - rest)[free].max() > 1e-3, "the tiny data moves: the targets are not trivially 0"
        # kinematic nodes (the walls here) are where they are, with the velocity of their coming step
        pos2, velocity2, _ = second_order.sample_state(k, t)
        assert np.array_equal(pos[~free], pos2[~free]) and np.array_equal(velocity[~free], velocity2[~free])


def _truth_rule(truth, scenario, bias=0.0):
    """The exact displacement from rest of the frame after each call (normalised), plus ``bias``."""
    def rule(model, graph):
        k = len(model.seen) - 1
        nodes = graph.scenario_nodes.numpy()
        exact = (truth[k + 1] - scenario.rest_pos)[nodes] / scenario.frame_dt
        return model.output_normalizer(torch.from_numpy(exact).float()) + bias
    return rule


def _stub(rule):
    model = Stub(rule)
    model.output_normalizer.accumulate(torch.randn(50, 2) * 0.05)
    return model


def test_an_exact_model_rolls_out_along_the_data_and_sees_only_the_drive(frames):
    scenario, x, v = frames.scenarios[0], frames.positions[0], frames.trajectory_velocities(0)
    free = scenario.node_type == NodeType.FREE
    steps = len(x) - 1
    model = _stub(_truth_rule(x, scenario))
    result = rollout(model, scenario, x[0], v[0], steps, known_positions=x, warmup=0, precision="f32")
    assert result.finite and len(model.seen) == steps
    np.testing.assert_allclose(result.positions[:, free], x[:, free], rtol=0, atol=2e-6)  # float32 network output
    for k, (pos, velocity, nodes) in enumerate(model.seen):
        mine = free[nodes.numpy()]
        np.testing.assert_allclose(pos.numpy()[mine], scenario.rest_pos[nodes.numpy()][mine], rtol=0, atol=1e-7,
                                   err_msg=f"step {k}")
        assert not velocity[torch.from_numpy(mine)].any(), f"step {k}: a free node has a velocity input"
    # the stored velocity is the frame's: (x_{t+1} - x_t) / dt
    np.testing.assert_allclose(result.velocities[1:, free],
                               (result.positions[1:] - result.positions[:-1])[:, free] / scenario.frame_dt,
                               rtol=1e-9, atol=1e-9)


def test_a_biased_model_errs_by_the_same_amount_every_frame(frames):
    """No error is carried over: a constant output bias b moves every predicted frame by
    dt b std (a quasi-static model's error would grow by that much per frame)."""
    scenario, x, v = frames.scenarios[1], frames.positions[1], frames.trajectory_velocities(1)
    free = scenario.node_type == NodeType.FREE
    model = _stub(_truth_rule(x, scenario, bias=0.5))
    result = rollout(model, scenario, x[0], v[0], len(x) - 1, known_positions=x, warmup=0, precision="f32")
    shift = scenario.frame_dt * 0.5 * model.output_normalizer.std.double().numpy()
    error = result.positions[1:, free] - x[1:, free]
    np.testing.assert_allclose(error, np.broadcast_to(shift, error.shape), rtol=1e-4, atol=1e-9)
    assert np.array_equal(result.positions[0], x[0])


def test_from_rest_trains_and_its_validation_rolls_out(tiny_dataset, folder, tmp_path, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, graph={"from_rest": True},
                                         noise={"position": 0.0, "velocity": 0.0},
                                         train={"validation": "rollout", "steps": 6, "valid_every": 6}))
    summary = Trainer(config, dataset_folder=folder).fit()
    assert np.isfinite(summary["loss"])
    rows = (tmp_path / "tiny/metrics.csv").read_text().splitlines()
    header, last = rows[0].split(","), rows[-1].split(",")
    assert np.isfinite(float(last[header.index("valid_vs_rest")]))


def test_from_rest_with_quasi_static_is_a_config_error():
    with pytest.raises(ConfigError) as error:
        GraphOptions(from_rest=True, quasi_static=True).validate()
    assert str(error.value) == ("config key 'graph.from_rest' predicts every frame from the rest shape and the drive, "
                                "'graph.quasi_static' steps from the frame before; set one of them to false")


def test_from_rest_with_noise_is_a_config_error(folder):
    with pytest.raises(ConfigError) as error:
        FrameDataset(split_files(folder, "train"), OPTIONS, NoiseOptions(position=1e-4))
    assert str(error.value).startswith("config key 'graph.from_rest' needs Lagrangian data and no input noise "
                                       "(no state enters its graphs, so noise has nothing to undo: set "
                                       "noise.position and noise.velocity to 0); ")


def test_from_rest_with_unrolled_training_is_a_config_error(tiny_dataset, tmp_path):
    with pytest.raises(ConfigError) as error:
        load_config(tiny_run_config(tiny_dataset, tmp_path, graph={"from_rest": True}, train={"unroll": 3}))
    assert str(error.value) == ("config key 'train.unroll' must be 1 with 'graph.from_rest': every frame is predicted "
                                "from the rest shape and the drive alone, so unrolled steps see the same inputs as "
                                "single steps; got 3")


def test_all_frames_in_one_call_equal_the_frame_by_frame_rollout(frames):
    """Frames that do not depend on each other go into one model call (frames_per_call); the
    rollout is the same as one call per frame, to float32 round-off."""
    scenario, x, v = frames.scenarios[0], frames.positions[0], frames.trajectory_velocities(0)
    steps = len(x) - 1
    torch.manual_seed(0)
    model = LearnedSimulator("bsms_gnn", 2, n_levels=3, contact=True, latent=16)
    model.node_normalizer.accumulate(torch.randn(50, model.node_normalizer.total.shape[-1]))
    model.output_normalizer.accumulate(torch.randn(50, 2) * 0.05)
    calls = []
    model.core.register_forward_hook(lambda module, args, out: calls.append(out.shape[0]))
    one = rollout(model, scenario, x[0], v[0], steps, known_positions=x, warmup=0, precision="f32")
    assert len(calls) == steps
    calls.clear()
    whole = rollout(model, scenario, x[0], v[0], steps, known_positions=x, warmup=0, precision="f32",
                    frames_per_call=steps)
    assert len(calls) == 1 and calls[0] == sum(one.graph_nodes[:, 0])
    np.testing.assert_allclose(whole.positions, one.positions, rtol=0, atol=1e-6)
    np.testing.assert_allclose(whole.velocities, one.velocities, rtol=0, atol=1e-4)
    assert len(whole.step_seconds) == steps and np.array_equal(whole.graph_nodes, one.graph_nodes)


def test_cpu_calls_hold_at_most_the_node_budget(frames, monkeypatch):
    """On a CPU, frames_per_call is capped so that a call holds at most CPU_NODES_PER_CALL graph
    nodes (at least one frame): same rollout, more calls."""
    scenario, x, v = frames.scenarios[0], frames.positions[0], frames.trajectory_velocities(0)
    steps = len(x) - 1
    torch.manual_seed(0)
    model = LearnedSimulator("bsms_gnn", 2, n_levels=3, contact=True, latent=16)
    model.output_normalizer.accumulate(torch.randn(50, 2) * 0.05)
    calls = []
    model.core.register_forward_hook(lambda module, args, out: calls.append(out.shape[0]))
    whole = rollout(model, scenario, x[0], v[0], steps, known_positions=x, warmup=0, precision="f32",
                    frames_per_call=steps)
    nodes = len(whole.positions[0])
    monkeypatch.setattr(rollout_module, "CPU_NODES_PER_CALL", 2 * nodes + 1)  # two frames per call
    calls.clear()
    capped = rollout(model, scenario, x[0], v[0], steps, known_positions=x, warmup=0, precision="f32",
                     frames_per_call=steps)
    assert len(calls) == -(-steps // 2) and max(calls) <= 2 * nodes
    np.testing.assert_allclose(capped.positions, whole.positions, rtol=0, atol=1e-6)
    monkeypatch.setattr(rollout_module, "CPU_NODES_PER_CALL", 1)  # below one frame: one frame per call
    calls.clear()
    rollout(model, scenario, x[0], v[0], steps, known_positions=x, warmup=0, precision="f32", frames_per_call=steps)
    assert len(calls) == steps


def test_compiled_message_passing_gets_the_larger_call_budget(frames, monkeypatch):
    """A lean model whose message passes are all compiled (Linear, ReLU, Linear edge MLPs, float32)
    is capped by CPU_NODES_PER_CALL_COMPILED; the same model in bf16, or a model with LayerNorm,
    by CPU_NODES_PER_CALL."""
    scenario, x, v = frames.scenarios[0], frames.positions[0], frames.trajectory_velocities(0)
    steps = len(x) - 1
    torch.manual_seed(0)
    lean = LearnedSimulator("bsms_gnn", 2, n_levels=3, contact=True, latent=16, hidden_layers=1,
                            core_options={"layer_norm": False})
    layer_norm = LearnedSimulator("bsms_gnn", 2, n_levels=3, contact=True, latent=16, hidden_layers=1)
    assert compiled_message_passing(lean, torch.float32) and not compiled_message_passing(lean, torch.bfloat16)
    assert not compiled_message_passing(layer_norm, torch.float32)
    nodes = scenario.n_nodes
    monkeypatch.setattr(rollout_module, "CPU_NODES_PER_CALL", 1)  # one frame per call
    monkeypatch.setattr(rollout_module, "CPU_NODES_PER_CALL_COMPILED", 2 * nodes + 1)  # two
    for model, precision, expected in ((lean, "f32", -(-steps // 2)), (lean, "bf16", steps), (layer_norm, "f32", steps)):
        calls = []
        handle = model.core.register_forward_hook(lambda module, args, out, calls=calls: calls.append(out.shape[0]))
        rollout(model, scenario, x[0], v[0], steps, known_positions=x, warmup=0, precision=precision,
                frames_per_call=steps)
        handle.remove()
        assert len(calls) == expected, (precision, calls)


def test_frames_that_depend_on_each_other_step_one_by_one(folder):
    dependent = FrameDataset(split_files(folder, "train"), GraphOptions(levels=3, quasi_static=True))
    scenario, x, v = dependent.scenarios[0], dependent.positions[0], dependent.trajectory_velocities(0)
    model = _stub(lambda model, graph: torch.zeros_like(graph.pos))
    rollout(model, scenario, x[0], v[0], 4, known_positions=x, warmup=0, precision="f32", frames_per_call=4)
    assert len(model.seen) == 4
