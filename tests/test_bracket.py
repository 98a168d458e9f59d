"""The bracket family: brackets clamped at the box's left wall (press scene, ``base: clamped``), bent by an indenter."""

from __future__ import annotations

import numpy as np
import pytest

from datagen import simulate
from datagen.config import ConfigError
from datagen.families import get_family, place
from datagen.families.bracket import random_bracket
from datagen.families.press import _simple
from datagen.scenes import get_scene

press = get_scene("press")
bracket = get_family("bracket")
FAST = {"E": 2e5, "body_size": 0.01, "mesh_size": 0.02, "size": 0.12}
BAR = [[0, 0], [1, 0], [1, 0.2], [0, 0.2]]


def test_a_clamped_body_sits_on_the_left_wall_centred_in_height():
    scene = press.build(press.params({**FAST, "polygon": BAR, "base": "clamped", "lift": 0.01}))
    nodes = scene.body.nodes
    assert nodes[:, 0].min() == 0.0  # the box's left wall
    assert (nodes[:, 1].min() + nodes[:, 1].max()) / 2 == pytest.approx(0.1 + 0.01, abs=1e-15)
    assert [w.kind for w in scene.walls] == ["sticky", "separating"]
    normals = np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
    assert scene.walls[0].where(np.zeros((4, 2)), normals).tolist() == [True, False, False, False]


def test_the_clamp_holds_the_end_while_the_indenter_bends_the_bar():
    """A bar 12 cm long clamped at x = 0, pushed down 9 mm (10 mm of travel less the 1 mm gap)
    near its free end: its clamped face moves 41 um (of a 20 mm background cell, measured), its
    tip drops 10.5 mm (the push and its own sag under gravity, measured)."""
    config = {"scene": "press", "params": {
        **FAST, "polygon": BAR, "base": "clamped", "indenter": "box", "indenter_size": [0.01, 0.01],
        "indenter_x": 0.045, "gap": 0.001, "speed": 0.1, "press_time": 0.1, "damping": 100.0},
        "solver": {"cfl": 0.5, "threads": 1}, "output": {"frames": 5, "frame_interval": 0.02}}
    trajectory = simulate(config)
    rest = trajectory.mesh.nodes
    moved = trajectory.positions[-1] - trajectory.positions[0]
    face, tip = rest[:, 0] <= 1e-12, rest[:, 0] >= rest[:, 0].max() - 1e-12
    assert np.abs(moved[face]).max() < 1e-4
    assert -0.012 < moved[tip, 1].mean() < -0.009


def test_random_brackets_leave_the_wall_straight_and_touch_it_only_there():
    """The clamped face is the one square end on x = 0; every other corner keeps at least half the
    bar's thickness (the face's length) off the wall, and the outline never crosses itself."""
    rng = np.random.default_rng(3)
    for segments in (1, 2, 3):
        for _ in range(20):
            ring = np.array(random_bracket(rng, segments, rng.uniform(0.18, 0.3)))
            assert np.ptp(ring, axis=0).max() == pytest.approx(1.0, abs=1e-5)
            assert _simple(ring) and ring[:, 0].min() == 0.0
            at_wall = ring[:, 0] == 0.0
            assert at_wall.sum() == 2
            face = np.ptp(ring[at_wall, 1])
            assert 0.04 < face < 0.5
            assert (ring[~at_wall, 0] > 0.5 * face - 2e-6).all()


def test_family_samples_are_deterministic_clamped_and_in_range():
    a = bracket.sample({}, np.random.default_rng(5), "train")
    b = bracket.sample({}, np.random.default_rng(5), "train")
    assert a == b and a["base"] == "clamped"
    draws = [bracket.sample({}, np.random.default_rng(k), "test") for k in range(30)]
    assert all(3e7 <= d["E"] <= 3e8 and d["indenter"] in ("disk", "box") for d in draws)
    assert len({str(d["polygon"]) for d in draws}) == 30  # every bracket drawn afresh
    scene = press.build(press.params({**FAST, **{k: v for k, v in a.items() if k not in FAST}}))
    assert scene.body.nodes[:, 0].min() == 0.0
    with pytest.raises(ConfigError, match=r"ranges.turn is the largest turn .* 0 to 135, got 150"):
        bracket.sample({"turn": 150.0}, np.random.default_rng(0), "train")


def test_family_clamps_one_foreign_mesh(tmp_path):
    config = place("bracket", [_bar_mesh()], "configs/datasets/bracket.yaml", {"speed": 0.1})
    assert config["scene"] == "press" and config["params"]["base"] == "clamped"
    assert config["params"]["speed"] == 0.1 and config["params"]["indenter"] == "disk"
    with pytest.raises(ConfigError, match="family 'bracket' clamps one body"):
        place("bracket", [_bar_mesh(), _bar_mesh()], "configs/datasets/bracket.yaml")
    with pytest.raises(ConfigError, match="overrides.char is not a press scene parameter"):
        place("bracket", [_bar_mesh()], "configs/datasets/bracket.yaml", {"char": "A"})


def _bar_mesh():
    from datagen import shapes
    return shapes.polygon(np.array(BAR, float) * 0.1, size=0.01)
