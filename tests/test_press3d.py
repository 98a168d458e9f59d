"""The 3D press: its meshers (datagen.shapes3d), its scene (datagen.scenes.press3d) and family."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from datagen import shapes3d, simulate
from datagen.config import ConfigError
from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.families import get_family
from datagen.scenes import get_scene
from datagen.scenes.solids import body_mesh

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "datasets"
scene = get_scene("press3d")
family = get_family("press3d")
FAST = {"E": 1e5, "nodes": 200, "mesh_size": 0.02, "size": 0.12}


def signed_volumes(mesh) -> np.ndarray:
    p = mesh.nodes[mesh.cells]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6


def test_an_extruded_outline_holds_its_area_times_its_depth():
    outer = [[0, 0], [1.0, 0], [1.2, 0.7], [0.3, 0.9]]
    hole = [[0.4, 0.3], [0.7, 0.3], [0.6, 0.5]]
    mesh = shapes3d.extrude(outer, [hole], depth=0.35, size=0.1)
    x, y = np.asarray(outer).T
    hx, hy = np.asarray(hole).T
    area = 0.5 * abs(x @ np.roll(y, -1) - y @ np.roll(x, -1)) - 0.5 * abs(hx @ np.roll(hy, -1) - hy @ np.roll(hx, -1))
    volumes = signed_volumes(mesh)
    assert volumes.min() > 0, "every tetrahedron positively oriented"
    assert volumes.sum() == pytest.approx(area * 0.35, rel=1e-12)
    np.testing.assert_allclose(np.ptp(mesh.nodes, axis=0), [1.2, 0.9, 0.35], atol=1e-12)


@pytest.mark.parametrize(("make", "volume"), [
    (lambda: shapes3d.holed_block([1.0, 0.6, 0.5], 0.15, 0.08, axis=0), 0.3 - math.pi * 0.15**2 * 1.0),
    (lambda: shapes3d.slotted_block([1.0, 0.6, 0.5], 0.2, 0.4, 0.08, axis=1),  # a 0.4 x 0.2 slot in the 0.5 x 1 face
     0.3 - (0.2 * 0.2 + math.pi * 0.01) * 0.6),
    (lambda: shapes3d.cylinder(0.3, 1.0, 0.1), math.pi * 0.09),
    (lambda: shapes3d.extrude(shapes3d.section_outline("T", 1.0, 0.8, 0.2, 0.25), depth=0.5, size=0.1),
     (0.2 + 0.25 * 0.6) * 0.5),
])
def test_solids_are_positively_oriented_with_their_volume(make, volume):
    mesh = make()
    volumes = signed_volumes(mesh)
    assert volumes.min() > 0
    assert volumes.sum() == pytest.approx(volume, rel=0.01)  # curved faces are faceted


def test_a_hole_goes_through_the_block_along_its_axis():
    mesh = shapes3d.holed_block([1.0, 0.6, 0.5], 0.15, 0.08, axis=0)
    np.testing.assert_allclose(np.ptp(mesh.nodes, axis=0), [1.0, 0.6, 0.5], atol=1e-12)
    r = np.hypot(mesh.nodes[:, 1] - 0.3, mesh.nodes[:, 2] - 0.25)
    assert r.min() == pytest.approx(0.15, rel=1e-6)  # no node inside the hole, along the whole x axis
    on_hole = np.isclose(r, 0.15, rtol=1e-6)
    assert np.ptp(mesh.nodes[on_hole, 0]) == pytest.approx(1.0)


def test_meshers_are_deterministic():
    for make in (lambda: shapes3d.extrude_rings(shapes3d.glyph_rings("R", 0.08), 0.3, 0.08),
                 lambda: shapes3d.slotted_block([1.0, 0.6, 0.5], 0.2, 0.5, 0.1)):
        a, b = make(), make()
        np.testing.assert_array_equal(a.nodes, b.nodes)
        np.testing.assert_array_equal(a.cells, b.cells)


def test_section_outlines_and_bad_arguments():
    assert shapes3d.section_outline("L", 1.0, 0.8, 0.2, 0.3)[:3] == [[0.0, 0.0], [1.0, 0.0], [1.0, 0.2]]
    with pytest.raises(ValueError, match="section kind must be 'L' or 'T'"):
        shapes3d.section_outline("U", 1.0, 0.8, 0.2, 0.3)
    with pytest.raises(ValueError, match="does not fit"):
        shapes3d.holed_block([1.0, 0.6, 0.5], 0.3, 0.1)
    with pytest.raises(ValueError, match="extrusion depth must be a positive number"):
        shapes3d.extrude([[0, 0], [1, 0], [0, 1]], depth=0.0)


@pytest.mark.parametrize(("given", "nodes"), [
    ({"char": "W"}, 1200), ({"body": "block", "feature": "slot", "feature_axis": 1}, 3000), ({"body": "cylinder"}, 1000)])
def test_bodies_get_about_the_nodes_asked_for(given, nodes):
    mesh = body_mesh(scene.params({**given, "nodes": nodes}))
    assert 0.8 * nodes <= mesh.n_nodes <= 1.2 * nodes
    assert signed_volumes(mesh).min() > 0


def test_a_toppling_profile_is_set_on_its_most_stable_side():
    """A J stands on its hook no better than the 2D press's: it is laid down, as pose 'stable' says."""
    laid = body_mesh(scene.params({**FAST, "char": "J"}))
    upright = body_mesh(scene.params({**FAST, "char": "J", "pose": "upright"}))
    assert np.ptp(laid.nodes[:, 1]) < 0.5 * np.ptp(upright.nodes[:, 1])
    assert np.ptp(laid.nodes[:, :2], axis=0).max() == pytest.approx(0.12, rel=1e-9)


