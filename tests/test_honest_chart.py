"""The honest chart: every speed-up end to end, the solver as a practitioner runs a quasi-static load
(mass scaling), the physics-only input as a method of its own, and a held-out ``final`` split."""

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from bsms.data import GraphOptions, Scenario
from bsms.evaluate import MASS_SCALING_LIMIT, _more_mass_scaling, _Results
from bsms.rollouts.learned_rollouts import end_to_end, physics_rollouts
from bsms.rollouts.rollout import body_size, rollout_metrics
from bsms.rollouts.solver_runs import (
    SOLVER_SETTINGS,
    is_setting,
    mass_scaling_factor,
    next_mass_scaling,
    run_solver,
    setting_config,
    setting_label,
)
from bsms.run import load_model, split_files
from datagen.config import ConfigError
from datagen.dataset import load
from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.families import get_family
from datagen.generate import main as datagen_main

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs" / "datasets"


@pytest.fixture(scope="module")
def pressed(tmp_path_factory):
    """Two test trajectories of the quickstart's press family (about a second of solver time each)."""
    root = tmp_path_factory.mktemp("pressed")
    assert datagen_main(["configs/datasets/press_quickstart.yaml", "--split", "test", "--out", str(root),
                         "--shard", "0/4", "--quiet"]) == 0
    return [load(path) for path in split_files(root / "press_quickstart", "test")]


# ----------------------------------------------------------------------------- mass scaling
def test_mass_scaling_settings_are_named_and_climb_the_1_3_10_ladder():
    assert [s for s in SOLVER_SETTINGS if mass_scaling_factor(s)] == [
        "mass_scaling_10", "mass_scaling_100", "mass_scaling_1000", "mass_scaling_3000"]
    assert [mass_scaling_factor(s) for s in ("mass_scaling_2", "mass_scaling_30000", "mass_scaling_1",
                                             "mass_scaling_010", "mass_scaling_x", "large_step")] == \
        [2, 30000, None, None, None, None]
    ladder = ["mass_scaling_3000"]
    while len(ladder) < 5:
        ladder.append(next_mass_scaling(ladder[-1]))
    assert ladder == ["mass_scaling_3000", "mass_scaling_10000", "mass_scaling_30000", "mass_scaling_100000",
                      "mass_scaling_300000"]
    assert next_mass_scaling("mass_scaling_10") == "mass_scaling_30"
    assert next_mass_scaling("mass_scaling_5") == "mass_scaling_10"
    assert is_setting("mass_scaling_70000") and not is_setting("mass_scaling_0")
    assert setting_label("mass_scaling_30000", []) == "solver, mass scaling x30000"
    assert setting_label("mass_scaling_100", []) == SOLVER_SETTINGS["mass_scaling_100"]
    with pytest.raises(ValueError, match="'large_step' is no mass_scaling_S setting"):
        next_mass_scaling("large_step")
    with pytest.raises(ValueError, match="unknown solver setting 'mass_scaling_1'; choose from ground_truth, "):
        setting_config({"scene": "press", "params": {}}, "mass_scaling_1", 4)


def test_mass_scaling_multiplies_inertia_and_keeps_the_weight(pressed):
    base = pressed[0].config
    scaled = setting_config(base, "mass_scaling_1000", 7)
    params, original = scaled["params"], base["params"]
    assert params["density"] == pytest.approx(1000 * original["density"], rel=1e-15)
    assert params["gravity"] == pytest.approx(original["gravity"] / 1000, rel=1e-15)
    assert params["density"] * params["gravity"] == pytest.approx(original["density"] * original["gravity"],
                                                                  rel=1e-15)
    # the damping ratio c / (2 omega) kept: omega goes as 1 / sqrt(density)
    for key in ("damping", "settle_damping"):
        assert original[key] > 0 and params[key] == pytest.approx(original[key] / 1000**0.5, rel=1e-15)
    changed = {k for k in params if params[k] != original[k]}
    assert changed == {"density", "gravity", "damping", "settle_damping"}, "nothing else changes (the drive)"
    assert scaled["solver"] == base["solver"] and scaled["output"]["frames"] == 7


def test_a_scene_that_is_not_quasi_static_gets_no_mass_scaling(tiny_dataset):
    _, root = tiny_dataset
    trajectory = load(split_files(Path(root) / "tiny_glyphs", "test")[0])
    assert setting_config(trajectory.config, "mass_scaling_100", 2) is None
    result = run_solver(trajectory, "mass_scaling_100", 2, 0.5)
    assert result == {"skipped": "the scene's drive is not quasi-static: mass scaling would change its physics",
                      "setting": "mass_scaling_100"}


