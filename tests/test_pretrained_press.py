"""pretrained/press2d: committed, weights-only loadable, and it knows how a bonded body deforms.

A body drawn from the family's training ranges with a seed no split uses is simulated over the
whole press and the committed model predicts it through the code ``bsms.evaluate`` runs; then a
shape of no split (a plate with a V notch) is placed by ``bsms.infer`` and checked against the
solver."""

import json
import sys
from pathlib import Path

from pretrained_checks import exported, fresh_rollout

from bsms.infer import main as infer_main
from datagen import shapes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from press_zero_shot import outlines  # noqa: E402

# measured with the model trained on press_stiff_960 and its mirror average (docs/press.md at 8757482, "The mirror
# average in one pass"): 0.182 on the star and 0.337 on the notched plate (0.87% and 0.78% at rest;
# meshed at 4 mm and refined once, as bsms.infer places them; python benchmarks/press_zero_shot.py;
# without the average 0.240 and 0.335); the bar for shapes of no split is 0.5. The fresh body: a random
# polygon, 0.40% of its size at rest.
VS_REST_FRESH, VS_REST_STAR, VS_REST_NOTCH = 0.5, 0.5, 0.5


def test_weights_only_and_small():
    _, dataset = exported("press2d")
    assert dataset["family"] == "press" and dataset["params"]["base"] == "bonded"
    assert dataset["params"]["mesh_size"] == 0.00375  # the background mesh a 7.5 mm one is not converged to


def test_presses_a_fresh_body_better_than_predicting_no_motion(tmp_path):
    metrics = fresh_rollout(exported("press2d")[0], tmp_path)
    assert metrics["rest_rel_all"] > 0.003  # the press moves the body: no motion is off
    assert metrics["vs_rest"] < VS_REST_FRESH, metrics["vs_rest"]


def _infer(mesh, tmp_path):
    mesh_file = tmp_path / "shape.msh"
    mesh.write(str(mesh_file))
    out = tmp_path / "out"
    assert infer_main([str(exported("press2d")[0]), "--mesh", str(mesh_file), "--solver", "--out", str(out),
                       "--quiet"]) == 0
    return json.loads((out / "summary.json").read_text()), out


def test_infers_a_star_of_no_split_within_the_bar(tmp_path):
    """press_zero_shot.py's five-pointed star, meshed at 4 mm, placed by the family's ``place``."""
    summary, _ = _infer(shapes.polygon(outlines()["star"], size=0.004), tmp_path)
    assert summary["finite"] is True and summary["rest_rel_all"] > 0.003
    assert summary["vs_rest"] < VS_REST_STAR, summary["vs_rest"]


def test_infers_a_shape_of_no_split_against_the_solver(tmp_path):
    """A 12 x 6 cm plate with a V notch in its top, meshed at 4 mm, placed by the family's ``place``
    (bonded to the floor, a disk straight down; the mesh subdivided once to the family's resolution)."""
    summary, out = _infer(shapes.polygon(outlines()["notched plate"], size=0.004), tmp_path)
    assert summary["finite"] is True and summary["params"]["base"] == "bonded"
    assert summary["nodes"] == [573] and summary["body_nodes"] == 2187  # refined once to the family's 2.5 mm
    assert (out / "solver.xdmf").is_file() and (out / "prediction.xdmf").is_file()
    assert summary["rest_rel_all"] > 0.003
    assert summary["vs_rest"] < VS_REST_NOTCH, summary["vs_rest"]
