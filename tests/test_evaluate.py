"""A reduced quickstart end to end (train.py -> evaluate -> report), and bsms.evaluate's outputs."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bsms.evaluate import SOLVER_SETTINGS, _interpolate_to, evaluate
from bsms.trainer import load_config

ROOT = Path(__file__).resolve().parents[1]
PNG, GIF = b"\x89PNG\r\n\x1a\n", b"GIF8"


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
    return runs / "quickstart", result.stdout


def test_quickstart_writes_the_report_and_every_chart(quickstart_run):
    run, stdout = quickstart_run
    assert "evaluated on 1 test trajectories: rollout RMSE" in stdout
    report = (run / "report.md").read_text()
    for picture in ("speed_accuracy.png", "error_vs_step.png", "training_curve.png", "rollout_0.gif"):
        assert f"(evaluation/{picture})" in report
        data = (run / "evaluation" / picture).read_bytes()
        assert data.startswith(GIF if picture.endswith(".gif") else PNG) and len(data) > 5000, picture
    import meshio

    with meshio.xdmf.TimeSeriesReader(str(run / "evaluation" / "rollout_0.xdmf")) as reader:
        points, _ = reader.read_points_cells()
        assert reader.num_steps == 7  # frame 0 and 6 predicted frames
        _, point_data, _ = reader.read_data(6)
    assert set(point_data) == {"position", "displacement", "error"} and point_data["error"].shape == (len(points),)
    with open(run / "evaluation" / "speed_accuracy.csv", newline="") as fh:
        rows = {row["label"]: row for row in csv.DictReader(fh)}
    assert set(rows) == {"quickstart", *SOLVER_SETTINGS.values()}
    assert float(rows[SOLVER_SETTINGS["reference"]]["rmse_all"]) == 0.0
    for label, row in rows.items():
        assert float(row["seconds_per_sim_second"]) > 0, label
    details = json.loads((run / "evaluation" / "metrics.json").read_text())
    reference = next(r for r in details["rows"] if r["label"] == SOLVER_SETTINGS["reference"])
    assert reference["max_difference_from_stored"] == 0.0, "the solver re-run must reproduce the stored data"
    learned = details["learned"]["quickstart"][0]
    assert len(learned["error_curve"]) == 6 and learned["steps"] == 6


def test_evaluate_learned_only_with_fewer_steps(quickstart_run):
    run, _ = quickstart_run
    config = load_config(run / "config.yaml")
    options = config.evaluate
    options.solver, options.steps, options.gifs = [], 3, 0
    result = evaluate(run, options=options, progress=False)
    (row,) = result["rows"]
    assert row["label"] == "quickstart" and row["trajectories"] == 1
    details = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert len(details["learned"]["quickstart"][0]["error_curve"]) == 3


def test_evaluate_cli_errors(tmp_path):
    result = subprocess.run([sys.executable, "-m", "bsms.evaluate", str(tmp_path / "missing")],
                            capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip() == (f"error: run folder {tmp_path / 'missing'} does not exist; train one with "
                                     "python train.py CONFIG")


def test_coarser_body_is_compared_at_the_reference_points():
    """A displacement field that is linear per body is carried over exactly between meshes."""
    from datagen import shapes

    fine, coarse = shapes.disk(0.5, 0.08), shapes.disk(0.5, 0.2)
    matrix = np.array([[0.1, 0.02], [-0.03, 0.05]])

    def moved(nodes, t):
        return nodes + t * (nodes @ matrix.T + np.array([0.2, -0.1]))

    times = np.linspace(0, 1, 4)[:, None, None]
    other = np.stack([moved(coarse.nodes, t) for t in times[:, 0, 0]])
    out = _interpolate_to(fine.nodes, np.zeros(fine.n_nodes, int), coarse.nodes, np.zeros(coarse.n_nodes, int),
                          other)
    inside = np.linalg.norm(fine.nodes, axis=1) < 0.45  # the coarse polygon covers these
    expected = np.stack([moved(fine.nodes, t) for t in times[:, 0, 0]])
    np.testing.assert_allclose(out[:, inside], expected[:, inside], atol=1e-12)
