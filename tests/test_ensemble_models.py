"""Ensembles (bsms.models.ensemble, bsms.ensemble): several runs joined by python -m bsms.pretrained,
loaded by every command taking a run, answering as the mean of their members."""

import json

import meshio
import numpy as np
import pytest
import torch
import yaml
from conftest import tiny_run_config

from bsms.checkpoint import CheckpointError
from bsms.data import FrameDataset
from bsms.ensemble import ENSEMBLE_FILE, member_folders
from bsms.fields import world_positions
from bsms.infer import main as infer_main
from bsms.infer.pretrained import export_ensemble
from bsms.infer.pretrained import main as export_main
from bsms.models.ensemble import Ensemble
from bsms.rollouts.learned_rollouts import learned_rollouts
from bsms.rollouts.rollout import body_size
from bsms.run import build_model, load_config, load_model, prepare_dataset, split_files
from bsms.training.trainer import Trainer
from datagen import shapes
from datagen.dataset import load

FROM_REST = {"levels": 3, "constants": ["log_E"], "from_rest": True}


def train(dataset, runs, name, seed, graph=None):
    config = load_config(tiny_run_config(dataset, runs, name=name, graph=graph or FROM_REST,
                                         noise={"position": 0.0, "velocity": 0.0},
                                         train={"steps": 4, "valid_every": 4, "checkpoint_every": 4, "seed": seed}))
    Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    return runs / name


@pytest.fixture(scope="module")
def runs(tiny_dataset, tmp_path_factory):
    folder = tmp_path_factory.mktemp("runs")
    return [train(tiny_dataset, folder, name, seed) for name, seed in (("a", 0), ("b", 1))]


@pytest.fixture(scope="module")
def joined(runs, tmp_path_factory):
    out = tmp_path_factory.mktemp("ensemble") / "ab"
    assert export_main([str(runs[0]), str(runs[1]), str(out)]) == 0
    return out


def test_the_ensemble_answers_the_mean_of_its_members(runs, tiny_folder):
    (a, config, _), (b, _, _) = load_model(runs[0]), load_model(runs[1])
    frames = FrameDataset(split_files(tiny_folder, "train")[:1], config.graph)
    graph = frames[3]
    first, second = a.velocity_change(graph), b.velocity_change(graph)
    assert (first - second).abs().max() > 1e-6  # two seeds, two answers
    assert torch.equal(Ensemble([a, b]).velocity_change(graph), (first + second) / 2)
    assert torch.equal(Ensemble([a, a]).velocity_change(graph), first)
    assert torch.equal(Ensemble([a, b]).member_changes(graph), torch.stack([first, second]))
    with pytest.raises(TypeError, match="train each member with python train.py CONFIG"):
        Ensemble([a, b])(graph)


def test_members_must_learn_the_same_fields(runs):
    a, config, _ = load_model(runs[0])
    other = build_model(config, 3)
    with pytest.raises(ValueError, match="ensemble member 1 has dim 3, member 0 2: every member must learn the same"):
        Ensemble([a, other])
    with pytest.raises(ValueError, match="at least one member"):
        Ensemble([])


