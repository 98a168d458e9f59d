"""pretrained/bracket2d: committed, weights-only loadable, and it knows how a clamped bracket bends.

A bracket drawn from the family's ranges with a seed no split uses is simulated over the whole
drive and the committed model predicts it through the code ``bsms.evaluate`` runs; then a
bracket of no split (a tapered bar) is placed by ``bsms.infer`` and checked against the solver."""

import json

import numpy as np
from pretrained_checks import PRETRAINED, exported, fresh_rollout

from bsms.infer import main as infer_main
from datagen import shapes

FOLDER = PRETRAINED / "bracket2d"
# measured: 0.0997 on the fresh bracket (5.5% of the body size at rest), 0.142 on the tapered bar (8.5%)
VS_REST_FRESH, VS_REST_TAPER = 0.2, 0.3


def test_weights_only_and_small():
    _, dataset = exported("bracket2d")
    assert dataset["family"] == "bracket" and dataset["params"]["damping"] == 200.0
    assert dataset["params"]["mesh_size"] == 0.00375  # the background mesh a 7.5 mm one is not converged to


def test_bends_a_fresh_bracket_far_better_than_predicting_no_motion(tmp_path):
    metrics = fresh_rollout(FOLDER, tmp_path)
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
