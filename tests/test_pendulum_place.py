"""Zero-shot placement in the pendulum family: a user's plate hung on a pin through its hole
(``datagen.families.pendulum.place``, the scene's ``mesh`` parameter)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from datagen import shapes, simulate
from datagen.config import ConfigError
from datagen.families import place
from datagen.mesh import Mesh
from datagen.scenes import get_scene
from datagen.scenes.base import vertex_volumes

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "datasets"
FULL, QUICK = CONFIGS / "pendulum.yaml", CONFIGS / "pendulum_quick.yaml"
scene = get_scene("pendulum")
BAR = [[0.0, 0.0], [1.0, 0.0], [1.0, 0.3], [0.0, 0.3]]
HOLE = 0.0108  # m at the drawn size 0.12: 8.55 mm once placed at the family's 0.095 (1.4 cells of the quick 6 mm)


def _plate(tmp_path, pin_radius: float = HOLE, name: str = "plate.msh") -> tuple[Path, np.ndarray, int]:
    """A bar 12 cm long with a round hole at (18, 18) mm, meshed at 5 mm as the family meshes its plates
    (the hole a polygon of nodes on its circle); its file, the hole's centre and its node count."""
    p = scene.params({"polygon": BAR, "pivot": [0.15, 0.15], "size": 0.12, "pin_radius": pin_radius,
                      "body_size": 0.005})
    mesh, pivot = scene.plate(p)
    mesh.write(tmp_path / name)
    return tmp_path / name, pivot, max(12, math.ceil(2 * math.pi * pin_radius / 0.005))


def _ring(centre, rx: float, ry: float, count: int) -> np.ndarray:
    turn = 2 * math.pi * np.arange(count) / count
    return np.asarray(centre) + np.stack([rx * np.cos(turn), ry * np.sin(turn)], 1)


def test_the_pin_is_the_round_hole_and_the_plate_is_scaled_like_the_familys(tmp_path):
    """The pin's centre is the hole's and its radius the hole's (scaled to the family's mid-range size):
    exactly as meshed, and within the chords' sagitta (1 - cos(pi/14), 2.5%) where the family's 2.5 mm
    plates make the placement subdivide the 5 mm mesh (the chords' midpoints become nodes)."""
    path, centre, count = _plate(tmp_path)
    scale = 0.095 / 0.12
    config = place("pendulum", [str(path)], QUICK)  # 5 mm bodies: the mesh is kept as it is
    p = config["params"]
    assert config["scene"] == "pendulum" and p["mesh"] == str(path.resolve()) and p["kind"] == "mesh"
    assert p["size"] == pytest.approx(0.095) and p["E"] == pytest.approx(math.sqrt(1e11))
    assert (p["nu"], p["density"], p["amplitude"], p["angle"], p["direction"]) == (0.35, 1250.0, 55.0, 0.0, 1.0)
    np.testing.assert_allclose(p["pivot"], centre, atol=1e-12)
    assert p["pin_radius"] == pytest.approx(HOLE * scale, rel=1e-9)
    built = scene.build(scene.params(p))
    assert built.given_cells is None
    np.testing.assert_allclose(np.linalg.norm(built.obstacle_nodes, axis=1), p["pin_radius"], rtol=1e-9)
    assert np.linalg.norm(built.x, axis=1).min() == pytest.approx(p["pin_radius"], rel=1e-9)  # no particle inside

    fine = place("pendulum", [str(path)], FULL)["params"]
    np.testing.assert_allclose(fine["pivot"], centre, atol=1e-12)
    assert fine["pin_radius"] == pytest.approx(HOLE * scale * math.cos(math.pi / count), rel=1e-9)
    built = scene.build(scene.params(fine))
    assert built.given_cells is not None and built.body.n_nodes > 3 * len(np.unique(built.given_cells))


