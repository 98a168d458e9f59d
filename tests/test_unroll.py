"""bsms.training.unroll: multi-step (pushforward) training, its states and targets, gradients and resume."""

import copy

import numpy as np
import pytest
import torch
import yaml
from conftest import tiny_run_config
from torch_geometric.data import Batch

from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType, NoiseOptions
from bsms.models.simulator import LearnedSimulator
from bsms.rollouts.rollout import rollout
from bsms.run import load_config, split_files
from bsms.training.trainer import Trainer
from bsms.training.unroll import UnrollSamples, collate, unrolled_loss

K = 3  # model steps per sample; the tiny trajectories have 7 frames


@pytest.fixture(scope="module")
def folder(tiny_folder):
    return tiny_folder


@pytest.fixture(scope="module")
def frames(folder):
    """The tiny training trajectories (floor and walls as obstacle nodes, contact edges), no noise."""
    return FrameDataset(split_files(folder, "train"), GraphOptions(levels=3))


def small_model(seed: int = 0) -> LearnedSimulator:
    torch.manual_seed(seed)
    return LearnedSimulator("bsms_gnn", 2, n_levels=3, contact=True, latent=16)


class Stub(LearnedSimulator):
    """A simulator whose core is replaced by ``rule(model, graph)`` (normalised outputs), and
    which records the node inputs of every call."""

    def __init__(self, rule):
        super().__init__("bsms_gnn", 2, n_levels=3, contact=True, latent=8)
        self.rule, self.seen = rule, []

    def forward(self, graph, accumulate=False, precision="f32"):
        self.seen.append((graph.pos.clone(), graph.velocity.clone(), graph.scenario_nodes.clone()))
        return self.rule(self, graph)


def oracle(model, graph):  # the true velocity change (the graph's target)
    return model.output_normalizer(graph.target)


def zero(model, graph):  # no change: free fall without gravity, i.e. constant velocity
    return torch.zeros_like(graph.pos)


def whole_batch(samples, keys=None) -> tuple:
    keys = range(len(samples)) if keys is None else keys
    return collate([samples[key] for key in keys]), [samples.locate(key[0] if isinstance(key, tuple) else key)
                                                     for key in keys]


def per_sample(graph, values: torch.Tensor) -> list[torch.Tensor]:
    counts = graph["n_nodes_0"]
    return torch.split(values, counts.tolist() if torch.is_tensor(counts) else [int(counts)])


# ----------------------------------------------------------------------------- samples
def test_samples_never_reach_past_the_end(frames):
    lengths = [len(p) for p in frames.positions]
    samples = UnrollSamples(frames, K)
    assert len(samples) == sum(length - K for length in lengths)
    located = [samples.locate(i) for i in range(len(samples))]
    assert located == [(k, t) for k, length in enumerate(lengths) for t in range(length - K)]
    one = UnrollSamples(frames, 1)
    assert len(one) == len(frames) and [one.locate(i) for i in range(len(one))] == [
        frames.locate(i) for i in range(len(frames))]
    with pytest.raises(IndexError):
        samples.locate(len(samples))


def test_the_trainer_draws_only_samples_that_unroll(tiny_dataset, folder, tmp_path):
    trainer = Trainer(load_config(tiny_run_config(tiny_dataset, tmp_path, train={"unroll": K, "batch_size": 2})),
                      dataset_folder=folder)
    assert len(trainer.samples) == sum(len(p) - K for p in trainer.train_set.positions) == 8
    drawn = {i for step in range(4) for i in trainer.global_batch(step)}
    assert drawn == set(range(len(trainer.samples))), "every step of every epoch draws from the unrollable samples"
    for i in drawn:
        k, t = trainer.samples.locate(i)
        assert t + K <= len(trainer.train_set.positions[k]) - 1