def test_mass_scaling_steps_sqrt_s_times_longer_and_is_timed_end_to_end(pressed):
    """dt from the CFL condition goes as sqrt(density) (wave speed sqrt(E / density), the body at
    rest at frame 0): x100 takes a tenth of the substeps; its time is its setup and its frames."""
    trajectory = pressed[0]
    frames = 4
    truth = run_solver(trajectory, "ground_truth", frames, 0.5)
    scaled = run_solver(trajectory, "mass_scaling_100", frames, 0.5)
    assert truth["substeps"] == trajectory.substeps and truth["max_difference_from_stored"] == 0.0
    assert math.ceil((truth["substeps"] - 1) / 10) <= scaled["substeps"] <= math.ceil(truth["substeps"] / 10)
    assert scaled["dt_factor"] == pytest.approx(truth["substeps"] / scaled["substeps"], rel=1e-12)
    for run in (truth, scaled):
        assert run["seconds"] == run["solver_s"] > run["setup_s"] > 0 and run["preroll_s"] > 0
        assert run["seconds_per_sim_second"] == pytest.approx(run["solver_s"] / (frames * 0.02), rel=1e-12)
    assert truth["rmse_all"] == 0.0 and 0 < scaled["rel_all"] < 0.5 and scaled["unstable_step"] is None


def _results(model_errors, scaled: dict) -> _Results:
    learned = {"model": [{"rel_all": e} for e in model_errors]}
    solver = {setting_label(name, []): [{"setting": name, **run} for run in runs] for name, runs in scaled.items()}
    return _Results(learned, solver)


def test_mass_scaling_goes_on_while_the_solver_is_more_accurate_than_the_model():
    good, bad = {"rel_all": 0.001, "unstable_step": None}, {"rel_all": 0.02, "unstable_step": None}
    assert _more_mass_scaling(_results([0.01, 0.01], {"mass_scaling_1000": [good, good],
                                                      "mass_scaling_3000": [good, good]})) == "mass_scaling_10000"
    assert _more_mass_scaling(_results([0.01], {"mass_scaling_3000": [good], "mass_scaling_10000": [bad]})) is None
    assert _more_mass_scaling(_results([0.01, 0.01], {"mass_scaling_30000": [good, bad]})) is None, \
        "the mean error over the trajectories decides (0.0105 against 0.01)"
    assert _more_mass_scaling(_results([0.011, 0.011], {"mass_scaling_30000": [good, bad]})) == "mass_scaling_100000"
    unstable = {"rel_all": 0.001, "unstable_step": 3}
    assert _more_mass_scaling(_results([0.01], {"mass_scaling_3000": [unstable]})) is None
    assert _more_mass_scaling(_results([0.01], {"mass_scaling_3000": [{"skipped": "not quasi-static"}]})) is None
    assert _more_mass_scaling(_results([0.01], {"large_step": [good]})) is None
    top = f"mass_scaling_{MASS_SCALING_LIMIT}"
    assert _more_mass_scaling(_results([0.01], {top: [good]})) is None, "no further than the limit"


# ----------------------------------------------------------------------------- the physics-only row
def _answers_as_a_model_sees_them(trajectory, options: GraphOptions, frames: int) -> np.ndarray:
    """Frames 1..frames as the rest shape plus the elastic input of the graphs a from-rest model's
    rollout builds (bsms.rollouts.rollout: the body at rest, kinematic nodes with their coming step)."""
    scenario = Scenario.from_trajectory(trajectory, options)
    n = scenario.n_body
    known = scenario.positions(np.where(scenario.kinematic[:n, None], trajectory.positions, scenario.rest_pos[:n]),
                               trajectory.obstacle_positions)
    out = []
    for t in range(frames):
        velocity = np.where(scenario.kinematic[:, None], (known[t + 1] - known[t]) / scenario.frame_dt, 0.0)
        frame = scenario.frame(known[t], velocity)
        predicted = known[t + 1][:n].copy()
        nodes = frame.nodes["scenario_nodes"]
        body = (nodes < n) & ~scenario.kinematic[nodes]
        predicted[nodes[body]] = scenario.rest_pos[nodes[body]] + frame.nodes["elastic"][body]
        out.append(predicted)
    return np.concatenate([trajectory.positions[:1], np.stack(out)])


def test_the_physics_row_is_the_elastic_input_alone_timed_end_to_end(pressed):
    options = GraphOptions(levels=3, from_rest=True, penetration=True, elastic=True)
    frames = [len(t.times) - 1 for t in pressed]
    rows = physics_rollouts(options, pressed, frames)
    assert len(rows) == 2
    for trajectory, n, metrics in zip(pressed, frames, rows, strict=True):
        expected = _answers_as_a_model_sees_them(trajectory, options, n)
        free = trajectory.node_type == 0
        truth = rollout_metrics(expected, trajectory.positions, free, body_size(trajectory.mesh.nodes))
        assert metrics["rmse_all"] == pytest.approx(truth["rmse_all"], rel=1e-10)
        assert 0.05 < metrics["vs_rest"] < 1.0, "it knows some of the motion, not all of it"
        assert metrics["seconds"] == pytest.approx(metrics["setup_s"] + metrics["learned_s"], rel=1e-15)
        assert metrics["setup_s"] > 0 and metrics["latency_ms"] > 0
        assert metrics["seconds_per_sim_second"] == pytest.approx(metrics["seconds"] / (n * 0.02), rel=1e-12)
    assert physics_rollouts(GraphOptions(levels=3, from_rest=True, penetration=True), pressed, frames) == []