def test_several_holes_take_the_largest_or_the_one_the_pivot_names(tmp_path):
    outline = np.array(BAR) * 0.12
    small, large = _ring([0.018, 0.018], 0.0103, 0.0103, 14), _ring([0.1, 0.018], 0.0115, 0.0115, 16)
    mesh = shapes.polygon(outline, [small, large], size=0.005)
    p = place("pendulum", [mesh], QUICK)["params"]
    np.testing.assert_allclose(p["pivot"], [0.1, 0.018], atol=1e-12)
    p = place("pendulum", [mesh], QUICK, {"pivot": [0.02, 0.015]})["params"]
    np.testing.assert_allclose(p["pivot"], [0.018, 0.018], atol=1e-12)
    assert p["pin_radius"] == pytest.approx(0.0103 * 0.095 / 0.12, rel=1e-9)
    with pytest.raises(ConfigError, match=re.escape(
            "overrides.pivot [0.06, 0.018] lies in none of the 2 hole(s) of mesh meshes[0] (a Mesh); give a point "
            "inside the hole the pin goes through, in the mesh's own units (the holes' pins would be centred at "
            "[[0.1, 0.018], [0.018, 0.018]])")):
        place("pendulum", [mesh], QUICK, {"pivot": [0.06, 0.018]})


@pytest.mark.parametrize(("overrides", "angle", "amplitude", "sense"), [
    ({}, 0.0, 55.0, 1.0),  # the middle of the family's starts
    ({"angle": 20.0, "amplitude": 40.0, "direction": -1.0, "E": 2e5}, 20.0, 40.0, -1.0),
])
def test_the_placed_plate_starts_as_a_rigid_pendulum_of_its_amplitude(tmp_path, overrides, angle, amplitude, sense):
    path, _, _ = _plate(tmp_path)
    config = place("pendulum", [str(path)], QUICK, overrides)
    assert config["params"]["E"] == overrides.get("E", math.sqrt(1e11))
    built = scene.build(scene.params(config["params"]))
    x, v, volume = built.x, built.v, vertex_volumes(built.body)
    com = volume @ x / volume.sum()
    assert math.degrees(math.atan2(com[0], -com[1])) == pytest.approx(angle, abs=1e-9)
    spin = (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0]) / (x**2).sum(1)  # a rigid turn about the pin
    np.testing.assert_allclose(spin, spin[0], rtol=1e-9)
    d, k2 = np.linalg.norm(com), volume @ (x**2).sum(1) / volume.sum()
    energy = 0.5 * k2 * spin[0] ** 2 - 9.81 * d * math.cos(math.radians(angle))
    assert np.sign(spin[0]) == sense and energy == pytest.approx(-9.81 * d * math.cos(math.radians(amplitude)), rel=1e-9)


def test_bad_plates_are_refused_naming_the_mesh_and_the_fix(tmp_path):
    path, _, _ = _plate(tmp_path)
    solid = tmp_path / "solid.msh"
    shapes.rectangle(0.12, 0.036, 0.005).write(solid)
    with pytest.raises(ConfigError, match="^" + re.escape(
            f"mesh file {solid} has no hole for the pin: family 'pendulum' hangs its plates on a fixed pin through a "
            "round hole in them; mesh the plate with a round hole where it should turn (an inner boundary: in gmsh, "
            "cut a disk out of the surface; the family's holes are 6.3-7.9% of the plate's largest extent in "
            "radius)") + "$"):
        place("pendulum", [str(solid)], FULL)
    with pytest.raises(ConfigError, match="^" + re.escape(
            f"family 'pendulum' swings one plate on its pin: give meshes as a list of exactly one Mesh or file path, "
            f"got 2 meshes (file {path}, file {path}); place each on its own (bsms infer --separately)") + "$"):
        place("pendulum", [str(path), str(path)], FULL)
    block = tmp_path / "block.msh"
    Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2, 3]])).write(block)
    with pytest.raises(ConfigError, match="^" + re.escape(
            f"mesh file {block} is a 3D mesh but family 'pendulum' swings 2D plates; give a 2D triangle mesh (z = 0) "
            "of the plate") + "$"):
        place("pendulum", [str(block)], FULL)
    with pytest.raises(ConfigError, match="^overrides.pin_radius is not a pendulum scene parameter that can be "
                                          "overridden; known: E, amplitude, angle,"):
        place("pendulum", [str(path)], FULL, {"pin_radius": 0.01})


