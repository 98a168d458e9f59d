"""The flow family (issue 33): CSMPM's shock_channel scene as Eulerian data, the family that samples
it, and BSMS-GNN trained and evaluated on it against CSMPM re-runs and persistence."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import datagen
from bsms.fields import FieldSpec, infer_spec
from bsms.rollouts.rollout import eulerian_metrics
from datagen.config import ConfigError
from datagen.csmpm import flow
from datagen.csmpm.coupled_scenes import shock_state
from datagen.dataset import load
from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.trajectory import NodeType

ROOT = Path(__file__).resolve().parents[1]
SMALL = {"scene": "shock_channel", "params": {"cells": 16, "mach": 2.0},
         "output": {"frames": 3, "frame_interval": 0.02}}


def test_shock_channel_writes_eulerian_fields_the_learned_side_reads():
    t = datagen.simulate(SMALL)
    nx, ny = 32, 16
    n = t.mesh.n_nodes
    assert n < nx * ny and t.positions.shape == (4, n, 2) and np.all(t.positions == t.positions[0])
    assert t.fields["velocity"].shape == (4, n, 2) and t.fields["density"].shape == (4, n, 1)
    assert t.fields["pressure"].shape == (4, n, 1) and t.fields["node_type"].shape == (1, n, 1)
    assert t.config["field_spec"] == flow.FIELD_SPEC == infer_spec(t.fields, 2).to_dict()
    codes = t.fields["node_type"].ravel()
    x = t.mesh.nodes[:, 0]
    np.testing.assert_array_equal(codes[x < 1 / 16], 4)  # the inflow column
    np.testing.assert_array_equal(codes[x > 2 - 1 / 16], 5)  # the outflow column
    np.testing.assert_array_equal(t.node_type, np.where(codes == 4, NodeType.CLAMPED, NodeType.FREE))
    assert (codes == 6).sum() >= 2 * (nx - 2), "wall boundary: both channel walls and the obstacle's rim"
    # frame 0: the Rankine-Hugoniot state behind the shock (x < 0.1), still gas ahead of it
    rho2, u2, p2 = shock_state(2.0, 1.4, 1.0)
    behind = x < 0.1
    np.testing.assert_allclose(t.fields["density"][0, behind, 0], rho2, rtol=1e-15)
    np.testing.assert_allclose(t.fields["velocity"][0, behind, 0], u2, rtol=1e-14)
    np.testing.assert_allclose(t.fields["pressure"][0, ~behind, 0], 1.0, rtol=1e-14)
    assert np.all(t.fields["velocity"][0, ~behind] == 0.0)
    # the inflow column (prescribed from the data) stays near the inflow the inlet's ghost cells hold
    np.testing.assert_allclose(t.fields["density"][:, codes == 4, 0], rho2, rtol=1e-2)
    with pytest.raises(ConfigError, match="must lie inside the channel"):
        datagen.simulate({**SMALL, "params": {**SMALL["params"], "obstacle": [[0.05, 0.4], [0.3, 0.4], [0.2, 0.6]]}})
    with pytest.raises(ConfigError, match="must be > 1 \\(a shock\\)"):
        datagen.simulate({**SMALL, "params": {**SMALL["params"], "mach": 0.9}})
    with pytest.raises(ConfigError, match="'params.outlet' must be extrapolate or characteristic, got 'open'"):
        datagen.simulate({**SMALL, "params": {**SMALL["params"], "outlet": "open"}})


def test_the_family_draws_obstacles_and_shocks_reproducibly():
    config = load_dataset_config(ROOT / "configs/datasets/shock_channel.yaml")
    a, b = trajectory_config(config, "train", 3), trajectory_config(config, "train", 3)
    assert a == b and a != trajectory_config(config, "train", 4)
    machs, centres = [], []
    for index in range(40):
        p = trajectory_config(config, "train", index)["params"]
        machs.append(p["mach"])
        corners = np.asarray(p["obstacle"])
        centres.append(corners.mean(0))
        assert 4 <= len(corners) <= 8 and corners[:, 0].min() > 0.1 + 2 / 32
    assert 1.5 <= min(machs) and max(machs) <= 3.0 and np.ptp(machs) > 1.0
    assert np.ptp(np.asarray(centres)[:, 1]) > 0.15


def _persistence(velocity: np.ndarray, free: np.ndarray) -> float:
    """Closed form of persistence's relative velocity error: the RMS over steps 1..T and free
    nodes of |v_t - v_0|, over the RMS of |v_t| over frames 0..T."""
    v = velocity[:, free]
    return float(np.sqrt(np.mean(np.sum((v[1:] - v[:1]) ** 2, -1))) / np.sqrt(np.mean(np.sum(v ** 2, -1))))


def test_eulerian_metrics_put_a_rollout_beside_persistence():
    spec = FieldSpec.from_dict(flow.FIELD_SPEC)
    rng = np.random.default_rng(0)
    # velocity t * a per node (density, pressure anything): persistence errs |t a| at step t, so its
    # error over the field's RMS is sqrt(mean_{1..5} t^2 / mean_{0..5} t^2) = sqrt(6 / 5)
    t = np.arange(6.0)[:, None, None]
    truth = np.concatenate([t * rng.normal(size=(1, 50, 2)), rng.normal(size=(6, 50, 2))], axis=-1)
    free = np.ones(50, bool)
    exact = eulerian_metrics(spec, truth, truth, free)
    assert exact["rel_all"] == 0.0 and exact["vs_rest"] == 0.0 and exact["field"] == "velocity"
    assert exact["rest_rel_all"] == pytest.approx(np.sqrt(1.2), rel=1e-12)
    persisting = eulerian_metrics(spec, np.repeat(truth[:1], 6, axis=0), truth, free)
    assert persisting["rel_all"] == pytest.approx(np.sqrt(1.2), rel=1e-12)
    half = eulerian_metrics(spec, 0.5 * (truth + truth[:1]), truth, free)
    assert half["vs_rest"] == pytest.approx(0.5, rel=1e-12)


def test_bsms_gnn_trains_on_the_flow_family_and_is_charted_against_csmpm(tmp_path):
    dataset = tmp_path / "flow.yaml"
    dataset.write_text(yaml.safe_dump({"extends": str(ROOT / "configs/datasets/shock_channel.yaml"),
                                       "dataset": "flow_tiny", "splits": {"train": 2, "valid": 1, "test": 1},
                                       "params": {"cells": 16}, "output": {"frames": 4, "frame_interval": 0.02}}))
    run = subprocess.run([sys.executable, str(ROOT / "train.py"), str(ROOT / "configs/shock_channel.yaml"),
                          f"dataset.config={dataset}", f"dataset.root={tmp_path / 'data'}", "name=flow_tiny",
                          "dataset.workers=1", "train.steps=6", "train.valid_every=3", "train.checkpoint_every=3",
                          "train.normalizer_steps=3", "optim.warmup=2", "train.log_every=3", "model.latent=16",
                          "graph.levels=3", "evaluate.gifs=0", "evaluate.threads=1", "--quiet"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    metrics = json.loads((tmp_path / "runs/flow_tiny/evaluation/metrics.json").read_text())
    (truth,) = metrics["solver"]["solver, data settings (ground truth)"]
    assert truth["max_difference_from_stored"] == 0.0 and truth["rel_all"] == 0.0
    (doubled,) = metrics["solver"]["solver, time step 2x larger"]
    assert 1.5 < doubled["dt_factor"] <= 2.0 and 0 < doubled["rel_all"] < 0.1
    stored = load(tmp_path / "data/flow_tiny/test/00000.h5")
    persistence = _persistence(stored.fields["velocity"], stored.node_type == NodeType.FREE)
    assert persistence > 0.5, "a shock sweeping the channel: holding the first frame is far off"
    for run_metrics in (truth, doubled):
        assert run_metrics["rest_rel_all"] == pytest.approx(persistence, rel=1e-12)
    assert doubled["vs_rest"] == pytest.approx(doubled["rel_all"] / persistence, rel=1e-12)
    (learned,) = metrics["learned"]["flow_tiny"]
    assert learned["field"] == "velocity" and set(learned["fields"]) == {"velocity", "density", "pressure"}
    assert learned["vs_rest"] == pytest.approx(learned["rel_all"] / persistence, rel=1e-12)
    report = (tmp_path / "runs/flow_tiny/report.md").read_text()
    assert "Persistence (the first frame's fields held for ever)" in report
