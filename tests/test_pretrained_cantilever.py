"""pretrained/cantilever2d: committed, weights-only loadable, and it knows how a beam swings.

A beam drawn from the family's ranges with a seed no split uses is simulated for a few frames
and the committed model rolls out against it through the code ``bsms.evaluate`` runs."""

from pretrained_checks import exported, fresh_rollout

FRAMES = 20


def test_weights_only_and_small():
    assert exported("cantilever2d")[1]["family"] == "cantilever"


def test_beats_predicting_no_motion_on_a_fresh_beam(tmp_path):
    metrics = fresh_rollout(exported("cantilever2d")[0], tmp_path, frames=FRAMES)
    assert metrics["rest_rel_all"] > 0.01  # the beam swings: no motion is far off
    assert metrics["vs_rest"] < 0.1, metrics["vs_rest"]  # 0.04 measured (rest 14% of the body size, model 0.6%)
