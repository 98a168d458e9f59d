"""model.mirror_average: the answer to a frame averaged with the reflected answer to its mirror
image, so a model is exactly mirror-equivariant at inference; python -m bsms.pretrained --set."""

import copy

import numpy as np
import pytest
import torch
from conftest import tiny_run_config

from bsms.augment import ROTATED_FIELDS, mirrored, reflected
from bsms.checkpoint import CheckpointError
from bsms.config import ConfigError
from bsms.data import FrameDataset
from bsms.fields import FieldSpec
from bsms.infer.pretrained import export, parse_settings
from bsms.infer.pretrained import main as export_main
from bsms.models.simulator import LearnedSimulator
from bsms.rollouts.learned_rollouts import learned_rollouts
from bsms.run import load_config, load_model, prepare_dataset, split_files
from bsms.training.trainer import Trainer
from datagen.dataset import load

GRAPH = {"levels": 3, "constants": ["log_E"], "from_rest": True, "penetration": True, "clearance": True,
         "elastic": True}


# the general network (two hidden layers, LayerNorm: the two images in two passes) and a lean one
# (the press recipe's: both images in one pass of the fused blocks, BSMSGNN.runs_groups)
NETWORKS = {"general": {}, "lean": {"hidden_layers": 1, "layer_norm": False, "first_level": 1}}


@pytest.fixture(scope="module", params=list(NETWORKS))
def run(request, tiny_dataset, tmp_path_factory):
    """A tiny from-rest run trained with train.mirror (a few steps: the weights are arbitrary, not
    equivariant), its config asking for the mirror average."""
    model = {"name": "bsms_gnn", "latent": 16, "mirror_average": True, **NETWORKS[request.param]}
    config = load_config(tiny_run_config(tiny_dataset, tmp_path_factory.mktemp("runs"), graph=GRAPH,
                                         noise={"position": 0.0, "velocity": 0.0}, model=model,
                                         train={"steps": 6, "valid_every": 6, "checkpoint_every": 6, "mirror": True}))
    Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    return config.run_dir


def _graph(run, frame=5):
    model, config, _ = load_model(run, "latest")
    folder = prepare_dataset(config, progress=False)
    return model, config, FrameDataset(split_files(folder, "train")[:1], config.graph)[frame]


def test_reflected_negates_the_first_component_of_every_vector_field_only(run):
    _, _, graph = _graph(run)
    image = reflected(graph)
    present = [key for key in ROTATED_FIELDS if key in graph]
    assert {"pos", "rest_pos", "penetration", "clearance", "elastic"} <= set(present)
    for key in present:
        assert torch.equal(image[key][:, 0], -graph[key][:, 0]) and torch.equal(image[key][:, 1:], graph[key][:, 1:])
    for key in graph.keys():
        if key not in ROTATED_FIELDS:
            assert image[key] is graph[key]  # structure shared, not copied
    assert torch.equal(reflected(image).pos, graph.pos) and image.pos is not graph.pos


def test_the_mirror_average_is_exactly_equivariant_and_the_network_alone_is_not(run):
    model, config, graph = _graph(run)
    assert model.mirror_average
    plain = copy.deepcopy(model)
    plain.mirror_average = False
    flip = torch.tensor([-1.0, 1.0])
    image = reflected(graph)
    own, mirror_answer = plain.velocity_change(graph), plain.velocity_change(image)
    assert (mirror_answer - own * flip).abs().max() > 1e-3 * own.abs().max()  # the network alone: not equivariant
    averaged, expected = model.velocity_change(graph), 0.5 * (own + mirror_answer * flip)
    if model.core.runs_groups():  # both images in one pass: the products over the paired rows round apart
        torch.testing.assert_close(averaged, expected, rtol=0, atol=1e-6 * float(expected.abs().max()))
    else:
        assert torch.equal(averaged, expected)
    assert torch.equal(model.velocity_change(image), averaged * flip)  # bit for bit: the sum commutes


def test_a_lean_network_runs_both_images_in_one_pass_with_the_answers_of_two(run, monkeypatch):
    """The lean network's blocks are fused, so the frame and its image go through the core once,
    side by side (groups=2); its answers are those of two passes to float32 round-off. The general
    network runs twice."""
    model, _, graph = _graph(run)
    lean = model.core.runs_groups()
    assert lean == (model.core.first_level == 1)
    groups = []
    forward = type(model.core).forward
    monkeypatch.setattr(type(model.core), "forward",
                        lambda core, *args, **kwargs: groups.append(kwargs.get("groups", 1)) or forward(core, *args,
                                                                                                          **kwargs))
    averaged = model.velocity_change(graph)
    assert groups == ([2] if lean else [1, 1])
    monkeypatch.setattr(model, "_paired", lambda *args: None)
    twice = model.velocity_change(graph)
    torch.testing.assert_close(averaged, twice, rtol=0, atol=1e-6 * float(twice.abs().max()))
    assert float(twice.abs().max()) > 0