def test_the_exported_folder_loads_as_the_ensemble_of_its_runs(runs, joined, capsys):
    assert yaml.safe_load((joined / ENSEMBLE_FILE).read_text()) == {"members": ["members/0-a", "members/1-b"]}
    assert member_folders(joined) == [joined / "members" / "0-a", joined / "members" / "1-b"]
    assert (joined / "config.yaml").read_text() == (joined / "members" / "0-a" / "config.yaml").read_text()
    assert json.loads((joined / "dataset.json").read_text())["family"] == "glyphs"
    model, config, state = load_model(joined)
    assert isinstance(model, Ensemble) and len(model.members) == 2 and config.name == "a+b"
    assert state["members"] == [str(f) for f in member_folders(joined)]
    for member, run in zip(model.members, runs, strict=True):
        for (key, value), (key2, value2) in zip(member.state_dict().items(), load_model(run)[0].state_dict().items(),
                                                strict=True):
            assert key == key2 and torch.equal(value, value2)
    # from the rest shape every frame stands alone: the ensemble's rollout is the mean of its members'
    folder = prepare_dataset(config, progress=False)
    trajectories = [load(p) for p in split_files(folder, "train")[:2]]
    frames = [len(world_positions(model.spec, t)) - 1 for t in trajectories]
    alone = [[r.positions for _, r in learned_rollouts(m, config.graph, trajectories, folder / "hierarchies", frames)]
             for m in model.members]
    mean = [r.positions for _, r in learned_rollouts(model, config.graph, trajectories, folder / "hierarchies",
                                                     frames)]
    for k in range(2):
        assert np.abs(alone[0][k] - alone[1][k]).max() > 1e-7
        # the mean of float32 answers against the mean of float64 positions: float32 round-off of a step
        np.testing.assert_allclose(mean[k], (alone[0][k] + alone[1][k]) / 2, rtol=0, atol=1e-8)


def test_infer_on_an_ensemble_reports_how_far_its_members_disagree(runs, joined, tmp_path, capsys):
    mesh = shapes.disk(1.0, 0.3)
    mesh_file = tmp_path / "disk.msh"
    meshio.write(mesh_file, meshio.Mesh(np.pad(mesh.nodes, ((0, 0), (0, 1))), [("triangle", mesh.cells)]))
    predictions = {}
    for folder, name in ((joined, "ab"), (runs[0], "a"), (runs[1], "b")):
        assert infer_main([str(folder), "--mesh", str(mesh_file), "--steps", "3", "--out", str(tmp_path / name),
                           "--quiet"]) == 0
        with meshio.xdmf.TimeSeriesReader(str(tmp_path / name / "prediction.xdmf")) as reader:
            reader.read_points_cells()
            data = [reader.read_data(k)[1] for k in range(4)]
        predictions[name] = (np.stack([d["position"] for d in data]),
                             np.stack([d["spread"] for d in data]) if "spread" in data[0] else None)
    summary = json.loads((tmp_path / "ab" / "summary.json").read_text())
    (ab, spread), (a, _), (b, _) = predictions["ab"], predictions["a"], predictions["b"]
    assert predictions["a"][1] is None and "members" not in json.loads((tmp_path / "a" / "summary.json").read_text())
    np.testing.assert_allclose(ab, (a + b) / 2, rtol=0, atol=1e-8)  # float32 round-off of a step
    np.testing.assert_allclose(spread, np.linalg.norm(a - b, axis=-1) / 2, rtol=1e-12, atol=1e-18)
    size = body_size(ab[0])  # the disk as the family placed (and scaled) it
    free = np.ones(len(mesh.nodes), bool)  # a glyph's nodes are all free
    expected = np.sqrt(np.mean(spread[1:][:, free] ** 2))
    assert summary["members"] == 2 and summary["spread_all"] == pytest.approx(expected, rel=1e-12)
    assert summary["spread_rel_all"] == pytest.approx(summary["spread_all"] / size, rel=1e-6)
    assert f"the mean of 2 members, who disagree by {summary['spread_rel_all']:.3g} of the body size" \
        in capsys.readouterr().out


def test_runs_that_cannot_join_are_named_with_the_reason(runs, joined, tiny_dataset, tmp_path, capsys):
    other = train(tiny_dataset, tmp_path, "c", 2, graph={**FROM_REST, "levels": 2})
    with pytest.raises(CheckpointError, match=r"ensemble member .*c builds another graph than .*a \(graph.levels\): "
                                              "members must share their graph options"):
        export_ensemble([runs[0], other], tmp_path / "x")
    assert not (tmp_path / "x").exists()
    scene = tmp_path / "scene"
    export_main([str(runs[1]), str(scene)])
    dataset = json.loads((scene / "dataset.json").read_text())
    dataset["params"]["gravity"] = 1.0
    (scene / "dataset.json").write_text(json.dumps(dataset))
    with pytest.raises(CheckpointError, match=r"ensemble member .*scene learned another scene than .*a \(dataset "
                                              r"params differ\): members must be trained on one family's setting"):
        export_ensemble([runs[0], scene], tmp_path / "y")
    with pytest.raises(CheckpointError, match="an ensemble joins at least two runs"):
        export_ensemble([runs[0]], tmp_path / "z")
    assert export_main([str(joined), str(runs[0]), str(tmp_path / "w")]) == 2
    assert f"error: {joined} is an ensemble; give its members' runs to join them into another" \
        in capsys.readouterr().err