def test_a_pin_too_small_for_the_background_or_loose_in_its_hole_is_refused(tmp_path):
    """Under the family's smallest pin in background cells (6 mm over 3.75 mm: 1.6) the joint is not what
    the family's data hold (docs/pendulum.md); a square hole fits its pin snugly, a slot 1.5 times as long
    as wide leaves it 0.94 cells of play."""
    small, _, _ = _plate(tmp_path, pin_radius=0.0065, name="small.msh")
    message = (f"mesh file {small}: the largest pin its hole takes is 4.97 mm in radius with the plate scaled to "
               "0.095 m, 1.33 background cells of 3.75 mm; family 'pendulum''s pins are at least 1.60 cells, and "
               "fewer let the hole wander off the pin (docs/pendulum.md); mesh a larger hole, scale the plate up "
               "(overrides size=0.1147) or refine the background (overrides mesh_size=0.003106)")
    with pytest.raises(ConfigError, match="^" + re.escape(message) + "$"):
        place("pendulum", [str(small)], FULL)
    for fix in ({"size": 0.1147}, {"mesh_size": 0.003106}):  # either fix places it
        assert place("pendulum", [str(small)], FULL, fix)["params"]["pin_radius"] >= 1.6 * 0.003106
    outline = np.array(BAR) * 0.12
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * 0.0095 + 0.018
    p = place("pendulum", [shapes.polygon(outline, [square], size=0.003)], FULL)["params"]
    inscribed, spacing = 0.0095 * 0.095 / 0.12, 0.003 * 0.095 / 0.12  # nodes every 3 mm: the pin bulges between
    assert inscribed < p["pin_radius"] <= inscribed + spacing**2 / (8 * inscribed)  # them by a sagitta at most
    slot = np.array([[-1.5, -1], [1.5, -1], [1.5, 1], [-1.5, 1]]) * 0.0085 + 0.018
    with pytest.raises(ConfigError, match="^" + re.escape(
            "mesh meshes[0] (a Mesh): the largest pin its hole takes (6.82 mm in radius with the plate scaled to "
            "0.095 m) could move 3.54 mm about in it, 0.94 background cells of 3.75 mm, and family 'pendulum''s "
            "joint is a pin that fills its hole (at most 0.5 cells of play); mesh a round hole, or one the pin "
            "touches all round (a square, a regular polygon)") + "$"):
        place("pendulum", [shapes.polygon(outline + [0.01, 0], [slot + [0.01, 0]], size=0.003)], FULL)


def test_the_placed_plate_swings_on_the_pin_with_its_hole_around_it(tmp_path):
    """The quick config's coarse plate (237 nodes, 6 mm background; E 20 MPa: a soft plate's hole
    stretches under its weight), 20 frames from the bottom of a 55 degree swing: the centroid of the
    hole's nodes (a round hole: its centre) stays within 0.1 mm of the pin (0.02 mm measured), the
    scene's own measure of it agrees, and the plate turns back at the amplitude it was started for."""
    path, _, _ = _plate(tmp_path)
    config = place("pendulum", [str(path)], QUICK, {"E": 2e7})
    config["solver"] = {**config["solver"], "threads": 1}
    config["output"] = {"frames": 20, "frame_interval": 0.01}
    t = simulate(config)
    x0, radius = t.positions[0], config["params"]["pin_radius"]
    rim = np.abs(np.linalg.norm(x0, axis=1) - radius) < 1e-9 * radius
    assert rim.sum() >= 12
    offset = np.linalg.norm(t.positions[:, rim].mean(1), axis=1)
    assert offset.max() < 1e-4
    np.testing.assert_allclose(t.diagnostics["hole_offset"], offset, atol=1e-6)
    swing = t.diagnostics["swing"]
    assert swing.max() == pytest.approx(55.0, abs=3.0) and swing[-1] < swing.max() - 5.0