@pytest.mark.parametrize(("shape", "sizes"), [("sphere", [0.02]), ("box", [0.02, 0.01, 0.015]), ("bar", [0.01, 0.01])])
def test_the_indenter_starts_gap_above_the_body_and_comes_back(shape, sizes):
    built = scene.build(scene.params({**FAST, "body": "block", "indenter": shape, "indenter_size": sizes,
                                      "indenter_x": 0.01, "indenter_z": -0.005, "gap": 0.003, "angle": 10.0,
                                      "azimuth": 90.0, "speed": 0.05, "press_time": 0.2}))
    collider = built.colliders[0]
    nodes = torch.tensor(built.body.nodes)
    lifted, _ = collider.signed_distance(nodes + torch.tensor([0.0, 0.003, 0.0], dtype=nodes.dtype), 0.0)
    assert float(lifted.min()) == pytest.approx(0.0, abs=1e-12)
    start, bottom = collider.path.position(0.0), collider.path.position(0.2)
    np.testing.assert_allclose(bottom - start, 0.01 * np.array([0.0, -math.cos(math.radians(10)),
                                                                math.sin(math.radians(10))]), atol=1e-15)
    np.testing.assert_allclose(collider.path.position(0.4), start, atol=1e-15)
    if shape == "bar":  # lying across the whole body along z
        assert collider.shape == "box" and 2 * collider.size[2] > np.ptp(built.body.nodes[:, 2])
    assert built.body.nodes[:, 1].min() == 0.0
    np.testing.assert_allclose((built.body.nodes.min(0) + built.body.nodes.max(0))[[0, 2]] / 2, [0.09, 0.09])


