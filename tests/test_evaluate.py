"""A reduced quickstart end to end (train.py -> evaluate -> report), and bsms.evaluate's outputs."""

import csv
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest
import yaml
from PIL import Image

from bsms.config import ConfigError
from bsms.data import NodeType, Scenario
from bsms.evaluate import evaluate
from bsms.evaluate import main as evaluate_main
from bsms.evaluate.pareto import dominates, row_point
from bsms.rollouts.rollout import rollout
from bsms.rollouts.solver_runs import SOLVER_SETTINGS, STABILITY_FACTORS, interpolate_to, mass_scaling_factor
from bsms.run import load_config, load_model
from datagen.dataset import load

ROOT = Path(__file__).resolve().parents[1]
PNG, GIF = b"\x89PNG\r\n\x1a\n", b"GIF8"
GROUND_TRUTH = SOLVER_SETTINGS["ground_truth"]


@pytest.fixture(scope="module")
def quickstart_run(tiny_dataset, tmp_path_factory):
    """python train.py configs/quickstart.yaml, reduced to a few steps on the tiny dataset."""
    runs = tmp_path_factory.mktemp("runs")
    dataset_config, data_root = tiny_dataset
    overrides = [
        f"runs={runs}", f"dataset.config={dataset_config}", f"dataset.root={data_root}", "train.steps=8",
        "train.log_every=4", "train.valid_every=4", "train.checkpoint_every=4", "train.valid_samples=4",
        "graph.levels=3", "model.latent=32", "evaluate.gifs=1", "train.normalizer_steps=4",
    ]
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), "configs/quickstart.yaml", *overrides,
                             "--quiet"], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert result.returncode == 0, result.stderr[-4000:]
    details = json.loads((runs / "quickstart" / "evaluation" / "metrics.json").read_text())
    return runs / "quickstart", result.stdout, details


def independent_rollout(run: Path, trajectory_file: str, steps: int):
    """(predicted body positions (T, N, d), per-step RMSE over the free body nodes) of the run's best model."""
    model, config, _ = load_model(run)
    trajectory = load(trajectory_file)
    scenario = Scenario.from_trajectory(trajectory, config.graph)
    known = scenario.full(trajectory.positions[: steps + 1])
    result = rollout(model, scenario, known[0], scenario.full(trajectory.velocities[:1], 0.0)[0], steps, known)
    predicted = result.positions[:, : scenario.n_body]
    free = trajectory.node_type == NodeType.FREE
    error = (predicted - trajectory.positions[: steps + 1])[:, free]
    return predicted, np.sqrt(np.mean(np.sum(error**2, axis=-1), axis=-1))[1:]


# the metric each column of the report's table must show (metrics.json row keys)
TABLE = {
    "method": "label", "kind": "kind", "RMSE@1 (m)": "rmse_1", "RMSE@50 (m)": "rmse_50", "RMSE all (m)": "rmse_all",
    "± std": "rmse_all_std", "RMSE all / body size": "rel_all", "vs at rest": "vs_rest",
    "rigid part / body size": "rigid_rel_all", "deformation part / body size": "deform_rel_all", "unstable rollouts": "unstable",
    "first unstable step": "first_unstable_step", "setup per mesh (s)": "setup_s", "s end to end": "seconds",
    "s per simulated s (end to end)": "seconds_per_sim_second", "speed-up end to end": "speedup",
    "speed-up, throughput": "speedup_throughput", "latency (ms per frame)": "latency_ms",
    "peak memory (MB)": "peak_memory_mb", "dominated by": "dominated_by",
}


def table(report: str) -> tuple[list[str], list[list[str]]]:
    """(titles, cells of each row) of the table under '## Metrics'."""
    lines = [line for line in report.split("## Metrics")[1].split("##")[0].splitlines() if line.startswith("|")]
    titles, *rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]
    return titles, rows[1:]  # without the separator


