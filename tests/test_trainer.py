"""bsms.training.trainer, bsms.checkpoint and train.py: learning, exact resume, data parallelism, errors."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import tiny_run_config
from torch_geometric.data import Batch

from bsms.checkpoint import CheckpointError, load_checkpoint
from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType, NoiseOptions, frame_velocities
from bsms.models.simulator import LearnedSimulator
from bsms.run import build_model, load_config, load_model, prepare_dataset, split_files
from bsms.training.trainer import Trainer, lr_factor

ROOT = Path(__file__).resolve().parents[1]


def config_dict(tiny_dataset, runs, **sections) -> dict:
    return tiny_run_config(tiny_dataset, runs, **sections)


@pytest.fixture(scope="module")
def folder(tiny_dataset, tmp_path_factory):
    config = load_config(config_dict(tiny_dataset, tmp_path_factory.mktemp("runs")))
    return prepare_dataset(config, progress=False)


# ----------------------------------------------------------------------------- samples
def test_a_samples_velocities_are_the_whole_trajectorys(folder, monkeypatch):
    """FrameDataset.sample_velocities differences only the frames a sample needs; it must give exactly what
    frame_velocities gives over the whole trajectory, kinematic nodes (every third here) included."""
    dataset = FrameDataset(split_files(folder, "train"), GraphOptions(levels=2))
    scenario_type = type(dataset.scenarios[0])
    monkeypatch.setattr(scenario_type, "kinematic", property(lambda self: np.arange(len(self.node_type)) % 3 == 0))
    for k, (scenario, positions) in enumerate(zip(dataset.scenarios, dataset.positions, strict=True)):
        whole = frame_velocities(positions, dataset.initial[k], scenario.frame_dt, scenario.kinematic)
        assert np.array_equal(dataset.trajectory_velocities(k), whole)
        for t in range(len(positions) - 1):
            velocity, coming = dataset.sample_velocities(k, t)
            assert np.array_equal(velocity, whole[t]) and np.array_equal(coming, whole[t + 1]), (k, t)


def test_samples_integrate_to_the_next_frame(folder):
    """No noise: x_t + dt (v_t + target) is frame t+1; v_t is the backward difference."""
    dataset = FrameDataset(split_files(folder, "train"), GraphOptions(levels=2))
    k, t = dataset.locate(len(dataset) - 1)
    graph = dataset[len(dataset) - 1]
    positions = dataset.positions[k][:, graph.scenario_nodes.numpy()]  # the nodes of the frame's graph
    dt = dataset.scenarios[k].frame_dt
    # graphs hold float32: a few float32 ulps of velocities and positions of order 1
    np.testing.assert_allclose(graph.velocity.numpy(), (positions[t] - positions[t - 1]) / dt, rtol=0, atol=1e-7)
    nxt = graph.pos.double() + dt * (graph.velocity.double() + graph.target.double())
    np.testing.assert_allclose(nxt.numpy(), positions[t + 1], atol=2e-7)
    assert len(dataset) == sum(len(p) - 1 for p in dataset.positions)


@pytest.mark.parametrize("gamma", [0.0, 1.0])
def test_noise_is_corrected_in_the_target(folder, gamma):
    noise = NoiseOptions(position=1e-3, velocity=1e-2, gamma=gamma)
    dataset = FrameDataset(split_files(folder, "train"), GraphOptions(levels=2), noise)
    clean, noisy = dataset[3], dataset[(3, (0, 7, 3))]
    again = dataset[(3, (0, 7, 3))]
    assert torch.equal(noisy.pos, again.pos), "the noise must be a function of its seed"
    free = clean.node_type == NodeType.FREE
    assert not torch.equal(noisy.pos[free], clean.pos[free])
    assert torch.equal(noisy.pos[~free], clean.pos[~free]) and torch.equal(noisy.target[~free], clean.target[~free])
    dt = float(clean.frame_dt[0])
    true_next_velocity = clean.velocity + clean.target
    if gamma == 1.0:  # the target brings the noisy position back to the true next position
        torch.testing.assert_close(noisy.pos + dt * (noisy.velocity + noisy.target),
                                   clean.pos + dt * true_next_velocity, atol=3e-7, rtol=0)
    else:  # the target restores the true next velocity
        torch.testing.assert_close(noisy.velocity + noisy.target, true_next_velocity, atol=3e-7, rtol=0)


def resting_on_the_floor(dataset: FrameDataset, k: int):
    """The last frame of trajectory ``k`` with its letters moved down to rest on the floor y = 0."""
    scenario, positions, velocities = dataset.scenarios[k], dataset.positions[k], dataset.trajectory_velocities(k)
    body = scenario.node_type != NodeType.OBSTACLE
    assert not body.all() and (scenario.body_id[~body] == scenario.body_id.max()).all()
    pos = positions[-1].copy()
    pos[body, 1] -= pos[body, 1].min() - 0.2 * scenario.contact_radius
    return scenario, scenario.graph(pos, velocities[-1])


def test_obstacles_and_contacts_batch_like_each_alone(folder):
    dataset = FrameDataset(split_files(folder, "train"), GraphOptions(levels=3))
    graphs = []
    for k in range(2):
        scenario, graph = resting_on_the_floor(dataset, k)
        contacts = graph.contact_index_0
        assert (scenario.body_id[contacts[0]] != scenario.body_id[contacts[1]]).all(), "no self-contact by default"
        for l in range(3):
            assert graph[f"contact_index_{l}"].shape[1] >= 4, "letters on the floor touch the walls on every level"
        graphs.append(graph)
    assert graphs[0].num_nodes != graphs[1].num_nodes, "the batch must join graphs of different sizes"
    torch.manual_seed(0)
    model = LearnedSimulator("bsms_gnn", 2, n_levels=3, contact=True, latent=16)
    model.loss(dataset[len(dataset) - 1], accumulate=True)  # normalisers that are not the identity
    model.eval()
    with torch.no_grad():
        alone = torch.cat([model(g) for g in graphs])
        together = model(Batch.from_data_list(graphs))
    torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)  # float32 matmuls of other shapes


# ----------------------------------------------------------------------------- training
def test_lr_schedule():
    assert lr_factor(0, 4, 20, 0.1) == 0.25 and lr_factor(3, 4, 20, 0.1) == 1.0
    assert lr_factor(4, 4, 20, 0.1) == pytest.approx(1.0, rel=1e-15)
    assert lr_factor(12, 4, 20, 0.1) == pytest.approx(0.55, rel=1e-15)
    assert lr_factor(20, 4, 20, 0.1) == pytest.approx(0.1, rel=1e-15)


# measured final/first loss: 0.0045 (bsms_gnn), 0.037 (meshgraphnets)
@pytest.mark.parametrize(("model", "ratio"), [("bsms_gnn", 0.04), ("meshgraphnets", 0.1)])
def test_overfits_a_tiny_dataset(tiny_dataset, folder, tmp_path, model, ratio, one_thread):
    config = load_config(config_dict(
        tiny_dataset, tmp_path, noise={"position": 0.0, "velocity": 0.0},
        model={"name": model, "passes": 4}, optim={"lr": 2e-3, "warmup": 10},
        train={"steps": 250, "batch_size": 4, "normalizer_steps": 10, "log_every": 10, "valid_every": 250,
               "checkpoint_every": 250},
    ))
    trainer = Trainer(config, dataset_folder=folder)
    first = trainer.train_step(Batch.from_data_list([trainer.train_set[i] for i in range(len(trainer.train_set))]))
    trainer.fit()
    whole = Batch.from_data_list([trainer.train_set[i] for i in range(len(trainer.train_set))])
    trainer.model.eval()
    with torch.no_grad():
        final = float(trainer.model.loss(whole))
    assert final < ratio * first, f"one-step loss fell from {first:.3g} to {final:.3g} only"
    metrics = (tmp_path / "tiny" / "metrics.csv").read_text().splitlines()
    assert metrics[0] == "step,loss,lr,seconds,samples_per_s,valid_rmse,valid_vs_rest"
    assert [int(line.split(",")[0]) for line in metrics[1:]] == list(range(10, 251, 10))
    assert metrics[-1].split(",")[-2] != "", "the last step is validated"
    assert metrics[-1].split(",")[-1] == "", "one-step validation has no at-rest ratio"


def test_rollout_validation_keeps_the_checkpoint_whose_rollouts_are_best(tiny_dataset, folder, tmp_path, one_thread):
    """train.validation: rollout logs the RMSE over every step of the validation trajectories'
    rollouts; best.pt is the step with the least, and evaluating it on the validation split
    (a fresh process's path: saved, reloaded, rolled out one by one) gives that number."""
    import json

    from bsms.evaluate import evaluate
    from bsms.run import EvaluateConfig

    trainer = Trainer(load_config(config_dict(tiny_dataset, tmp_path, train={"validation": "rollout"})),
                      dataset_folder=folder)
    trainer.fit()
    import csv

    with open(tmp_path / "tiny" / "metrics.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["valid_rmse"]]
    logged = [float(r["valid_rmse"]) for r in rows]
    skill = [float(r["valid_vs_rest"]) for r in rows]  # the rollouts' error over predicting no motion
    assert len(logged) == 2 and np.isfinite(logged).all() and np.isfinite(skill).all() and min(skill) > 0
    evaluate(tmp_path / "tiny", options=EvaluateConfig(split="valid", solver=[], gifs=0, batch=1), progress=False)
    learned = json.loads((tmp_path / "tiny" / "evaluation" / "metrics.json").read_text())["learned"]["tiny"]
    assert len(learned) == len(split_files(folder, "valid")) >= 1
    assert np.sqrt(np.mean([m["rmse_all"] ** 2 for m in learned])) == pytest.approx(min(logged), rel=1e-5)
    assert np.mean([m["vs_rest"] for m in learned]) == pytest.approx(skill[int(np.argmin(logged))], rel=1e-5)
    one_step = Trainer(load_config(config_dict(tiny_dataset, tmp_path / "one")), dataset_folder=folder)
    one_step.model.load_state_dict(trainer.model.state_dict())
    assert one_step.validate() < 0.5 * trainer.validate(), "a rollout's error exceeds the one-step error"


def test_an_unknown_validation_mode_names_the_key(tiny_dataset, tmp_path):
    with pytest.raises(ConfigError, match="config key 'train.validation' must be one of"):
        load_config(config_dict(tiny_dataset, tmp_path, train={"validation": "rollouts"}))


def test_resume_continues_exactly(tiny_dataset, folder, tmp_path, one_thread):
    whole = Trainer(load_config(config_dict(tiny_dataset, tmp_path / "a")), dataset_folder=folder)
    whole.fit()
    interrupted = Trainer(load_config(config_dict(tiny_dataset, tmp_path / "b")), dataset_folder=folder)
    interrupted.fit(stop_at=5)  # saves latest.pt at step 5, as a killed run would have
    del interrupted
    resumed = Trainer(load_config(config_dict(tiny_dataset, tmp_path / "b")), dataset_folder=folder, resume=True)
    assert resumed.step == 5
    resumed.fit()
    for (name, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values(), strict=True):
        assert torch.equal(a, b), f"{name} differs after resume"
    assert whole.optimizer.state_dict()["state"][0]["exp_avg"].equal(resumed.optimizer.state_dict()["state"][0]["exp_avg"])
    rows_a = [r.split(",")[:3] for r in (tmp_path / "a/tiny/metrics.csv").read_text().splitlines()]
    rows_b = [r.split(",")[:3] for r in (tmp_path / "b/tiny/metrics.csv").read_text().splitlines()]
    assert [r[0] for r in rows_a] == [r[0] for r in rows_b] == ["step", "4", "6", "8", "12"]
    assert rows_a[-1][1:] == rows_b[-1][1:], "loss and lr logged after resume equal the uninterrupted run's"


def test_two_processes_make_the_update_of_one(tiny_dataset, folder, tmp_path):
    """torchrun with 2 gloo processes, each on half the batch, equals one process on all of it;
    with train.shard each process holds half the training trajectories instead of all."""
    data = config_dict(tiny_dataset, tmp_path, train={"steps": 3, "batch_size": 4, "normalizer_steps": 2})
    outputs = {}
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    # sharded: a batch of 8 from shares of 5 samples each (10 in all), 4 per process
    for label, launcher, train in (("one", [sys.executable], {}), ("two", torchrun, {}),
                                   ("sharded", torchrun, {"shard": True, "batch_size": 8})):
        config = tmp_path / f"{label}.yaml"
        config.write_text(yaml.safe_dump({**data, "name": label, "train": {**data["train"], **train}}))
        outputs[label] = tmp_path / f"{label}.pt"
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.pathsep.join(sys.path)}
        result = subprocess.run([*launcher, str(ROOT / "tests" / "ddp_worker.py"), str(config), str(folder),
                                 str(outputs[label])], capture_output=True, text=True, env=env, timeout=300)
        assert result.returncode == 0, result.stderr[-3000:]
    one, two = torch.load(outputs["one"]), torch.load(outputs["two"])
    for name, value in one.items():
        # float32 sums in another order (measured: 1.4e-7)
        torch.testing.assert_close(two[name], value, rtol=1e-5, atol=5e-7, msg=lambda m, name=name: f"{name}: {m}")
    torch.manual_seed(0)
    initial = build_model(load_config(data), 2).state_dict()
    moved = max(float((one[name] - initial[name]).abs().max()) for name in initial if "normalizer" not in name)
    assert moved > 5e-4, "the steps must have changed the weights for the comparison to mean anything"  # 2e-3
    assert one["node_normalizer.count"] > 0 and torch.equal(one["node_normalizer.count"], two["node_normalizer.count"])
    train = [str(f) for f in split_files(folder, "train")]
    held = {label: [json.loads(Path(f"{outputs[label]}.rank{r}.json").read_text()) for r in (0, 1)]
            for label in ("two", "sharded")}
    assert len(train) == 2 and held["two"] == [train, train] and held["sharded"] == [train[:1], train[1:]]
    sharded = torch.load(outputs["sharded"])
    assert all(bool(torch.isfinite(v).all()) for v in sharded.values())
    assert max(float((sharded[name] - initial[name]).abs().max()) for name in initial if "normalizer" not in name) > 5e-4


def test_checkpoint_reproduces_predictions_in_a_fresh_process(tiny_dataset, folder, tmp_path, one_thread):
    trainer = Trainer(load_config(config_dict(tiny_dataset, tmp_path, train={"steps": 6})), dataset_folder=folder)
    trainer.fit()
    graph = trainer.valid_set[2]
    model, config, state = load_model(tmp_path / "tiny")
    assert state["step"] == 6 and config.model.name == "bsms_gnn"
    # both processes on one thread (one_thread here): the comparison is bitwise, and a float32
    # sum split over threads differs with the thread count (seen in the full suite on an AMD EPYC)
    with torch.no_grad():
        here = model.velocity_change(graph)
    torch.save(here, tmp_path / "here.pt")
    script = (
        "import sys, torch\n"
        "torch.set_num_threads(1)\n"
        "from bsms.data import FrameDataset\n"
        "from bsms.run import load_model, split_files\n"
        "model, config, _ = load_model(sys.argv[1])\n"
        "graph = FrameDataset(split_files(sys.argv[2], 'valid'), config.graph)[2]\n"
        "assert torch.equal(model.velocity_change(graph), torch.load(sys.argv[3])), 'predictions differ'\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    result = subprocess.run([sys.executable, "-c", script, str(tmp_path / "tiny"), str(folder), str(tmp_path / "here.pt")],
                            capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("override, message", [
    ({"model": {"name": "gcn"}}, "config key 'model.name' must be one of 'bsms_gnn', 'meshgraphnets', 'ms_gnn_grid', 'graph_unets', got 'gcn'"),
    ({"optim": {"lr": -1.0}}, "config key 'optim.lr' must be positive, got -1.0"),
    ({"train": {"batch_size": 0}}, "config key 'train.batch_size' must be >= 1, got 0"),
    ({"train": {"stpes": 10}}, "unknown config key 'train.stpes'"),
    ({"graph": {"levels": 0}}, "config key 'graph.levels' must be from 1 to 16"),
    ({"noise": {"gamma": 2.0}}, "config key 'noise.gamma' must lie in [0, 1], got 2.0"),
    ({"name": "a/b"}, "config key 'name' must be a run folder name"),
])
def test_config_errors_name_the_key(tiny_dataset, tmp_path, override, message):
    with pytest.raises(ConfigError) as info:
        load_config(config_dict(tiny_dataset, tmp_path, **override))
    assert message in str(info.value)


def test_run_folder_errors(tiny_dataset, folder, tmp_path):
    data = config_dict(tiny_dataset, tmp_path, train={"steps": 2})
    with pytest.raises(ConfigError, match="cannot resume: .*latest.pt does not exist"):
        Trainer(load_config(data), dataset_folder=folder, resume=True)
    Trainer(load_config(data), dataset_folder=folder).fit()
    with pytest.raises(ConfigError, match="already holds a checkpoint; pass --resume"):
        Trainer(load_config(data), dataset_folder=folder)
    with pytest.raises(ConfigError, match=r"config key 'optim.lr' was 0.001 and is now 0.002; resume with optim.lr=0.001 \(what the run"):
        Trainer(load_config(config_dict(tiny_dataset, tmp_path, optim={"lr": 2e-3}, train={"steps": 2})),
                dataset_folder=folder, resume=True)
    with pytest.raises(ConfigError, match=r"train.batch_size. \(1000\) exceeds the 12 training samples"):
        Trainer(load_config(config_dict(tiny_dataset, tmp_path, name="big", train={"batch_size": 1000})),
                dataset_folder=folder)
    with pytest.raises(ConfigError, match="dataset config nope.yaml does not exist"):
        prepare_dataset(load_config(config_dict(tiny_dataset, tmp_path, dataset={"config": "nope.yaml"})))
    with pytest.raises(ValueError, match="graph constant 'log_G'.*no numeric scene parameter 'G'"):
        FrameDataset(split_files(folder, "valid"), GraphOptions(constants=["log_G"]))


def test_checkpoint_errors(tmp_path):
    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'pwned'}",))

    torch.save({"format": 1, "evil": Payload()}, tmp_path / "evil.pt")
    with pytest.raises(CheckpointError, match="evil.pt is damaged or not a bsms checkpoint"):
        load_checkpoint(tmp_path / "evil.pt")
    assert not (tmp_path / "pwned").exists(), "loading a checkpoint must never run code"
    (tmp_path / "cut.pt").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(CheckpointError, match="cut.pt is damaged"):
        load_checkpoint(tmp_path / "cut.pt")
    (tmp_path / "run").mkdir()
    with pytest.raises(CheckpointError, match="has no usable checkpoint .*checkpoints/best.pt, checkpoints/latest.pt"):
        load_model(tmp_path / "run")
    with pytest.raises(CheckpointError, match="run folder .*nowhere does not exist"):
        load_model(tmp_path / "nowhere")


def test_train_py_reports_config_errors(tmp_path):
    config = tmp_path / "bad.yaml"
    config.write_text("name: x\nmodel: {name: gcn}\ndataset: {config: configs/datasets/glyphs_quick.yaml}\n")
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), str(config), "optim.lr=3e-4"],
                            capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip() == ("error: config key 'model.name' must be one of 'bsms_gnn', 'meshgraphnets', "
                                     "'ms_gnn_grid', 'graph_unets', got 'gcn'")


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_training_configs_are_valid(path):
    from datagen.dataset_config import load_dataset_config
    from datagen.families import get_family

    config = load_config(path)
    dataset = load_dataset_config(ROOT / config.dataset.config)
    ranges = {**get_family(dataset["family"]).RANGES, **dataset.get("ranges", {})}  # the family's defaults, overridden
    # contact edges wherever bodies can touch: not for the single clamped beam, not for Eulerian flow
    assert config.graph.contact == (dataset["family"] not in ("cantilever", "shock_channel"))
    for name in config.graph.constants:  # every constant is a scene parameter the family varies
        assert name.removeprefix("log_") in ranges or name.removeprefix("log_") in dataset["params"]


def test_train_trajectories_takes_the_first_n_and_names_the_shortfall(tiny_dataset, folder, tmp_path):
    """train.trajectories (learning curves) trains on the first N training files only."""
    files = split_files(folder, "train")
    trainer = Trainer(load_config(config_dict(tiny_dataset, tmp_path, train={"trajectories": 1})),
                      dataset_folder=folder)
    assert trainer.train_set.files == [str(files[0])]
    assert len(trainer.train_set) == len(trainer.train_set.positions[0]) - 1
    with pytest.raises(ConfigError, match=rf"'train.trajectories' asks for 99 training trajectories, but .* holds "
                                          rf"{len(files)}; ask for fewer"):
        Trainer(load_config(config_dict(tiny_dataset, tmp_path / "b", train={"trajectories": 99})),
                dataset_folder=folder)
    with pytest.raises(ConfigError, match=r"'train.trajectories' must be >= 1"):
        load_config(config_dict(tiny_dataset, tmp_path, train={"trajectories": 0}))
