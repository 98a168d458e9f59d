"""benchmarks/press_convergence.py: its checks change the scene exactly as they say (no solver run)."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from datagen.scenes import get_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from press_convergence import CHECKS, SHIFTS, at_rest, finer_body  # noqa: E402

PARAMS = {"char": "J", "size": 0.1, "pose": "stable", "body_size": 0.004, "mesh_size": 0.0075}


@pytest.mark.parametrize("base", ["bonded", "clamped"])
def test_finer_mesh_and_body_refines_the_stored_body_where_it_stands(base):
    """The stored body, subdivided and given inline, is set down exactly where the scene had set it
    (its nodes first), on a background twice as fine."""
    scene = get_scene("press")
    params = {**PARAMS, "base": base}
    body = scene.build(scene.params(params)).body
    config = {"params": dict(params)}
    finer_body(config, SimpleNamespace(mesh=body))
    assert "char" not in config["params"] and config["params"]["mesh_size"] == 0.00375
    fine = scene.build(scene.params(config["params"])).body
    assert fine.n_nodes == body.n_nodes + len(body.edges)
    np.testing.assert_allclose(fine.nodes[: body.n_nodes], body.nodes, rtol=0, atol=1e-15)


@pytest.mark.parametrize(("base", "axis"), [("bonded", 0), ("clamped", 1)])
def test_grid_shift_moves_the_body_and_its_indenter_half_a_cell(base, axis):
    scene = get_scene("press")
    params = {**PARAMS, "base": base}
    before = scene.build(scene.params(params))
    config = {"params": dict(params, box=[0.0, 0.0, 0.24, 0.2])}
    CHECKS["grid shift"](config, None)
    after = scene.build(scene.params(config["params"]))
    shift = SHIFTS["grid shift"](config)
    assert shift[axis] == 0.00375 and shift[1 - axis] == 0.0
    np.testing.assert_allclose(after.body.nodes - shift, before.body.nodes, rtol=0, atol=1e-15)
    indenter = slice(-after.collider_nodes[0], None)
    np.testing.assert_allclose(after.obstacle_nodes[indenter] - shift, before.obstacle_nodes[indenter], rtol=0,
                               atol=1e-15)
    assert (after.domain.nodes.min(0) == before.domain.nodes.min(0)).all()  # the grid starts where it did


THIN = {**PARAMS, "body_size": 0.01, "min_nodes": 300, "grid_ratio": 1.5}  # a J refined below body_size


@pytest.mark.parametrize("name", ["finer mesh", "finer mesh and body"])
def test_finer_checks_halve_a_background_that_follows_the_body(name):
    """With params.grid_ratio the background is finer than mesh_size for a thin body: both finer
    checks halve the spacing the data ran with, not mesh_size alone."""
    scene = get_scene("press")
    before = scene.build(scene.params(THIN))
    assert before.grid_spacing < THIN["mesh_size"] / 2  # so halving mesh_size alone would change nothing
    config = {"params": dict(THIN)}
    CHECKS[name](config, SimpleNamespace(mesh=before.body))
    after = scene.build(scene.params(config["params"]))
    assert after.grid_spacing == pytest.approx(before.grid_spacing / 2, rel=1e-9)


def test_grid_shift_is_half_the_cell_the_body_had():
    scene = get_scene("press")
    params = dict(THIN, box=[0.0, 0.0, 0.24, 0.2])
    before = scene.build(scene.params(params))
    config = {"params": dict(params)}
    CHECKS["grid shift"](config, None)
    after = scene.build(scene.params(config["params"]))
    shift = SHIFTS["grid shift"](config)
    assert shift[0] == pytest.approx(before.grid_spacing / 2, rel=1e-9) and shift[1] == 0.0
    np.testing.assert_allclose(after.body.nodes - shift, before.body.nodes, rtol=0, atol=1e-15)
    assert after.grid_spacing == pytest.approx(before.grid_spacing, rel=1e-12)


def test_at_rest_is_the_rms_displacement_over_free_nodes_and_frames_relative_to_the_body_size():
    """A 3 x 4 rectangle's nodes: frame 0 at rest (not a step), frame 1 moved by (0.3, 0.4) (|d| = 0.5),
    frame 2 by (0.6, 0.8) (|d| = 1), a fixed node whose motion does not count: sqrt((0.25 + 1) / 2)
    over the diagonal 5."""
    nodes = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0], [0.0, 4.0]])
    positions = np.stack([nodes, nodes + [0.3, 0.4], nodes + [0.6, 0.8]])
    positions[1:, 3] += 10.0  # node 3 is not free
    node_type = np.array([0, 0, 0, 1])
    trajectory = SimpleNamespace(mesh=SimpleNamespace(nodes=nodes), positions=positions, node_type=node_type)
    assert at_rest(positions, trajectory) == pytest.approx(np.sqrt(1.25 / 2) / 5.0, rel=1e-12)
