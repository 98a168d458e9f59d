"""bsms.models.precision: the core network in bfloat16 where the hardware has it, and float32
(features, normalisers) and float64 (integration) around it in every precision."""

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from torch_geometric.data import Batch

import bsms.models.precision as precision
import bsms.training.trainer
from bsms.config import ConfigError
from bsms.data import GraphOptions, NodeType, Scenario
from bsms.models.normalize import Normalizer
from bsms.models.simulator import LearnedSimulator
from bsms.rollouts.rollout import rollout
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer
from datagen import shapes

DIM = 2


def floor_scenario() -> Scenario:
    """A clamped-at-one-end strip resting just above a floor: mesh and contact edges on every level."""
    mesh = shapes.rectangle(1.0, 0.3, 0.06, origin=(0.0, 0.05))
    node_type = np.where(mesh.nodes[:, 0] < 1e-9, NodeType.CLAMPED, NodeType.FREE)
    return Scenario.build(mesh, GraphOptions(levels=3), frame_dt=0.01, node_type=node_type,
                          obstacle_nodes=np.array([[-0.5, 0.0], [1.5, 0.0]]), obstacle_facets=np.array([[0, 1]]))


def state(scenario: Scenario, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions near rest and a smooth velocity field, (N, d) each."""
    rng = np.random.default_rng(seed)
    x = scenario.rest_pos
    velocity = np.sin(3.0 * x[:, ::-1] + rng.uniform(0, 6, DIM)) * rng.uniform(0.1, 1.0, DIM)
    velocity[scenario.kinematic] = 0.0
    return x + 1e-3 * velocity, velocity


def warmed_up(core: str, scenario: Scenario) -> LearnedSimulator:
    """An untrained model whose normalisers have seen a few states (inputs of unit scale);
    ``bsms_gnn_lean``: the press recipe's core (no LayerNorm, messages from level 1, one hidden layer)."""
    torch.manual_seed(0)
    lean = core == "bsms_gnn_lean"
    model = LearnedSimulator("bsms_gnn" if lean else core, DIM, n_levels=3, contact=True, latent=32, n_passes=4,
                             hidden_layers=1 if lean else 2,
                             core_options={"layer_norm": False, "first_level": 1} if lean else None)
    for seed in range(4):
        pos, velocity = state(scenario, seed)
        graph = scenario.graph(pos, velocity, target=0.01 * velocity)
        model.loss(graph, accumulate=True)
    return model.eval()


def test_precision_names_are_checked():
    message = "precision must be one of 'auto', 'bf16', 'f32', got 'fp16'"
    with pytest.raises(ValueError, match=message):
        precision.network_dtype("fp16", "cpu")
    scenario = floor_scenario()
    model = warmed_up("bsms_gnn", scenario)
    pos, velocity = state(scenario, 0)
    with pytest.raises(ValueError, match=message):
        model(scenario.graph(pos, velocity), precision="fp16")
    calls = []
    model.velocity_change = lambda *args, **kwargs: calls.append(1)  # a bad precision stops before any step
    with pytest.raises(ValueError, match=message):
        rollout(model, scenario, pos, velocity, 2, precision="fp16")
    assert not calls


def test_auto_is_bf16_only_where_the_hardware_has_it(monkeypatch):
    for has_bf16, expected in ((True, torch.bfloat16), (False, torch.float32)):
        monkeypatch.setattr(precision, "cpu_has_bf16", lambda has_bf16=has_bf16: has_bf16)
        assert precision.network_dtype("auto", "cpu") == expected
        assert precision.network_dtype("auto", "cpu", precision.CPU_BF16_MIN_LATENT) == expected
        assert precision.network_dtype("auto", "cpu", 32) == torch.float32, "narrow networks are faster in f32"
        assert precision.network_dtype("bf16", "cpu", 32) == torch.bfloat16
        assert precision.network_dtype("bf16", "cpu") == torch.bfloat16
        assert precision.network_dtype("f32", "cpu") == torch.float32
    assert precision.network_dtype("auto", "meta") == torch.float32


def record_dtypes(model: LearnedSimulator) -> dict:
    """dtype of every normaliser output and of the core's first Linear layer's output, per call."""
    seen = {"normalizers": set(), "network": set()}
    for module in model.modules():
        if isinstance(module, Normalizer):
            module.register_forward_hook(lambda m, args, out: seen["normalizers"].add(out.dtype))
    first = next(m for m in model.core.modules() if isinstance(m, torch.nn.Linear))
    first.register_forward_hook(lambda m, args, out: seen["network"].add(out.dtype))
    return seen


@pytest.mark.parametrize("core", ["bsms_gnn", "meshgraphnets", "bsms_gnn_lean"])
def test_bf16_network_is_close_to_f32_with_float32_features(core):
    scenario = floor_scenario()
    model = warmed_up(core, scenario)
    seen = record_dtypes(model)
    worst = 0.0
    for seed in range(4, 8):
        graph = scenario.graph(*state(scenario, seed))
        with torch.no_grad():
            f32 = model(graph, precision="f32")
            assert seen == {"normalizers": {torch.float32}, "network": {torch.float32}}
            bf16 = model(graph, precision="bf16")
            assert seen == {"normalizers": {torch.float32}, "network": {torch.float32, torch.bfloat16}}
            seen["network"].clear()
        assert bf16.dtype == torch.float32
        worst = max(worst, float((bf16 - f32).abs().max() / f32.abs().max()))
    # bfloat16 keeps 8 significant bits: measured 2.0e-2 (bsms_gnn), 2.8e-2 (meshgraphnets) and 9.2e-3
    # (bsms_gnn_lean) of the output's scale for these untrained networks
    assert 1e-4 < worst < 0.1, worst


def test_a_bf16_rollout_integrates_in_float64():
    scenario = floor_scenario()
    model = warmed_up("bsms_gnn", scenario)
    seen = record_dtypes(model)
    pos, velocity = state(scenario, 9)
    runs = {p: rollout(model, scenario, pos, velocity, 3, warmup=0, precision=p) for p in ("f32", "bf16")}
    assert seen["network"] == {torch.float32, torch.bfloat16}
    for run in runs.values():
        assert run.finite and run.positions.dtype == run.velocities.dtype == np.float64
    free = scenario.node_type == NodeType.FREE
    # kinematic nodes follow their prescribed motion exactly in both
    assert np.array_equal(runs["bf16"].positions[:, ~free], runs["f32"].positions[:, ~free])
    step = np.abs(runs["f32"].positions[-1] - pos)[free].max()
    assert np.abs(runs["bf16"].positions - runs["f32"].positions).max() < 0.1 * step


def test_train_amp_on_cpu_only_with_bf16_instructions(tiny_dataset, tmp_path, monkeypatch, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, name="amp", train={"amp": True, "device": "cpu"}))
    folder = prepare_dataset(config, progress=False)
    monkeypatch.setattr(bsms.training.trainer, "cpu_has_bf16", lambda: False)
    with pytest.raises(ConfigError, match="'train.amp' needs a CUDA device or a CPU with bfloat16 instructions "
                                          r"\(AMX-BF16 or AVX512-BF16\).*set train.amp: false"):
        Trainer(config, dataset_folder=folder)
    monkeypatch.setattr(bsms.training.trainer, "cpu_has_bf16", lambda: True)
    trainer = Trainer(config, dataset_folder=folder)
    seen = record_dtypes(trainer.model)
    loss = trainer.train_step(Batch.from_data_list([trainer.train_set[(0, (0, 0, 0))]]))
    assert np.isfinite(loss) and seen["network"] == {torch.bfloat16} and seen["normalizers"] == {torch.float32}
