"""pretrained/bracket2d: committed, weights-only loadable, and it knows how a clamped bracket bends.

A bracket drawn from the family's ranges with a seed no split uses is simulated over the whole
drive and the committed model predicts it through the code ``bsms.evaluate`` runs; then a
bracket of no split (a tapered bar) is placed by ``bsms.infer`` and checked against the solver."""

import json
from pathlib import Path

import numpy as np
import torch

from bsms.infer import main as infer_main
from bsms.learned_rollouts import learned_rollouts
from bsms.run import load_model
from datagen import shapes
from datagen.dataset import load
from datagen.generate import generate

FOLDER = Path(__file__).resolve().parents[1] / "pretrained" / "bracket2d"
# measured: 0.0997 on the fresh bracket (5.5% of the body size at rest), 0.142 on the tapered bar (8.5%)
VS_REST_FRESH, VS_REST_TAPER = 0.2, 0.3


def test_weights_only_and_small():
    weights = FOLDER / "checkpoints" / "best.pt"
    assert weights.is_file() and weights.stat().st_size < 10 * 2**20
    state = torch.load(weights, map_location="cpu", weights_only=True)
    assert "optimizer" not in state and state["config"]["model"]["name"] == "bsms_gnn"
    dataset = json.loads((FOLDER / "dataset.json").read_text())
    assert dataset["family"] == "bracket" and dataset["params"]["damping"] == 200.0
    assert dataset["params"]["mesh_size"] == 0.00375  # the background mesh a 7.5 mm one is not converged to


def test_bends_a_fresh_bracket_far_better_than_predicting_no_motion(tmp_path):
    dconfig = json.loads((FOLDER / "dataset.json").read_text())
    dconfig.update(dataset="fresh_bracket", seed=987_654, splits={"test": 1})
    generate(dconfig, out=tmp_path, splits=["test"], workers=1, progress=False)
    trajectory = load(next((tmp_path / "fresh_bracket" / "test").glob("*.h5")))
    frames = len(trajectory.times) - 1
    model, config, _ = load_model(FOLDER)
    (metrics, result), = learned_rollouts(model, config.graph, [trajectory], tmp_path / "cache", [frames])
    assert np.isfinite(result.positions).all() and metrics["unstable_step"] is None
    assert metrics["rest_rel_all"] > 0.04  # the bracket bends: no motion is far off
    assert metrics["vs_rest"] < VS_REST_FRESH, metrics["vs_rest"]


def test_infers_a_bracket_of_no_split_against_the_solver(tmp_path):
    """A tapered bar (3.4 cm at the wall, 1 cm at its tip, 12 cm long), placed by the family's
    ``place`` (clamped at its leftmost points, a disk straight down over its outer part)."""
    ring = np.array([[0.0, 0.0], [0.12, 0.012], [0.12, 0.022], [0.0, 0.034]])
    mesh_file = tmp_path / "taper.msh"
    shapes.polygon(ring, size=0.0025).write(str(mesh_file))
    out = tmp_path / "out"
    assert infer_main([str(FOLDER), "--mesh", str(mesh_file), "--solver", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["finite"] is True and summary["params"]["base"] == "clamped"
    assert summary["rest_rel_all"] > 0.04
    assert summary["vs_rest"] < VS_REST_TAPER, summary["vs_rest"]
