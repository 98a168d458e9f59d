"""pretrained/press2d: committed, weights-only loadable, and it knows how a bonded body deforms.

A body drawn from the family's training ranges with a seed no split uses is simulated over the
whole press and the committed model predicts it through the code ``bsms.evaluate`` runs; then a
shape of no split (a plate with a V notch) is placed by ``bsms.infer`` and checked against the
solver."""

import json

import numpy as np
from pretrained_checks import exported, fresh_rollout

from bsms.infer import main as infer_main
from datagen import shapes

# measured: 0.356 on the fresh body (a random polygon, 0.40% of its size at rest), 0.430 on the notched
# plate (0.78% at rest; meshed at 4 mm and refined once, to 2187 nodes, as bsms.infer places it: 0.674 as
# given, 573 nodes; the bar for shapes of no split is 0.5, docs/press.md)
VS_REST_FRESH, VS_REST_NOTCH = 0.5, 0.5


def test_weights_only_and_small():
    _, dataset = exported("press2d")
    assert dataset["family"] == "press" and dataset["params"]["base"] == "bonded"
    assert dataset["params"]["mesh_size"] == 0.00375  # the background mesh a 7.5 mm one is not converged to


def test_presses_a_fresh_body_better_than_predicting_no_motion(tmp_path):
    metrics = fresh_rollout(exported("press2d")[0], tmp_path)
    assert metrics["rest_rel_all"] > 0.003  # the press moves the body: no motion is off
    assert metrics["vs_rest"] < VS_REST_FRESH, metrics["vs_rest"]


def test_infers_a_shape_of_no_split_against_the_solver(tmp_path):
    """A 12 x 6 cm plate with a V notch in its top, meshed at 4 mm, placed by the family's ``place``
    (bonded to the floor, a disk straight down; the mesh subdivided once to the family's resolution)."""
    ring = np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.06], [0.07, 0.06], [0.06, 0.032], [0.05, 0.06], [0.0, 0.06]])
    mesh_file = tmp_path / "notched.msh"
    shapes.polygon(ring, size=0.004).write(str(mesh_file))
    out = tmp_path / "out"
    folder = exported("press2d")[0]
    assert infer_main([str(folder), "--mesh", str(mesh_file), "--solver", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["finite"] is True and summary["params"]["base"] == "bonded"
    assert summary["nodes"] == [573] and summary["body_nodes"] == 2187  # refined once to the family's 2.5 mm
    assert (out / "solver.xdmf").is_file() and (out / "prediction.xdmf").is_file()
    assert summary["rest_rel_all"] > 0.003
    assert summary["vs_rest"] < VS_REST_NOTCH, summary["vs_rest"]