def test_report_table_is_metrics_json(quickstart_run):
    run, _, details = quickstart_run
    titles, cells = table((run / "report.md").read_text())
    assert titles == list(TABLE)
    assert [row[0] for row in cells] == [row["label"] for row in details["rows"]]
    for row_cells, row in zip(cells, details["rows"], strict=True):
        for cell, title in zip(row_cells, titles, strict=True):
            value = row.get(TABLE[title])
            if value is None or (isinstance(value, float) and math.isnan(value)):
                assert cell == "-", (row["label"], title)
            elif isinstance(value, str):
                assert cell == value
            elif isinstance(value, list):  # labels of the rows that dominate this one
                assert cell == ("; ".join(value) or "none"), (row["label"], title)
            else:  # three significant digits
                assert float(cell) == pytest.approx(value, rel=5e-3, abs=0), (row["label"], title)
    with open(run / "evaluation" / "speed_accuracy.csv", newline="") as fh:
        csv_rows = list(csv.DictReader(fh))
    assert list(csv_rows[0]) == list(TABLE.values())
    for csv_row, row in zip(csv_rows, details["rows"], strict=True):
        assert float(csv_row["rmse_all"]) == row["rmse_all"] and csv_row["label"] == row["label"]
        assert csv_row["dominated_by"] == ("; ".join(row["dominated_by"]) or "none")


def test_metrics_are_what_they_claim(quickstart_run):
    run, stdout, details = quickstart_run
    rows = {row["label"]: row for row in details["rows"]}
    settings = {row["setting"]: row for row in details["rows"] if row["kind"] == "solver"}
    # the glyphs fall freely: no quasi-static drive, so no mass scaling (skipped: no row)
    assert set(settings) == {s for s in SOLVER_SETTINGS if mass_scaling_factor(s) is None}
    assert set(rows) == {"quickstart", *(r["label"] for r in settings.values())}, "no physics row: no elastic input"
    assert details["threads"] == 1 and details["data_solver_threads"] == [1], "every point timed on one thread"
    truth = rows[GROUND_TRUTH]
    assert truth["rmse_all"] == 0.0 and truth["max_difference_from_stored"] == 0.0, \
        "the solver re-run at the data's settings must reproduce the stored trajectory bit for bit"
    for label, row in rows.items():
        assert row["speedup"] == pytest.approx(truth["seconds_per_sim_second"] / row["seconds_per_sim_second"],
                                               rel=1e-15), label
        if label not in ("quickstart", GROUND_TRUTH, settings["adaptive"]["label"]):  # cheaper settings change it
            assert 0 < row["rmse_all"] < math.inf, label
    assert 0 <= settings["adaptive"]["rmse_all"] < 1e-6, "the adaptive reference configuration changes little here"
    (learned,) = details["learned"]["quickstart"]
    curve = np.array(learned["error_curve"])
    assert len(curve) == 6 and learned["steps"] == 6
    assert learned["rmse_all"] == pytest.approx(np.sqrt(np.mean(curve**2)), rel=1e-15)
    assert learned["rmse_1"] == curve[0] and learned["rel_all"] == pytest.approx(
        learned["rmse_all"] / learned["body_size"], rel=1e-15)
    # end to end: the per-mesh setup and the mesh's rollout alone; throughput: the batched step
    assert learned["seconds"] == pytest.approx(learned["setup_s"] + learned["learned_s"], rel=1e-15)
    assert learned["setup_s"] > 0 and learned["latency_ms"] > 0
    assert learned["seconds_per_sim_second"] == pytest.approx(learned["seconds"] / (6 * 0.05), rel=1e-12)
    assert learned["throughput_seconds_per_sim_second"] == pytest.approx(learned["seconds_per_step"] / 0.05, rel=1e-15)
    model = rows["quickstart"]
    assert model["speedup_throughput"] == pytest.approx(
        truth["seconds_per_sim_second"] / model["throughput_seconds_per_sim_second"], rel=1e-15)
    assert truth["seconds"] == pytest.approx(truth["solver_s"], rel=1e-15) and truth["setup_s"] > 0
    assert truth["seconds_per_sim_second"] == pytest.approx(truth["solver_s"] / (6 * 0.05), rel=1e-12)
    predicted, expected = independent_rollout(run, details["trajectories"][0], 6)
    np.testing.assert_allclose(curve, expected, rtol=1e-6, atol=0)  # float32 network (measured: equal)
    assert re.search(rf"rollout RMSE {rows['quickstart']['rmse_all']:.4g} m", stdout)
    with meshio.xdmf.TimeSeriesReader(str(run / "evaluation" / "rollout_0.xdmf")) as reader:
        reader.read_points_cells()
        assert reader.num_steps == 7  # frame 0 and 6 predicted frames
        _, point_data, _ = reader.read_data(6)
    assert set(point_data) == {"position", "displacement", "error"}
    truth_positions = load(details["trajectories"][0]).positions
    np.testing.assert_allclose(point_data["error"], np.linalg.norm(predicted[6] - truth_positions[6], axis=-1),
                               rtol=1e-6, atol=0)


