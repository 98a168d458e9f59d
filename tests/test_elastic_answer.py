"""benchmarks/elastic_answer.py: graph.elastic's input alone, scored as a learned rollout is."""

import sys
from pathlib import Path

import numpy as np
import pytest

from bsms.data import GraphOptions, Scenario
from bsms.fields import FieldSpec
from bsms.run import split_files
from datagen.dataset import load
from datagen.generate import main as datagen_main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import elastic_answer  # noqa: E402
from ensemble import score  # noqa: E402


@pytest.fixture(scope="module")
def pressed(tmp_path_factory):
    """Two test trajectories of the quickstart's press family (a second of solver time)."""
    root = tmp_path_factory.mktemp("pressed")
    assert datagen_main(["configs/datasets/press_quickstart.yaml", "--split", "test", "--out", str(root),
                         "--shard", "0/4", "--quiet"]) == 0
    return root / "press_quickstart"


def test_the_answer_is_the_input_a_model_gets_and_the_last_line_says_its_score(pressed, capsys):
    assert elastic_answer.main(["--data", str(pressed), "--hold", "1", "0.05"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == "| hold (median edges) | vs at rest (per trajectory) | RMSE all / body size |"
    first = lines[2].split("|")
    assert first[1].strip() == "1" and lines[3].split("|")[1].strip() == "0.05"
    # the same answer through a scenario of graph.elastic, frame by frame, as a model's input
    scored = []
    for path in split_files(pressed, "test"):
        trajectory = load(path)
        options = GraphOptions(levels=2, from_rest=True, penetration=True, elastic=True)
        scenario = Scenario.from_trajectory(trajectory, options)
        n = scenario.n_body
        predicted = np.empty_like(trajectory.positions)
        for k, obstacles in enumerate(trajectory.obstacle_positions):
            frame = scenario.frame(scenario.positions(scenario.rest_pos[:n], obstacles),
                                   np.zeros_like(scenario.rest_pos))
            body = frame.nodes["scenario_nodes"] < n
            predicted[k] = scenario.rest_pos[:n]
            predicted[k][frame.nodes["scenario_nodes"][body]] += frame.nodes["elastic"][body]
        scored.append(score(predicted, trajectory, FieldSpec.lagrangian(2)))
    vs = [m["vs_rest"] for m in scored]
    assert first[2].strip() == f"{np.mean(vs):.3g} ({', '.join(f'{v:.2f}' for v in vs)})"
    assert 0.05 < np.mean(vs) < 1.0  # it knows something of the motion, not all of it
    ms = float(lines[-1].split(", ")[-1].split()[0])
    assert lines[-1] == f"elastic answer: vs at rest {np.mean(vs):.3g} on 2 trajectories (hold 1 edges), " \
                        f"{ms:.3g} ms per frame"


def test_a_split_without_trajectories_is_refused(pressed, capsys):
    with pytest.raises(SystemExit):
        elastic_answer.main(["--data", str(pressed), "--split", "valid"])
    assert f"error: dataset folder {pressed} has no valid trajectories" in capsys.readouterr().err


def test_the_scale_table_gives_the_factor_that_best_fits_each_answer_to_its_data(pressed, capsys):
    assert elastic_answer.main(["--data", str(pressed), "--hold", "1", "0.5", "--scale"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == "| hold (median edges) | vs at rest (per trajectory) | RMSE all / body size |"
    assert lines[5:7] == ["| hold (median edges) | data / answer, median (per trajectory) |", "|---|---|"]
    spec = FieldSpec.lagrangian(2)
    for line, hold in zip(lines[7:9], (1.0, 0.5), strict=True):
        factors = []
        for path in split_files(pressed, "test"):
            trajectory = load(path)
            predicted, _ = elastic_answer.answers(trajectory, hold)
            factor = elastic_answer.best_scale(predicted, trajectory, spec)
            # the best factor: the fit's residual grows either way off it
            truth = trajectory.positions - trajectory.positions[:1]
            answer = predicted - trajectory.mesh.nodes
            residual = [np.sum((truth - f * answer) ** 2) for f in (0.99 * factor, factor, 1.01 * factor)]
            assert residual[1] < min(residual[0], residual[2])
            factors.append(factor)
        assert line == f"| {hold:g} | {np.median(factors):.3g} ({', '.join(f'{f:.2f}' for f in factors)}) |"
    assert lines[-1].startswith("elastic answer: vs at rest ")