def test_end_to_end_counts_the_setup_and_every_call(pressed):
    """pretrained/press2d on a new mesh: the scenario built with no cache, then the mesh alone;
    one frame per call is slower than the frames batched."""
    model, config, _ = load_model(ROOT / "pretrained" / "press2d")
    trajectory = pressed[1]
    timed = end_to_end(model, config.graph, trajectory, 8)
    assert set(timed) == {"setup_s", "learned_s", "seconds", "latency_ms"}
    assert timed["seconds"] == timed["setup_s"] + timed["learned_s"] and timed["setup_s"] > 0
    assert timed["latency_ms"] > 0 and timed["learned_s"] > 0


# ----------------------------------------------------------------------------- the final split
@pytest.mark.parametrize("name, digest", [("press_stiff_960", "3992c2b0fef93ca3"), ("bracket_fine", "de1855fc9684657e")])
def test_the_final_split_leaves_every_other_split_as_it_was(name, digest):
    """The published models' train, valid and test draws (digests of their first six each, taken
    before the final split existed) are unchanged."""
    d = load_dataset_config(CONFIGS / f"{name}.yaml")
    assert d["splits"]["final"] == 32
    drawn = [trajectory_config(d, split, k) for split in ("train", "valid", "test") for k in range(6)]
    assert hashlib.sha256(json.dumps(drawn, sort_keys=True).encode()).hexdigest()[:16] == digest


def test_the_press_final_split_holds_new_test_draws_and_characters_of_no_other_split():
    d = load_dataset_config(CONFIGS / "press_stiff_960.yaml")
    bodies = [trajectory_config(d, "final", k)["params"] for k in range(32)]
    test = [trajectory_config(d, "test", k)["params"] for k in range(8)]
    digits = [p["char"] for p in bodies if p.get("polygon") is None and p["char"] in "0123456789"]
    letters = [p["char"] for p in bodies if p.get("polygon") is None and p["char"] not in "0123456789"]
    polygons = [p["polygon"] for p in bodies if p.get("polygon") is not None]
    assert 10 <= len(digits) <= 22 and len(digits) + len(letters) + len(polygons) == 32
    assert set(letters) <= set("GJQSU") and polygons, "the rest are drawn as the test split's kinds"
    assert not any(p in [q.get("polygon") for q in test] for p in polygons), "new draws"
    with pytest.raises(ConfigError, match=r"ranges.final_chars shares 'A' with ranges.train_chars or "
                                          r"ranges.test_chars; the final split's novel characters must be of no "
                                          r"other split"):
        get_family("press").sample({**d["ranges"], "final_chars": "0A"}, np.random.default_rng(0), "final")
    all_novel = get_family("press").sample({**d["ranges"], "final_novel": 1.0}, np.random.default_rng(3), "final")
    assert all_novel["char"] in "0123456789" and all_novel.get("polygon") is None


def test_the_bracket_final_split_holds_brackets_of_a_kind_no_other_split_has(monkeypatch):
    from datagen.families import bracket

    drawn = []
    real = bracket.random_bracket

    def recording(rng, segments, width, turn=90.0):
        drawn.append((segments, width, turn))
        return real(rng, segments, width, turn)

    monkeypatch.setattr(bracket, "random_bracket", recording)
    d = load_dataset_config(CONFIGS / "bracket_fine.yaml")
    for k in range(32):
        trajectory_config(d, "final", k)
    novel = [b for b in drawn if b[0] == 4]
    assert 10 <= len(novel) <= 22
    assert all(0.12 <= w <= 0.18 and t == 120.0 for _, w, t in novel)
    assert all(1 <= s <= 3 and 0.18 <= w <= 0.3 and t == 90.0 for s, w, t in drawn if s != 4)


def test_a_family_without_its_own_final_split_draws_it_as_its_test_split():
    d = load_dataset_config(CONFIGS / "glyphs.yaml")
    d = {**d, "splits": {**d["splits"], "final": 4}}
    family = get_family("glyphs")
    assert not getattr(family, "FINAL", False)
    for k in range(4):
        config = trajectory_config(d, "final", k)
        rng = np.random.default_rng([d["seed"], 3, k])
        assert config["params"] == {**d["params"], **family.sample(d["ranges"], rng, "test")}
        assert config != trajectory_config(d, "test", k), "new draws, not the test split's"