def test_stability_limit_and_pareto_front_of_a_real_evaluation(quickstart_run):
    run, _, details = quickstart_run
    rows = details["rows"]
    limit = next(row for row in rows if row.get("setting") == "stability_limit")
    (run_metrics,) = details["solver"][limit["label"]]
    tries = run_metrics["search"]
    assert 1 <= len(tries) <= len(STABILITY_FACTORS) and all(t["stable"] for t in tries[:-1])
    stable = [t for t in tries if t["stable"]]
    assert run_metrics["dt_factor"] == (stable[-1]["dt_factor"] if stable else 1.0) == limit["dt_factor"]
    assert limit["label"] == f"{SOLVER_SETTINGS['stability_limit']} ({limit['dt_factor']:.3g}x)"
    assert limit["unstable"] == 0 and run_metrics["unstable_step"] is None, "the point is the last stable run"
    large = next(row for row in rows if row.get("setting") == "large_step")
    assert large["dt_factor"] == 2.0 and tries[0]["dt_factor"] == 2.0
    truth = next(row for row in rows if row["label"] == GROUND_TRUTH)
    points = {row["label"]: row_point(row, GROUND_TRUTH) for row in rows}
    for row in rows:  # the rule, pair by pair, on the numbers metrics.json holds
        assert row["dominated_by"] == [other["label"] for other in rows if other is not row
                                       and dominates(points[other["label"]], points[row["label"]])], row["label"]
        assert row["pareto_front"] == (not row["dominated_by"] and math.isfinite(points[row["label"]][1]))
    assert truth["pareto_front"] and truth["dominated_by"] == []
    report = (run / "report.md").read_text()
    front = [row["label"] for row in sorted(rows, key=lambda r: points[r["label"]]) if row["pareto_front"]]
    assert f"fastest first: {'; '.join(front)}." in report
    assert "- quickstart: " in report.split("## Error against time")[0]
    assert "on 1 CPU thread(s), learned models and solver alike" in report


def test_report_links_every_picture(quickstart_run):
    run, _, _ = quickstart_run
    report = (run / "report.md").read_text()
    for picture in ("speed_accuracy.png", "error_vs_step.png", "training_curve.png", "rollout_0.gif"):
        assert f"(evaluation/{picture})" in report
        data = (run / "evaluation" / picture).read_bytes()
        assert data.startswith(GIF if picture.endswith(".gif") else PNG), picture
    with Image.open(run / "evaluation" / "rollout_0.gif") as gif:
        assert gif.n_frames == 7 and gif.size[0] > 1.8 * gif.size[1], "solver and learned panels, every frame"
    assert "reproduces the stored trajectories to 0 m" in report


def test_evaluate_learned_only_with_fewer_steps(quickstart_run):
    run, _, details = quickstart_run
    six_steps = details["learned"]["quickstart"][0]["error_curve"]
    config = load_config(run / "config.yaml")
    options = config.evaluate
    options.solver, options.steps, options.gifs = [], 3, 0
    result = evaluate(run, options=options, progress=False)
    (row,) = result["rows"]
    assert row["label"] == "quickstart" and row["trajectories"] == 1
    three_steps = json.loads((run / "evaluation" / "metrics.json").read_text())["learned"]["quickstart"][0]
    assert three_steps["error_curve"] == six_steps[:3], "a shorter rollout is the start of the longer one"


