"""train.frame_stride: a learned step of k data frames (bsms.rollouts.stride), trained from every offset and
rolled out with every data frame given back."""

import dataclasses

import numpy as np
import pytest
import torch
from conftest import tiny_run_config

from bsms.augment import strided
from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType
from bsms.fields import FieldSpec
from bsms.rollouts.learned_rollouts import learned_rollouts
from bsms.rollouts.rollout import rollout
from bsms.rollouts.stride import model_steps, strided_known, upsampled
from bsms.run import build_model, load_config, prepare_dataset, split_files
from datagen.dataset import load

OPTIONS = GraphOptions(levels=2)


@pytest.fixture(scope="module")
def files(tiny_dataset, tmp_path_factory):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path_factory.mktemp("runs")))
    return split_files(prepare_dataset(config, progress=False), "train")


def test_upsampling_is_exact_on_quadratic_motion():
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 5, 2))
    dt, k, frames = 0.01, 4, 22  # 22 frames: 6 model steps, the last two frames past the data's end dropped
    t = np.arange(model_steps(frames, k) + 1)[:, None, None] * k * dt
    states = a + b * t + c * t**2
    out = upsampled(states, b, k, dt, frames)
    tf = np.arange(frames + 1)[:, None, None] * dt
    assert out.shape == (frames + 1, 5, 2)
    np.testing.assert_allclose(out, a + b * tf + c * tf**2, rtol=0, atol=1e-15)
    assert np.array_equal(out[::k], states[: len(out[::k])]), "the model's states are kept exactly"


def test_upsampling_a_rotation_errs_by_the_cubic_order():
    """A point on a circle of radius 1 turned by h radians per model step (k = 4): away from the
    ends the Hermite curve errs by 1.27e-4 at h = 0.2, 8.2 times less at h = 0.1 (third order);
    the one-sided tangent at the last state makes the largest error, 4.8e-4."""
    interior, largest = [], []
    for h in (0.2, 0.1):
        k, frames = 4, 40
        angle = np.arange(model_steps(frames, k) + 1) * h
        states = np.stack([np.cos(angle), np.sin(angle)], -1)[:, None]
        out = upsampled(states, np.array([[0.0, h / k]]), k, 1.0, frames)
        fine = np.arange(frames + 1) * h / k
        error = np.abs(out[:, 0] - np.stack([np.cos(fine), np.sin(fine)], -1))
        interior.append(error[8:-8].max())
        largest.append(error.max())
    assert interior[0] < 1.5e-4 and largest[0] < 5.5e-4
    assert 7.5 < interior[0] / interior[1] < 9.0


def test_strided_trajectory_and_known_rows(files):
    trajectory = load(files[0])
    part = strided(trajectory, 2, 1)
    assert np.array_equal(part.times, trajectory.times[1::2])
    assert np.array_equal(part.positions, trajectory.positions[1::2])
    assert np.array_equal(part.velocities[0], trajectory.velocities[1])
    assert strided(trajectory, 1) is trajectory
    known = np.arange(7.0)[:, None, None] * np.ones((7, 3, 2))
    assert strided_known(known, 6, 4)[:, 0, 0].tolist() == [0.0, 4.0, 6.0], "the drive held past the data's end"
    with pytest.raises(ValueError, match="offset in"):
        strided(trajectory, 2, 2)


def test_strided_samples_step_k_frames_from_every_offset(files):
    k = 2
    data, plain = FrameDataset(files[:1], OPTIONS, frame_stride=k), FrameDataset(files[:1], OPTIONS)
    positions = plain.positions[0]
    frames = len(positions)
    assert len(data.positions) == k and len(data) == sum(len(range(o, frames, k)) - 1 for o in range(k))
    assert data.scenarios[0].frame_dt == pytest.approx(k * plain.scenarios[0].frame_dt, rel=1e-12)
    assert data.scenarios[1].hierarchy is data.scenarios[0].hierarchy, "the offsets share one scenario's graphs"
    free = plain.scenarios[0].node_type == NodeType.FREE
    dt = data.scenarios[0].frame_dt
    for offset in range(k):
        start = data._starts[offset]
        for j in range(1, data._starts[offset + 1] - start):  # sample j of this offset: frame o + j k
            t = offset + j * k
            pos, velocity, target = data.sample_state(offset, j)
            assert np.array_equal(pos, positions[t])
            np.testing.assert_allclose(velocity[free], (positions[t] - positions[t - k])[free] / dt, rtol=1e-12)
            np.testing.assert_allclose((velocity + target)[free], (positions[t + k] - positions[t])[free] / dt,
                                       rtol=1e-12, atol=1e-12)
            assert data.locate(start + j) == (offset, j)


class _Coast(torch.nn.Module):
    """A model that predicts no velocity change: every node coasts."""

    def __init__(self, stride: int):
        super().__init__()
        self.frame_stride, self.calls = stride, 0

    def velocity_change(self, graph, precision="f32"):
        self.calls += 1
        return torch.zeros_like(graph.pos, dtype=torch.float32)