def test_the_scene_takes_a_given_plate_and_says_what_is_wrong_with_one(tmp_path):
    """``params.mesh`` straight to the scene: ``pivot`` picks the hole, ``hole_gap`` makes the pin smaller
    and rests the hole on it; a pivot in no hole, a gap as large as the hole, a plate without a hole and
    ``refine`` without a mesh are refused."""
    path, centre, _ = _plate(tmp_path)
    given = {"mesh": str(path), "pivot": centre.tolist(), "size": 0.12, "angle": 0.0, "body_size": 0.005,
             "mesh_size": 0.006}
    built = scene.build(scene.params({**given, "hole_gap": 0.001}))
    np.testing.assert_allclose(np.linalg.norm(built.obstacle_nodes, axis=1), HOLE - 0.001, rtol=1e-9)
    rim = np.abs(np.linalg.norm(built.x - [0.0, -0.001], axis=1) - HOLE) < 1e-9
    assert rim.sum() >= 12  # the hole's centre 1 mm below the pin, towards the centre of mass
    assert "mesh" not in scene.params({}) and "refine" not in scene.params({})  # drawn plates resolve as before
    with pytest.raises(ConfigError, match=re.escape("params.pivot [0.06, 0.018] lies in none of the 1 hole(s) of "
                                                    "params.mesh (the pin would fit at [[0.018, 0.018]]")):
        scene.build(scene.params({**given, "pivot": [0.06, 0.018]}))
    with pytest.raises(ConfigError, match=r"^params.hole_gap 0.011 m leaves no pin in the hole of params.mesh"):
        scene.build(scene.params({**given, "hole_gap": 0.011}))
    solid = tmp_path / "solid.msh"
    shapes.rectangle(0.12, 0.036, 0.005).write(solid)
    with pytest.raises(ConfigError, match="^params.mesh has no hole for the pin"):
        scene.build(scene.params({**given, "mesh": str(solid)}))
    with pytest.raises(ConfigError, match="^params.refine subdivides a given plate"):
        scene.params({"refine": True})


def test_bsms_infer_swings_a_users_plate_with_a_model_of_the_family(tmp_path):
    """``bsms infer RUN --mesh plate.msh --solver`` end to end: a tiny model trained 4 steps on 3 coarse
    trajectories of the family, rolled out on a plate of no split next to the solver's run of it."""
    from conftest import tiny_run_config

    from bsms.infer import main
    from bsms.run import load_config, prepare_dataset
    from bsms.training.trainer import Trainer
    from datagen.generate import generate

    dataset = tmp_path / "tiny_pendulum.yaml"
    dataset.write_text(f"extends: {QUICK}\ndataset: tiny_pendulum\nsplits: {{train: 2, valid: 1, test: 1, final: 0}}\n"
                       "output: {frames: 3, frame_interval: 0.01}\n")
    generate(dataset, out=tmp_path / "data", progress=False)
    config = load_config(tiny_run_config((dataset, tmp_path / "data"), tmp_path / "runs", name="pendulum",
                                         train={"steps": 4, "valid_every": 4, "checkpoint_every": 4}))
    Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    path, _, _ = _plate(tmp_path)
    out = tmp_path / "out"
    assert main([str(tmp_path / "runs" / "pendulum"), "--mesh", str(path), "--solver", "--steps", "3", "--quiet",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"] == "pendulum" and summary["finite"] and summary["steps"] == 3
    assert summary["params"]["mesh"] == str(path.resolve()) and summary["nodes"] == [237]
    assert (out / "solver.xdmf").is_file() and math.isfinite(summary["rel_all"])
