"""The press scene (a body on a floor pressed by a moving indenter) and the press family."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from datagen import simulate
from datagen.config import ConfigError
from datagen.families import get_family, place
from datagen.families.press import _simple, random_stroke
from datagen.scenes import get_scene
from datagen.scenes.press import INDENTER_SIZES

press = get_scene("press")
FAST = {"E": 2e4, "body_size": 0.01, "mesh_size": 0.02, "size": 0.12}


def build(**given):
    return press.build(press.params({**FAST, **given}))


def test_body_rests_on_the_floor_with_its_largest_extent_the_size():
    scene = build(char="H", lift=0.001)
    nodes = scene.body.nodes
    assert np.ptp(nodes, axis=0).max() == pytest.approx(0.12, rel=1e-12)
    assert nodes[:, 1].min() == pytest.approx(0.001, abs=1e-15)
    assert (nodes.min(0)[0] + nodes.max(0)[0]) / 2 == pytest.approx(0.12, abs=1e-15)  # the middle of the box


@pytest.mark.parametrize("shape", sorted(INDENTER_SIZES))
def test_the_indenter_starts_gap_above_the_body_under_it_and_comes_back(shape):
    """Over a sloping roof the indenter's underside (not its lowest point) comes within exactly
    ``gap`` of the body, straight above it: lifted by the gap, the body touches the indenter."""
    sizes = {"disk": [0.02], "box": [0.02, 0.01], "wedge": [0.02, 0.03]}[shape]
    scene = build(polygon=[[0, 0], [1, 0], [0.5, 0.6]], indenter=shape, indenter_size=sizes, indenter_x=0.025,
                  gap=0.003, speed=0.05, angle=30.0, press_time=0.2, hold_time=0.1)
    collider = scene.colliders[0]
    start = collider.path.position(0.0)
    nodes = torch.tensor(scene.body.nodes)
    lifted, _ = collider.signed_distance(nodes + torch.tensor([0.0, 0.003], dtype=nodes.dtype), 0.0)
    assert float(lifted.min()) == pytest.approx(0.0, abs=1e-12)
    assert float(collider.signed_distance(nodes, 0.0)[0].min()) > 0.0
    assert start[0] == pytest.approx(0.12 + 0.025, abs=1e-15)
    bottom = collider.path.position(0.2)
    np.testing.assert_allclose(bottom - start, 0.05 * 0.2 * np.array([math.sin(math.pi / 6), -math.cos(math.pi / 6)]),
                               atol=1e-15)
    np.testing.assert_array_equal(collider.path.position(0.3), bottom)  # held
    np.testing.assert_allclose(collider.path.position(0.5), start, atol=1e-15)  # back where it started
    np.testing.assert_allclose(collider.path.velocity(0.3, 0.5), -(bottom - start) / 0.2, atol=1e-15)


def test_obstacle_positions_move_only_the_indenter_surface_along_its_path():
    scene = build(char="L", indenter="box", indenter_size=[0.02, 0.01], speed=0.04)
    times = np.array([0.0, 0.05, 0.2, 0.4])
    moved = scene.obstacle_positions(times)
    m = scene.collider_nodes[0]
    walls = len(scene.obstacle_nodes) - m
    assert moved.shape == (4, len(scene.obstacle_nodes), 2)
    np.testing.assert_array_equal(moved[:, :walls], np.broadcast_to(scene.obstacle_nodes[:walls], (4, walls, 2)))
    path = scene.colliders[0].path
    for k, t in enumerate(times):
        np.testing.assert_allclose(moved[k, walls:] - scene.obstacle_nodes[walls:], np.broadcast_to(
            path.position(t) - path.points[0], (m, 2)), atol=1e-15)
    # the surface nodes are on the indenter's boundary at t = 0
    phi, _ = scene.colliders[0].signed_distance(__import__("torch").tensor(scene.obstacle_nodes[walls:]), 0.0)
    assert float(phi.abs().max()) < 1e-15


def test_a_static_scene_has_no_obstacle_positions():
    glyphs = get_scene("glyphs")
    scene = glyphs.build(glyphs.params({"body_size": 0.05, "mesh_size": 0.1}))
    assert scene.obstacle_positions([0.0, 0.1]) is None


def test_min_nodes_refines_thin_bodies_only():
    coarse = build(char="I", body_size=0.01)
    fine = build(char="I", body_size=0.01, min_nodes=400)
    assert fine.body.n_nodes >= 400 * 0.8 > coarse.body.n_nodes
    wide = build(char="M", body_size=0.01, min_nodes=10)  # already above: body_size kept
    assert wide.body.n_nodes == build(char="M", body_size=0.01).body.n_nodes


def test_grid_ratio_gives_a_body_meshed_finer_a_background_as_much_finer():
    """grid_ratio r: the background spacing is min(mesh_size, r x the body's spacing), the spacing
    a body refined for min_nodes was meshed at; a body at body_size keeps mesh_size exactly."""
    given = {"char": "I", "body_size": 0.01, "mesh_size": 0.02, "min_nodes": 400}
    thin = press.params({**FAST, **given, "grid_ratio": 1.5})
    scene = press.build(thin)
    area = float(scene.body.cell_measures.sum())
    body_spacing = math.sqrt(1.15 * area / 400)  # the min_nodes rule, finer than body_size here
    assert body_spacing < 0.01
    assert scene.grid_spacing == pytest.approx(1.5 * body_spacing, rel=1e-9)
    assert press.background_spacing(thin) == pytest.approx(scene.grid_spacing, rel=1e-9)
    assert scene.body.n_nodes == build(**given).body.n_nodes  # the body is meshed as without it
    edges = scene.domain.edge_lengths
    assert np.median(edges) == pytest.approx(scene.grid_spacing, rel=0.1)  # the background is meshed at it
    assert build(**given).grid_spacing == 0.02  # grid_ratio 0 (the default): mesh_size
    wide = build(char="M", body_size=0.01, mesh_size=0.02, grid_ratio=2.5)  # 2.5 x 0.01 > mesh_size
    assert wide.grid_spacing == 0.02 and wide.domain.n_nodes == build(char="M").domain.n_nodes
    assert build(char="M", body_size=0.01, mesh_size=0.02, grid_ratio=1.5).grid_spacing == pytest.approx(0.015)


def test_polygon_and_mesh_bodies():
    square = [[0, 0], [2, 0], [2, 1], [0, 1]]
    scene = build(polygon=square)
    assert np.ptp(scene.body.nodes, axis=0) == pytest.approx([0.12, 0.06], rel=1e-9)
    area = scene.body.cell_measures.sum()
    assert area == pytest.approx(0.12 * 0.06, rel=1e-9)
    inline = {"nodes": [[0, 0], [1, 0], [0, 1], [1, 1]], "cells": [[0, 1, 2], [1, 3, 2]]}
    assert build(mesh=inline).body.n_nodes == 4


@pytest.mark.parametrize("given, message", [
    ({"indenter": "cone"}, "params.indenter must be one of ['box', 'disk', 'wedge'], got 'cone'"),
    ({"indenter": "box", "indenter_size": [0.02]},
     "params.indenter_size must list 2 positive length(s) for a box indenter, got [0.02]"),
    ({"angle": 90.0}, "params.angle must lie in [-80, 80] degrees from straight down, got 90.0"),
    ({"gap": -0.1}, "params.gap must be >= 0, got -0.1"),
    ({"grid_ratio": -1.5}, "params.grid_ratio must be >= 0, got -1.5"),
    ({"pose": "lying"}, "params.pose must be one of ['stable', 'upright'], got 'lying'"),
    ({"char": "AB"}, "params.char must be a single visible character, got 'AB'"),
    ({"polygon": [[0, 0], [1, 0], [0, 1]], "mesh": "x.msh"},
     "params.polygon and params.mesh both give the body; give one of them (or params.char)"),
    ({"box": [0, 0, 0, 1, 1, 1]}, "params.box must be a 2D box [x0, y0, x1, y1] (the press scene is 2D), got "
                                  "[0, 0, 0, 1, 1, 1]"),
])
def test_bad_parameters_name_the_key(given, message):
    with pytest.raises(ConfigError) as info:
        press.params({**FAST, **given})
    assert str(info.value) == message


def test_a_standing_body_keeps_its_pose_and_a_toppling_one_is_turned_onto_its_most_stable_side():
    from scipy.spatial import ConvexHull

    from datagen.scenes.press import centre_of_mass, stands

    standing = build(char="H", pose="stable").body
    assert np.array_equal(standing.nodes, build(char="H").body.nodes)
    corner = [[1.0, 0.0], [0.2, 0.6], [-0.7, 0.5], [-0.6, -0.6], [0.1, -0.9]]  # rests on a corner when upright
    for given in ({"char": "J"}, {"polygon": corner}):
        upright, turned = build(**given).body, build(**given, pose="stable").body
        assert not stands(upright) and stands(turned)
        edges = upright.cells[:, :2]  # turned and scaled, not deformed: every edge by the same factor
        ratio = [np.linalg.norm(np.diff(m.nodes[edges], axis=1), axis=-1) for m in (turned, upright)]
        np.testing.assert_allclose(ratio[0] / ratio[1], (ratio[0] / ratio[1]).mean(), rtol=1e-12)
        assert np.ptp(turned.nodes, axis=0).max() == pytest.approx(0.12, rel=1e-12)
        # the hull edge nearest the centre of mass lies on the floor, the centre of mass over it
        hull = ConvexHull(turned.nodes)
        c = centre_of_mass(turned)
        nearest = hull.equations[np.argmax(hull.equations[:, :2] @ c + hull.equations[:, 2])]
        np.testing.assert_allclose(nearest[:2], [0.0, -1.0], atol=1e-12)
        on_floor = turned.nodes[np.abs(turned.nodes[:, 1] - turned.nodes[:, 1].min()) < 1e-9, 0]
        assert len(on_floor) >= 2 and on_floor.min() < c[0] < on_floor.max()


def test_a_body_larger_than_the_box_is_refused():
    with pytest.raises(ConfigError, match=r"params.size: the body spans .* more than params.box"):
        build(size=0.5)


def test_the_body_waits_for_the_indenter_then_is_pushed_down():
    """Two frames of a soft, coarse press: before the indenter arrives the body only settles under
    gravity (millimetres at most); the indenter's obstacle positions are stored per frame."""
    config = {"scene": "press", "params": {**FAST, "char": "H", "gap": 0.03, "speed": 0.05, "E": 1e5},
              "solver": {"cfl": 0.5, "threads": 1}, "output": {"frames": 2, "frame_interval": 0.02}}
    trajectory = simulate(config)
    moved = trajectory.obstacle_positions
    assert moved.shape == (3, len(trajectory.obstacle_nodes), 2)
    drop = moved[:, -1, 1] - moved[0, -1, 1]
    np.testing.assert_allclose(drop, [0.0, -0.001, -0.002], atol=1e-12)
    sag = np.abs(trajectory.positions[-1] - trajectory.positions[0]).max()
    g, rho, E, h = 9.81, 1200.0, 1e5, 0.12
    assert 0 < sag < 5 * rho * g * h**2 / E  # no contact yet: gravity sag only (static estimate 1.7 mm)


# ----------------------------------------------------------------------------- family
def test_family_samples_are_deterministic_and_test_shapes_are_unseen():
    family = get_family("press")
    draws = [family.sample({}, np.random.default_rng(k), "test") for k in range(12)]
    again = [family.sample({}, np.random.default_rng(k), "test") for k in range(12)]
    assert draws == again
    assert any("polygon" in p for p in draws) and any("char" in p for p in draws)
    assert all(p["char"] in "GJQSU" for p in draws if "char" in p)
    train = [family.sample({}, np.random.default_rng(k), "train") for k in range(12)]
    assert all("polygon" not in p and p["char"] in "ABCDEFHKLMNPRTVWXYZ" for p in train)
    for p in draws + train:
        assert 1e6 <= p["E"] <= 2e7 and 0.3 <= p["nu"] <= 0.45 and 0.03 <= p["speed"] <= 0.06
        assert p["indenter"] in INDENTER_SIZES and len(p["indenter_size"]) == INDENTER_SIZES[p["indenter"]]


def test_train_polygons_mix_random_polygons_into_training_and_leave_old_draws_alone():
    family = get_family("press")
    plain = [family.sample({}, np.random.default_rng(k), "train") for k in range(40)]
    assert plain == [family.sample({"train_polygons": 0.0}, np.random.default_rng(k), "train") for k in range(40)]
    mixed = [family.sample({"train_polygons": 0.5}, np.random.default_rng(k), "valid") for k in range(40)]
    polygons = [p["polygon"] for p in mixed if "polygon" in p]
    assert 10 <= len(polygons) <= 30 and all("char" in p for p in mixed if "polygon" not in p)
    assert len({str(p) for p in polygons}) == len(polygons)  # every one drawn afresh
    everything = [family.sample({"train_polygons": 1}, np.random.default_rng(k), "train") for k in range(5)]
    assert all("polygon" in p and 5 <= len(p["polygon"]) <= 9 for p in everything)
    for bad in (1.5, -0.1, "half", True):
        with pytest.raises(ConfigError) as error:
            family.sample({"train_polygons": bad}, np.random.default_rng(0), "train")
        assert str(error.value) == ("ranges.train_polygons is the fraction of bodies that are random polygons: "
                                    f"a number from 0 to 1, got {bad!r}")


def test_train_strokes_mix_thick_bent_bars_into_training():
    family = get_family("press")
    plain = [family.sample({"train_polygons": 0.5}, np.random.default_rng(k), "train") for k in range(30)]
    assert plain == [family.sample({"train_polygons": 0.5, "train_strokes": 0.0}, np.random.default_rng(k), "train")
                     for k in range(30)], "no strokes: the polygon datasets replay"
    tests = [family.sample({}, np.random.default_rng(k), "test") for k in range(30)]
    assert tests == [family.sample({"train_strokes": 0.4}, np.random.default_rng(k), "test") for k in range(30)]
    mixed = [family.sample({"train_polygons": 0.3, "train_strokes": 0.3}, np.random.default_rng(k), "train")
             for k in range(60)]
    rings = [np.array(p["polygon"]) for p in mixed if "polygon" in p]
    polygons_only = [family.sample({"train_polygons": 0.6}, np.random.default_rng(k), "train") for k in range(60)]
    assert [("polygon" in p) for p in mixed] == [("polygon" in p) for p in polygons_only], "one draw decides the kind"
    assert 24 <= len(rings) <= 48
    strokes = [family.sample({"train_strokes": 1}, np.random.default_rng(k), "train")["polygon"] for k in range(20)]
    for ring in map(np.array, strokes):
        assert _simple(ring), "a stroke's outline never crosses itself"
        assert np.ptp(ring, axis=0).max() == pytest.approx(1.0, abs=2e-6)
        np.testing.assert_allclose((ring.max(0) + ring.min(0)) / 2, 0.0, atol=2e-6)
        assert len(ring) % 2 == 0 and len(ring) >= 4  # two offset sides of one centreline
    with pytest.raises(ConfigError, match=r"^ranges.train_polygons \+ ranges.train_strokes is 1.2: the fractions"):
        family.sample({"train_polygons": 0.6, "train_strokes": 0.6}, np.random.default_rng(0), "train")


def test_a_stroke_meshes_as_a_press_body():
    ring = random_stroke(np.random.default_rng(5), 3, 0.25)
    scene = build(polygon=ring)
    nodes = scene.body.nodes
    assert np.ptp(nodes, axis=0).max() == pytest.approx(0.12, rel=1e-9)
    # the mesh fills the outline: its area is the outline's (shoelace), scaled to the body size
    outline = np.array(ring) * 0.12 / np.ptp(np.array(ring), axis=0).max()
    x, y = outline.T
    area = 0.5 * abs(x @ np.roll(y, -1) - y @ np.roll(x, -1))
    assert scene.body.cell_measures.sum() == pytest.approx(area, rel=1e-9)


def test_family_places_one_foreign_mesh_with_overrides(tmp_path):
    inline_nodes = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
    from datagen.mesh import Mesh
    path = tmp_path / "square.msh"
    Mesh(inline_nodes, np.array([[0, 1, 2], [1, 3, 2]])).write(path)
    dconfig = {"family": "press", "params": {"body_size": 0.01, "mesh_size": 0.02}, "solver": {"threads": 1},
               "output": {"frames": 3, "frame_interval": 0.01}}
    config = place("press", [str(path)], dconfig, {"indenter": "wedge", "indenter_size": [0.02, 0.03]})
    p = config["params"]
    assert config["scene"] == "press" and p["mesh"] == str(path.resolve())
    assert p["indenter"] == "wedge" and p["size"] == pytest.approx(0.115) and p["E"] == pytest.approx(math.sqrt(2e13))
    with pytest.raises(ConfigError, match="family 'press' presses one body"):
        place("press", [str(path), str(path)], dconfig)
    with pytest.raises(ConfigError, match="overrides.chars is not a press scene parameter"):
        place("press", [str(path)], dconfig, {"chars": ["A"]})


def test_settling_starts_the_frames_from_rest_in_equilibrium():
    """With a settling pre-roll the body starts at rest, already sagged under gravity, and the
    indenter starts where it would without it; without one the body rings as gravity comes on."""
    base = {"scene": "press", "params": {**FAST, "char": "H", "gap": 0.05, "speed": 0.02, "E": 1e5},
            "solver": {"cfl": 0.5, "threads": 1}, "output": {"frames": 2, "frame_interval": 0.01}}
    settled = simulate({**base, "params": {**base["params"], "settle_time": 0.15, "settle_damping": 400.0}})
    ringing = simulate(base)
    np.testing.assert_array_equal(settled.obstacle_positions, ringing.obstacle_positions)
    np.testing.assert_allclose(settled.times, ringing.times, atol=1e-12)  # the settling takes no frame time
    sag = settled.positions[0, :, 1] - settled.mesh.nodes[:, 1]
    assert sag.min() < 0, "frame 0 has sagged under gravity"
    speed = lambda t: np.abs(np.diff(t.positions, axis=0)).max() / 0.01  # noqa: E731
    assert speed(settled) < 0.1 * speed(ringing)  # measured 0.056


def test_a_bonded_base_holds_the_body_where_a_resting_one_slides():
    """params.base: bonded makes the floor a sticky wall. A block pushed down and sideways (60
    degrees) on a slippery floor slides on it when it rests there (base 1.8 mm in 0.1 s,
    measured); bonded, its base stays within a few hundredths of a background cell (61 um of a
    20 mm cell, measured) while its top is pushed over (0.83 mm): the motion is deformation."""
    def run(base):
        config = {"scene": "press", "params": {
            **FAST, "E": 1e5, "polygon": [[0, 0], [1, 0], [1, 0.6], [0, 0.6]], "base": base, "friction": 0.1,
            "indenter": "box", "indenter_size": [0.03, 0.01], "gap": 0.001, "speed": 0.1, "angle": 60.0,
            "press_time": 0.1}, "solver": {"cfl": 0.5, "threads": 1}, "output": {"frames": 5, "frame_interval": 0.02}}
        trajectory = simulate(config)
        y = trajectory.mesh.nodes[:, 1]
        dx = trajectory.positions[-1, :, 0] - trajectory.positions[0, :, 0]
        return np.abs(dx[y <= y.min() + 1e-9]).max(), dx[y >= y.max() - 1e-9].mean()

    resting_base, _ = run("resting")
    bonded_base, bonded_top = run("bonded")
    assert resting_base > 1e-3
    assert bonded_base < 1.5e-4 and bonded_top > 4e-4
    with pytest.raises(ConfigError, match="params.base"):
        build(base="glued")