# ----------------------------------------------------------------------------- losses, states and targets
def test_one_step_unroll_is_the_one_step_loss_bit_for_bit(folder):
    noisy = FrameDataset(split_files(folder, "train"), GraphOptions(levels=3), NoiseOptions(position=1e-3, velocity=1e-2))
    keys = [(i, (0, 5, i)) for i in range(len(noisy))]
    a = small_model()
    b = copy.deepcopy(a)
    batch, _ = whole_batch(UnrollSamples(noisy, 1), keys)
    for gradient in ("last", "all", "through"):  # K = 1: the three are one-step training
        a.zero_grad()
        unrolled = unrolled_loss(a, batch, None, 1, gradient, accumulate=gradient == "last")
        unrolled.backward()
        b.zero_grad()
        single = b.loss(Batch.from_data_list([noisy[key] for key in keys]), accumulate=gradient == "last",
                        reduction="sum")
        single.backward()
        assert torch.equal(unrolled, single)
        for (name, p), q in zip(a.named_parameters(), b.parameters(), strict=True):
            assert torch.equal(p.grad, q.grad), name
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(x, y), f"{name}: the normalisers learn alike"


def test_an_exact_model_unrolls_along_the_data(frames):
    """Predicting the true change keeps every step on the data: inputs, graphs and targets of
    step k are those of the one-step sample of frame t+k."""
    model = Stub(oracle)
    model.output_normalizer.accumulate(torch.randn(50, 2))  # a normaliser that is not the identity
    samples = UnrollSamples(frames, K)
    batch, located = whole_batch(samples)
    record = []
    loss = unrolled_loss(model, batch, samples, K, "all", record=record)
    assert float(loss) == 0.0
    assert len(record) == K
    for k, (graph, _) in enumerate(record):
        expected = Batch.from_data_list([frames[int(frames._starts[j]) + t + k] for j, t in located])
        assert torch.equal(graph.scenario_nodes, expected.scenario_nodes)
        assert torch.equal(graph.contact_index_0, expected.contact_index_0), "contacts follow the positions"
        for name in ("pos", "velocity", "target"):  # float32 round-off of the integration
            torch.testing.assert_close(graph[name], expected[name], rtol=0, atol=2e-6, msg=f"step {k}: {name}")


def test_a_zero_model_drifts_at_constant_velocity_and_is_corrected(frames):
    model = Stub(zero)
    samples = UnrollSamples(frames, K)
    batch, located = whole_batch(samples)
    record = []
    unrolled_loss(model, batch, samples, K, "last", record=record)
    for k, (graph, _) in enumerate(record):
        for (j, t), nodes, pos, velocity, target in zip(
                located, per_sample(graph, graph.scenario_nodes), per_sample(graph, graph.pos),
                per_sample(graph, graph.velocity), per_sample(graph, graph.target), strict=True):
            scenario, x, v = frames.scenarios[j], frames.positions[j], frames.trajectory_velocities(j)
            dt, nodes = scenario.frame_dt, nodes.numpy()
            free = scenario.node_type[nodes] == NodeType.FREE
            drift = x[t] + k * dt * v[t]
            correction = (x[t + k + 1] - x[t]) / dt - (k + 1) * v[t]
            np.testing.assert_allclose(pos.numpy()[free], drift[nodes][free], rtol=0, atol=1e-6)
            np.testing.assert_allclose(velocity.numpy()[free], v[t][nodes][free], rtol=0, atol=1e-6)
            np.testing.assert_allclose(target.numpy()[free], correction[nodes][free], rtol=1e-6, atol=1e-5)
            # kinematic nodes (the floor and walls) are where the data has them, with its velocities
            np.testing.assert_allclose(pos.numpy()[~free], x[t + k][nodes][~free], rtol=0, atol=1e-7)
            np.testing.assert_allclose(velocity.numpy()[~free], v[t + k][nodes][~free], rtol=0, atol=1e-7)
            if k:  # gravity and contacts: the drifting state has left the data
                assert np.abs(drift - x[t + k])[nodes][free].max() > 1e-4