def test_a_broken_ensemble_folder_is_named_with_the_fix(joined, tmp_path):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(joined, broken)
    (broken / ENSEMBLE_FILE).write_text("members: [members/0-a, members/9-gone]\n")
    with pytest.raises(CheckpointError, match=r"ensemble.yaml lists member .*9-gone, which does not exist"):
        load_model(broken)
    for text in ("members: []\n", "members: members/0-a\n", "[1, 2]\n", "members: [\n"):
        (broken / ENSEMBLE_FILE).write_text(text)
        with pytest.raises(CheckpointError, match="ensemble.yaml .*python -m bsms.pretrained RUN RUN ... OUT"):
            load_model(broken)


def test_evaluate_reports_the_ensemble_as_the_mean_of_its_members(runs, joined, capsys):
    """bsms.evaluate reads the ensemble folder (its members hold best.pt only: --checkpoint latest
    falls back to it, as on any pretrained folder) and scores the members' mean."""
    from bsms.evaluate import main as evaluate_main

    assert evaluate_main([str(joined), "--split", "train", "--trajectories", "2", "--no-solver", "--checkpoint",
                          "latest", "--quiet"]) == 0
    metrics = json.loads((joined / "evaluation" / "metrics.json").read_text())
    (row,) = metrics["rows"]
    assert row["label"] == "a+b"
    model, config, _ = load_model(joined)
    folder = prepare_dataset(config, progress=False)
    trajectories = [load(p) for p in split_files(folder, "train")[:2]]
    frames = [len(world_positions(model.spec, t)) - 1 for t in trajectories]
    scored = learned_rollouts(model, config.graph, trajectories, folder / "hierarchies", frames)
    assert row["vs_rest"] == pytest.approx(np.mean([m["vs_rest"] for m, _ in scored]), rel=1e-9)
    report = (joined / "report.md").read_text()
    assert "(the first of an ensemble of 2, averaged frame by frame)" in report


def test_the_surrogate_benchmark_copies_an_ensemble_with_its_members(joined, tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from surrogate_vs_solver import copy_run

    copy_run(joined, tmp_path / "run")
    copied, original = load_model(tmp_path / "run")[0], load_model(joined)[0]
    assert isinstance(copied, Ensemble) and len(copied.members) == 2
    for (key, value), (key2, value2) in zip(copied.state_dict().items(), original.state_dict().items(), strict=True):
        assert key == key2 and torch.equal(value, value2)


def test_exporting_over_an_earlier_export_replaces_it_whole(runs, tmp_path):
    out = tmp_path / "pretrained"
    assert export_main([str(runs[0]), str(out)]) == 0
    assert export_main([str(runs[0]), str(runs[1]), str(out)]) == 0  # a single model, then an ensemble over it
    assert not (out / "checkpoints").exists() and not (out / "metrics.csv").exists()
    assert isinstance(load_model(out)[0], Ensemble)
    assert export_main([str(runs[1]), str(out)]) == 0  # and a single model over the ensemble
    assert not (out / ENSEMBLE_FILE).exists() and not (out / "members").exists()
    model, config, _ = load_model(out)
    assert not isinstance(model, Ensemble) and config.name == "b"
    with pytest.raises(CheckpointError, match=r"run .*pretrained lies in .*pretrained: write the ensemble into a new "
                                              r"folder \(and move it there after\)"):
        export_ensemble([out, runs[0]], out)