def test_evaluate_the_latest_checkpoint_never_reads_best(quickstart_run, tmp_path):
    """evaluate.checkpoint: latest rolls out latest.pt (the fixed budget) and never opens best.pt:
    with best.pt garbled, the default fails on it and ``latest`` gives the errors of latest.pt."""
    import shutil

    from bsms.checkpoint import CheckpointError

    run, _, _ = quickstart_run
    copies = {}
    for name, best in (("garbled", None), ("best_is_latest", run / "checkpoints" / "latest.pt")):
        copies[name] = tmp_path / name
        shutil.copytree(run / "checkpoints", copies[name] / "checkpoints")
        shutil.copy(run / "config.yaml", copies[name] / "config.yaml")
        target = copies[name] / "checkpoints" / "best.pt"
        target.write_bytes(b"not a checkpoint" if best is None else best.read_bytes())
    options = load_config(run / "config.yaml").evaluate
    options.solver, options.steps, options.gifs, options.checkpoint = [], 3, 0, "latest"
    (latest,) = evaluate(copies["garbled"], options=options, progress=False)["rows"]
    options.checkpoint = "best"
    (same,) = evaluate(copies["best_is_latest"], options=options, progress=False)["rows"]
    for key in ("rmse_1", "rmse_all", "rel_all"):
        assert latest[key] == same[key] and latest[key] > 0, key
    with pytest.raises(CheckpointError):
        evaluate(copies["garbled"], options=options, progress=False)
    saved = yaml.safe_load((copies["garbled"] / "config.yaml").read_text())  # the run's own evaluate.checkpoint
    saved["evaluate"]["checkpoint"] = "latest"
    (copies["garbled"] / "config.yaml").write_text(yaml.safe_dump(saved))
    assert evaluate_main([str(copies["garbled"]), "--no-solver", "--steps", "3", "--quiet"]) == 0
    with pytest.raises(ConfigError, match=r"^config key 'evaluate.checkpoint' must be one of 'best', 'latest', got 'last'$"):
        load_config({"name": "x", "dataset": {"config": "d.yaml"}, "evaluate": {"checkpoint": "last"}})


def test_a_worker_pool_measures_the_same_errors(quickstart_run):
    """evaluate.workers: 2 runs the learned rollouts and each trajectory's solver runs as jobs of a
    pool; every error is the one-process evaluation's (the fixture's), bit for bit; only timings differ."""
    run, _, alone_details = quickstart_run
    alone = {row["label"]: row for row in alone_details["rows"]}
    config = load_config(run / "config.yaml")
    options = config.evaluate
    options.solver, options.gifs, options.workers = ["ground_truth", "large_step"], 0, 2
    pooled = {row["label"]: row for row in evaluate(run, options=options, progress=False)["rows"]}
    details = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert set(pooled) == {"quickstart", GROUND_TRUTH, SOLVER_SETTINGS["large_step"]}
    for label, row in pooled.items():
        for key in ("rmse_1", "rmse_all", "rel_all", "unstable"):
            assert row[key] == alone[label][key], (label, key)
        assert row["seconds_per_sim_second"] > 0 and row["speedup"] > 0
    for a, b in zip(details["learned"]["quickstart"], alone_details["learned"]["quickstart"], strict=True):
        assert a["error_curve"] == b["error_curve"]
    assert pooled[GROUND_TRUTH]["max_difference_from_stored"] == 0.0