def test_the_unroll_integrates_as_a_rollout(frames):
    """With the same state-dependent model, the unrolled inputs are a rollout's from frame t."""
    def rule(model, graph):
        return 0.3 * torch.tanh(graph.velocity) - 0.1

    samples = UnrollSamples(frames, K)
    j, t = samples.locate(len(samples) - 1)
    unrolled = Stub(rule)
    unrolled.output_normalizer.accumulate(torch.randn(50, 2))
    rolled = copy.deepcopy(unrolled)
    unrolled_loss(unrolled, collate([samples[len(samples) - 1]]), samples, K, "through")
    x, v = frames.positions[j], frames.trajectory_velocities(j)
    rollout(rolled, frames.scenarios[j], x[t], v[t], K, known_positions=x[t:], warmup=0, precision="f32")
    assert len(unrolled.seen) == len(rolled.seen) == K
    for k, (a, b) in enumerate(zip(unrolled.seen, rolled.seen, strict=True)):
        for name, p, q in zip(("pos", "velocity", "nodes"), a, b, strict=True):
            assert torch.equal(p, q), f"step {k}: {name} differs from the rollout's"


# ----------------------------------------------------------------------------- gradients
def step_gradients(model, graph) -> list[torch.Tensor]:
    """Gradients of the one-step loss of ``graph`` (its state taken as given)."""
    model.zero_grad()
    model.prediction_loss(model(graph), graph, reduction="sum").backward()
    return [p.grad.clone() for p in model.parameters()]


def test_last_trains_only_the_last_step_and_all_every_step(frames):
    samples = UnrollSamples(frames, K)
    batch, _ = whole_batch(samples)
    model = small_model()
    model.loss(batch.graph, accumulate=True)  # normalisers that are not the identity
    enabled = []
    model.core.register_forward_hook(lambda module, args, out: enabled.append(torch.is_grad_enabled()))
    losses, gradients, records = {}, {}, {}
    for gradient in ("last", "all", "through"):
        record = []
        model.zero_grad()
        losses[gradient] = unrolled_loss(model, batch, samples, K, gradient, record=record)
        losses[gradient].backward()
        gradients[gradient], records[gradient] = [p.grad.clone() for p in model.parameters()], record
    assert enabled == [False, False, True] + [True] * (2 * K), "pushforward: no gradient before the last step"
    assert [p.requires_grad for _, p in records["last"]] == [False, False, True]
    # last: exactly the gradient of the last step's loss alone
    for got, want in zip(gradients["last"], step_gradients(model, records["last"][-1][0]), strict=True):
        assert torch.equal(got, want)
    # all: the mean of the steps' own gradients (states detached)
    per_step = [step_gradients(model, graph) for graph, _ in records["all"]]
    for got, *each in zip(gradients["all"], *per_step, strict=True):
        torch.testing.assert_close(got, sum(each) / K, rtol=1e-4, atol=1e-6 * float(got.abs().max()))  # float32 sums
    # through: the same states and loss, but gradients also flow through the predicted states
    assert not records["all"][1][0].pos.requires_grad and records["through"][1][0].pos.requires_grad
    torch.testing.assert_close(losses["through"], losses["all"], rtol=1e-6, atol=0)
    difference = max(float((a - b).abs().max()) for a, b in zip(gradients["through"], gradients["all"], strict=True))
    assert difference > 1e-6 * max(float(g.abs().max()) for g in gradients["all"])


def test_a_diverging_unroll_gives_a_non_finite_loss_and_gradient(frames):
    samples = UnrollSamples(frames, K)
    model = Stub(lambda m, graph: torch.full_like(graph.pos, float("inf")) + 0 * next(m.parameters()).sum())
    loss = unrolled_loss(model, whole_batch(samples)[0], samples, K, "last")
    loss.backward()
    assert not torch.isfinite(loss) and not all(torch.isfinite(p.grad).all() for p in model.parameters())
    assert len(model.seen) == 1, "the unroll stops at the first non-finite state"