def test_a_strided_rollout_steps_every_k_frames_and_returns_every_frame(files):
    trajectory = load(files[0])
    scenario = FrameDataset(files[:1], OPTIONS).scenarios[0]
    x0 = scenario.positions(trajectory.positions[:1], trajectory.obstacle_positions)[0]
    v0 = np.zeros_like(x0)
    v0[scenario.node_type == NodeType.FREE] = [0.3, -0.2]
    model = _Coast(3)
    result = rollout(model, scenario, x0, v0, 7, warmup=0)
    assert model.calls == 3, "7 frames at 3 per step: 3 model calls"
    assert result.positions.shape[0] == 8 and len(result.step_seconds) == 7 and len(result.graph_nodes) == 7
    times = np.arange(8)[:, None, None] * scenario.frame_dt
    np.testing.assert_allclose(result.positions, x0 + times * v0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(result.velocities[1:], np.broadcast_to(v0, (7, *v0.shape)), atol=1e-12)


def test_config_checks_and_a_strided_model_through_training_and_validation(tiny_dataset, tmp_path):
    with pytest.raises(ConfigError, match="'train.frame_stride' must be 1 with 'graph.from_rest'"):
        load_config(tiny_run_config(tiny_dataset, tmp_path, graph={"from_rest": True},
                                    noise={"position": 0.0, "velocity": 0.0}, train={"frame_stride": 2}))
    with pytest.raises(ConfigError, match="'train.frame_stride' must be >= 1"):
        load_config(tiny_run_config(tiny_dataset, tmp_path, train={"frame_stride": 0}))
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, train={"frame_stride": 2}))
    model = build_model(config, 2)
    assert model.frame_stride == 2
    folder = prepare_dataset(config, progress=False)
    trajectories = [load(f) for f in split_files(folder, "valid")]
    frames = [len(t.times) - 1 for t in trajectories]
    (metrics, result), = learned_rollouts(model, config.graph, trajectories, tmp_path / "cache", frames)
    assert result.positions.shape[0] == frames[0] + 1 and np.isfinite(metrics["vs_rest"])
    assert dataclasses.is_dataclass(result)


def test_a_strided_run_trains_validates_by_rollout_and_loads_with_its_stride(tiny_dataset, tmp_path, one_thread):
    from bsms.run import load_model
    from bsms.training.trainer import Trainer

    config = load_config(tiny_run_config(tiny_dataset, tmp_path, train={
        "frame_stride": 2, "steps": 2, "valid_every": 2, "checkpoint_every": 2, "validation": "rollout"},
        evaluate={"enabled": False}))
    trainer = Trainer(config)
    plain = FrameDataset(trainer._train_files(), config.graph)
    assert len(trainer.train_set.positions) == 2 * len(plain.positions), "two offsets per training file"
    assert len(trainer.train_set) == len(plain) - len(plain.positions) * 1, "every frame but the last k starts a step"
    metrics = trainer.fit()
    assert np.isfinite(metrics["loss"]) and np.isfinite(trainer.valid_vs_rest)
    model, loaded, _ = load_model(config.run_dir, "latest")
    assert model.frame_stride == 2 and loaded.train.frame_stride == 2


@pytest.mark.parametrize("compiled", [True, False])
def test_edge_velocity_puts_a_rigid_turns_rate_on_every_mesh_edge(files, compiled, monkeypatch):
    """model.edge_velocity: each mesh edge's last d + 1 inputs are v_receiver - v_sender and its norm;
    for a rigid turn at rate w they are w J (x_receiver - x_sender) and w |x_receiver - x_sender|, on
    every level (the compiled edge inputs and torch's alike)."""
    from bsms.models import native
    from bsms.models.simulator import LearnedSimulator

    if not compiled:
        monkeypatch.setattr(native, "edge_offsets", lambda *args, **kwargs: None)
    graph = FrameDataset(files[:1], GraphOptions(levels=3))[3]
    rate, centre = 2.5, graph.pos.mean(0)
    turn = torch.tensor([[0.0, 1.0], [-1.0, 0.0]], dtype=graph.pos.dtype)  # row vector @ turn = J x
    graph.velocity = rate * (graph.pos - centre) @ turn
    model = LearnedSimulator("bsms_gnn", 2, n_levels=3, edge_velocity=True)
    for group in model.edge_normalizers:  # identity statistics: the raw inputs come through
        mesh = group[0]
        mesh.count.fill_(1.0), mesh.total.zero_(), mesh.total_squares.fill_(1.0)
    assert mesh.total.shape == (9,), "rest and world offsets and norms, then the velocity difference and norm"
    with torch.no_grad():
        for level in range(3):
            inputs = model._level(graph, level, accumulate=False)
            index, features = inputs.edge_sets[0]
            offsets = features[:, 3:5].double()  # world offsets: receiver minus sender
            np.testing.assert_allclose(features[:, 6:8].double(), rate * offsets @ turn.double(), rtol=1e-4, atol=1e-6)
            np.testing.assert_allclose(features[:, 8].double(), rate * offsets.norm(dim=1), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match="edge_velocity differences node velocities along mesh edges"):
        LearnedSimulator("bsms_gnn", 3, edge_velocity=True, fields=FieldSpec.lagrangian(3, 2))