def test_a_bonded_body_deforms_under_the_indenter_and_keeps_its_base():
    t = simulate({"scene": "press3d", "params": {**FAST, "body": "cylinder", "indenter": "box",
                                                 "indenter_size": [0.04, 0.01, 0.04], "gap": 0.0, "speed": 0.3},
                  "solver": {"cfl": 1.0}, "output": {"frames": 3, "frame_interval": 0.01}})
    moved = np.linalg.norm(t.positions[-1] - t.positions[0], axis=1)
    base = t.mesh.nodes[:, 1] < 1e-9
    top = t.mesh.nodes[:, 1] > t.mesh.nodes[:, 1].max() - 1e-9
    assert moved[top].mean() > 1e-3  # pushed down about as far as the punch went (9 mm)
    assert moved[base].max() < 0.05 * moved[top].mean()  # glued to the floor


def test_splits_hold_their_kinds_and_test_and_final_kinds_are_never_trained_on():
    d = load_dataset_config(CONFIGS / "press3d.yaml")
    drawn = {split: [trajectory_config(d, split, k)["params"] for k in range(60)] for split in ("train", "valid", "test",
                                                                                                   "final")}
    kinds = {split: {p["kind"] for p in bodies} for split, bodies in drawn.items()}
    assert kinds["train"] == kinds["valid"] == {"letter", "holed_block", "l_section"}
    assert kinds["test"] == {"letter", "polygon", "t_section", "cylinder"}
    assert {"digit", "slotted_block", "stroke"} <= kinds["final"] <= kinds["test"] | {"digit", "slotted_block", "stroke"}
    chars = {split: {p["char"] for p in bodies if p["kind"] == "letter"} for split, bodies in drawn.items()}
    assert chars["train"] <= set("ABCDEFHKLMNPRVWXYZ") and chars["test"] | chars["final"] <= set("GJQSU")
    assert {p["char"] for p in drawn["final"] if p["kind"] == "digit"} <= set("0123456789")
    novel = sum(p["kind"] in ("digit", "slotted_block", "stroke") for p in drawn["final"])
    assert 18 <= novel <= 42
    for bodies in drawn.values():
        assert all(1e7 <= p["E"] <= 2e8 and 1500 <= p["nodes"] <= 3000 for p in bodies)


@pytest.mark.parametrize(("ranges", "message"), [
    ({"test_kinds": ["polygon", "holed_block"]}, r"ranges.train_kinds and ranges.test_kinds share \['holed_block'\]"),
    ({"final_kinds": ["digit", "cylinder"]}, r"ranges.test_kinds and ranges.final_kinds share \['cylinder'\]"),
    ({"train_kinds": ["letter", "sphere"]}, "ranges.train_kinds must be a non-empty list of letter, digit"),
    ({"test_chars": "GA"}, "ranges.test_chars shares 'A' with ranges.train_chars"),
    ({"indenters": ["wedge"]}, "ranges.indenters may hold"),
])
def test_bad_ranges_name_the_key(ranges, message):
    d = load_dataset_config(CONFIGS / "press3d.yaml")
    with pytest.raises(ConfigError, match=message):
        for split in ("train", "test", "final"):
            for k in range(8):
                trajectory_config({**d, "ranges": {**d["ranges"], **ranges}}, split, k)


def test_bad_parameters_name_the_key():
    with pytest.raises(ConfigError, match=r"params.indenter_size must list 3 positive length\(s\) for a box"):
        scene.params({"indenter": "box", "indenter_size": [0.01]})
    with pytest.raises(ConfigError, match="params.box must be a 3D box"):
        scene.params({"box": [0.0, 0.0, 1.0, 1.0]})
    with pytest.raises(ConfigError, match="params.block must be 3 positive fractions of params.size"):
        body_mesh(scene.params({"body": "block", "block": [1.0, 0.5]}))
    with pytest.raises(ConfigError, match="params: the block body cannot be meshed: holed_block: a hole"):
        body_mesh(scene.params({"body": "block", "hole": 0.4}))
    with pytest.raises(ConfigError, match="params.size: the body spans"):
        scene.build(scene.params({**FAST, "size": 0.2}))
    with pytest.raises(ConfigError, match="family 'press3d' presses one body"):  # placement: test_press3d_infer.py
        family.place([], {}, None)