# ----------------------------------------------------------------------------- trainer
def test_warmup_trains_one_step_first(tiny_dataset, folder, tmp_path, one_thread):
    trainer = Trainer(load_config(tiny_run_config(tiny_dataset, tmp_path, train={
        "unroll": K, "unroll_warmup": 2, "unroll_gradient": "all", "steps": 4})), dataset_folder=folder)
    calls = []
    trainer.model.core.register_forward_hook(lambda module, args, out: calls.append(trainer.step))
    summary = trainer.fit()
    assert np.isfinite(summary["loss"])
    assert [calls.count(step) for step in range(4)] == [1, 1, K, K]  # validation calls come after the steps


def test_resume_with_unroll_continues_exactly(tiny_dataset, folder, tmp_path, one_thread):
    train = {"unroll": K, "steps": 8, "checkpoint_every": 4, "valid_every": 4}
    whole = Trainer(load_config(tiny_run_config(tiny_dataset, tmp_path / "a", train=train)), dataset_folder=folder)
    whole.fit()
    data = tiny_run_config(tiny_dataset, tmp_path / "b", train=train)
    Trainer(load_config(data), dataset_folder=folder).fit(stop_at=4)
    resumed = Trainer(load_config(data), dataset_folder=folder, resume=True)
    assert resumed.step == 4
    resumed.fit()
    for (name, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values(), strict=True):
        assert torch.equal(a, b), f"{name} differs after resume"
    rows_a = (tmp_path / "a/tiny/metrics.csv").read_text().splitlines()
    rows_b = (tmp_path / "b/tiny/metrics.csv").read_text().splitlines()
    assert [r.split(",")[:3] for r in rows_a] == [r.split(",")[:3] for r in rows_b]


def test_runs_saved_before_unrolling_resume_as_one_step(tiny_dataset, folder, tmp_path, one_thread):
    data = tiny_run_config(tiny_dataset, tmp_path, train={"steps": 4})
    Trainer(load_config(data), dataset_folder=folder).fit(stop_at=2)
    saved = tmp_path / "tiny" / "config.yaml"
    config = yaml.safe_load(saved.read_text())
    for key in ("unroll", "unroll_gradient", "unroll_warmup"):
        del config["train"][key]
    saved.write_text(yaml.safe_dump(config))
    assert Trainer(load_config(data), dataset_folder=folder, resume=True).fit()["steps"] == 4
    with pytest.raises(ConfigError, match=r"config key 'train.unroll' was 1 and is now 2; resume with train.unroll=1"):
        Trainer(load_config(tiny_run_config(tiny_dataset, tmp_path, train={"steps": 4, "unroll": 2})),
                dataset_folder=folder, resume=True)


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("train, message", [
    ({"unroll": 0}, "config key 'train.unroll' must be >= 1, got 0"),
    ({"unroll_gradient": "first"},
     "config key 'train.unroll_gradient' must be one of 'last', 'all', 'through', got 'first'"),
    ({"unroll_warmup": -1}, "config key 'train.unroll_warmup' must be >= 0, got -1"),
    ({"unroll": 1.5}, "config key 'train.unroll' must be an integer, got 1.5"),
])
def test_config_errors_name_the_key(tiny_dataset, tmp_path, train, message):
    with pytest.raises(ConfigError) as info:
        load_config(tiny_run_config(tiny_dataset, tmp_path, train=train))
    assert str(info.value) == message


def test_an_unroll_longer_than_the_trajectories_is_a_config_error(tiny_dataset, folder, tmp_path):
    with pytest.raises(ConfigError) as info:
        Trainer(load_config(tiny_run_config(tiny_dataset, tmp_path, train={"unroll": 7})), dataset_folder=folder)
    assert str(info.value) == ("config key 'train.unroll' (7) needs trajectories of more than 7 frames; the longest of "
                               "the 2 training trajectories has 7")
    with pytest.raises(ValueError, match="an unrolled step needs the samples and their starts"):
        unrolled_loss(small_model(), Batch.from_data_list([FrameDataset(split_files(folder, "train"),
                                                                        GraphOptions(levels=3))[0]]), None, 2)