def test_a_rollout_of_the_mirrored_trajectory_is_the_mirrored_rollout(run, tmp_path):
    model, config, _ = _graph(run)
    folder = prepare_dataset(config, progress=False)
    trajectory = load(split_files(folder, "test")[0])
    steps = [len(trajectory.positions) - 1] * 2
    (plain, a), (_, b) = learned_rollouts(model, config.graph, [trajectory, mirrored(trajectory)], tmp_path, steps)
    size = np.ptp(trajectory.positions[0], axis=0).max()
    gap = np.abs(b.positions * np.array([-1.0, 1.0]) - a.positions).max()
    assert gap < 1e-5 * size, gap
    assert np.abs(a.positions - a.positions[0]).max() > 1e3 * gap  # the rollout moves
    assert plain["vs_rest"] > 0


def test_mirror_average_needs_train_mirror_and_lagrangian_data(tiny_dataset, tmp_path):
    with pytest.raises(ConfigError, match=r"^config key 'model.mirror_average' averages the answers to each frame and "
                                          r"to its mirror image: train the network on both images \(train.mirror: "
                                          r"true\)$"):
        load_config(tiny_run_config(tiny_dataset, tmp_path, model={"mirror_average": True}))
    eulerian = FieldSpec.from_dict({"kind": "eulerian", "dim": 2, "material_dim": 2,
                                    "inputs": [["velocity", 2]], "outputs": [["velocity", 2, "change"]],
                                    "positions": "", "types": "", "n_types": 3})
    with pytest.raises(ValueError, match=r"^mirror_average reflects positions and velocities; this data has "):
        LearnedSimulator("bsms_gnn", 2, n_levels=2, fields=eulerian, mirror_average=True)


def test_an_export_can_turn_the_mirror_average_on(tiny_dataset, tmp_path, capsys):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path / "runs", graph=GRAPH,
                                         noise={"position": 0.0, "velocity": 0.0}, model={"latent": 16},
                                         train={"steps": 2, "valid_every": 2, "checkpoint_every": 2, "mirror": True}))
    Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    assert not load_model(config.run_dir, "latest")[0].mirror_average
    assert export_main([str(config.run_dir), str(tmp_path / "on"), "--which", "latest",
                        "--set", "model.mirror_average=true"]) == 0
    model, saved, _ = load_model(tmp_path / "on")
    assert model.mirror_average and saved.model.mirror_average
    assert "mirror_average: true" in (tmp_path / "on" / "config.yaml").read_text()
    torch.testing.assert_close(model.state_dict(), load_model(config.run_dir, "latest")[0].state_dict(), rtol=0, atol=0)
    for item, message in (("model.latent=3", "give KEY=VALUE with KEY one of model.mirror_average, model.rigid_step"),
                          ("model.mirror_average", "give KEY=VALUE with KEY one of model.mirror_average, model.rigid_step"),
                          ("model.mirror_average=1", "config key 'model.mirror_average' must be true or false, got 1"),
                          ("model.mirror_average=[", "the value is not valid YAML")):
        assert export_main([str(config.run_dir), str(tmp_path / "bad"), "--set", item]) == 2
        assert message in capsys.readouterr().err
    assert parse_settings(["model.mirror_average=false"]) == ["model.mirror_average=false"]
    with pytest.raises(ConfigError, match=r"^--set 'graph.levels=2': give KEY=VALUE with KEY one of "):
        export(config.run_dir, tmp_path / "refused", "latest", ["graph.levels=2"])
    unmirrored = load_config(tiny_run_config(tiny_dataset, tmp_path / "runs", name="plain", graph=GRAPH,
                                             noise={"position": 0.0, "velocity": 0.0}, model={"latent": 16},
                                             train={"steps": 2, "valid_every": 2, "checkpoint_every": 2}))
    Trainer(unmirrored, dataset_folder=prepare_dataset(unmirrored, progress=False)).fit()
    with pytest.raises(CheckpointError, match=r"model.mirror_average=true: config key 'model.mirror_average' averages"):
        export(unmirrored.run_dir, tmp_path / "refused", "latest", ["model.mirror_average=true"])