def test_evaluate_cli_errors(tmp_path):
    result = subprocess.run([sys.executable, "-m", "bsms.evaluate", str(tmp_path / "missing")],
                            capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip() == (f"error: run folder {tmp_path / 'missing'} does not exist; train one with "
                                     "python train.py CONFIG")


def test_unknown_solver_setting_names_the_key():
    from bsms.config import ConfigError

    with pytest.raises(ConfigError) as info:
        load_config({"name": "x", "dataset": {"config": "d.yaml"}, "evaluate": {"solver": ["coarse", "large_step"]}})
    assert str(info.value) == ("unknown config key 'evaluate.solver.coarse'; 'evaluate.solver' accepts: "
                               "adaptive, adaptive_coarse_mesh, coarse_mesh, coarse_mesh_1.5, fewer_particles, "
                               "ground_truth, large_step, mass_scaling_10, mass_scaling_100, mass_scaling_1000, "
                               "mass_scaling_3000, stability_limit, total, or mass_scaling_S for a whole S >= 2")
    with pytest.raises(ConfigError, match="unknown config key 'evaluate.solver.mass_scaling_1'; "):
        load_config({"name": "x", "dataset": {"config": "d.yaml"}, "evaluate": {"solver": ["mass_scaling_1"]}})
    scaled = load_config({"name": "x", "dataset": {"config": "d.yaml"}, "evaluate": {"solver": ["mass_scaling_30000"]}})
    assert scaled.evaluate.solver == ["mass_scaling_30000"]
    old = load_config({"name": "x", "dataset": {"config": "d.yaml"},
                       "evaluate": {"solver": ["coarse_mesh", "fewer_particles", "large_step"]}})
    assert old.evaluate.solver == ["coarse_mesh", "fewer_particles", "large_step"], "old configs keep working"
    former = load_config({"name": "x", "dataset": {"config": "d.yaml"}, "evaluate": {"solver": ["reference"]}})
    assert former.evaluate.solver == ["ground_truth"], "runs saved before the rename still load"


def test_coarser_body_is_compared_at_the_ground_truth_nodes():
    """A displacement field that is linear per body is carried over exactly between meshes."""
    from datagen import shapes

    fine, coarse = shapes.disk(0.5, 0.08), shapes.disk(0.5, 0.2)
    matrix = np.array([[0.1, 0.02], [-0.03, 0.05]])

    def moved(nodes, t):
        return nodes + t * (nodes @ matrix.T + np.array([0.2, -0.1]))

    times = np.linspace(0, 1, 4)[:, None, None]
    other = np.stack([moved(coarse.nodes, t) for t in times[:, 0, 0]])
    out = interpolate_to(fine.nodes, np.zeros(fine.n_nodes, int), coarse.nodes, np.zeros(coarse.n_nodes, int),
                         other)
    inside = np.linalg.norm(fine.nodes, axis=1) < 0.45  # the coarse polygon covers these
    expected = np.stack([moved(fine.nodes, t) for t in times[:, 0, 0]])
    np.testing.assert_allclose(out[:, inside], expected[:, inside], rtol=0, atol=1e-15)


def test_the_body_at_rest_baseline_is_the_error_of_predicting_no_motion(quickstart_run):
    from bsms.rollouts.rollout import body_size

    run = quickstart_run[0]  # the run's latest evaluation (other tests evaluate it again with other options)
    details = json.loads((run / "evaluation" / "metrics.json").read_text())
    expected = []
    for name in details["trajectories"]:
        trajectory = load(name)
        x = trajectory.positions[: details["learned"]["quickstart"][0]["steps"] + 1]
        free = trajectory.node_type == NodeType.FREE
        curve = np.sqrt(np.mean(np.sum((x[1:, free] - x[0, free]) ** 2, axis=-1), axis=-1))
        expected.append(np.sqrt(np.mean(curve**2)) / body_size(trajectory.mesh.nodes))
    row = details["rows"][0]
    assert row["rest_rel_all"] == pytest.approx(np.mean(expected), rel=1e-12)
    assert row["rest_rel_all"] > 0.01, "the tiny letters fall: no motion is far off"
    report = (run / "report.md").read_text()
    assert f"RMSE all / body size {row['rest_rel_all']:.3g} on these trajectories" in report
    learned = details["learned"]["quickstart"]
    for metrics, rest in zip(learned, expected, strict=True):  # the skill: error / at-rest error, per trajectory
        assert metrics["rest_rel_all"] == pytest.approx(rest, rel=1e-12)
        assert metrics["vs_rest"] == pytest.approx(metrics["rel_all"] / rest, rel=1e-12)
    assert row["vs_rest"] == pytest.approx(np.mean([m["vs_rest"] for m in learned]), rel=1e-12)
    for setting in details["rows"][1:]:  # the solver's cheaper settings are measured against the same baseline
        assert setting["rest_rel_all"] == pytest.approx(row["rest_rel_all"], rel=1e-12), setting["label"]
    skill = report.split("## Skill per trajectory")[1].split("##")[0]
    cells = [line.split("|")[1:-1] for line in skill.splitlines() if line.startswith("| mean")]
    assert len(cells) == 1 and float(cells[0][3]) == pytest.approx(row["vs_rest"], rel=5e-3)
