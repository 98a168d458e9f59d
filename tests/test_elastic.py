"""graph.elastic: the body's linear-elastic answer to the penetration loads, as a node input."""

import itertools

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from test_penetration import _scene

from bsms.config import ConfigError
from bsms.data import GraphOptions, NodeType, Scenario
from bsms.models.simulator import LearnedSimulator
from bsms.physics.elastic import HOLD, ElasticResponse, held_nodes, stiffness
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer


def grid_triangles(nx, ny, width=1.0, height=1.0):
    """A structured triangulation of [0, width] x [0, height], alternating diagonals."""
    x, y = np.meshgrid(np.linspace(0, width, nx + 1), np.linspace(0, height, ny + 1), indexing="ij")
    nodes = np.stack([x.ravel(), y.ravel()], 1)
    index = np.arange(len(nodes)).reshape(nx + 1, ny + 1)
    cells = []
    for i, j in itertools.product(range(nx), range(ny)):
        a, b, c, d = index[i, j], index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]
        cells += [[a, b, c], [a, c, d]] if (i + j) % 2 else [[a, b, d], [b, c, d]]
    return nodes, np.array(cells)


def kuhn_tetrahedra(n):
    """The unit cube cut into n^3 cells of 6 tetrahedra each (Kuhn's subdivision)."""
    g = np.linspace(0, 1, n + 1)
    nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    index = np.arange(len(nodes)).reshape(n + 1, n + 1, n + 1)
    cells = []
    for i, j, k in itertools.product(range(n), repeat=3):
        for order in itertools.permutations(range(3)):
            corner, path = np.array([i, j, k]), [index[i, j, k]]
            for axis in order:
                corner = corner.copy()
                corner[axis] += 1
                path.append(index[tuple(corner)])
            cells.append(path)
    return nodes, np.array(cells)


def _energy_density(strain, nu):
    lam, mu = nu / ((1 + nu) * (1 - 2 * nu)), 1 / (2 * (1 + nu))
    return mu * (strain * strain).sum() + 0.5 * lam * np.trace(strain) ** 2


@pytest.mark.parametrize("dim", [2, 3])
def test_the_stiffness_passes_the_patch_test_and_stores_the_closed_form_energy(dim):
    nodes, cells = grid_triangles(5, 4, 2.0, 1.5) if dim == 2 else kuhn_tetrahedra(3)
    nu = 0.3
    k = stiffness(nodes, cells, nu)
    assert abs(k - k.T).max() < 1e-13 * abs(k).max()
    rng = np.random.default_rng(0)
    gradient = rng.normal(size=(dim, dim))
    u = nodes @ gradient.T  # a linear field: constant strain
    forces = (k @ u.ravel()).reshape(-1, dim)
    boundary = np.any((nodes <= 1e-12) | (nodes >= nodes.max(0) - 1e-12), axis=1)
    assert np.abs(forces[~boundary]).max() < 1e-12 * np.abs(forces).max(), "interior nodes of a uniform strain are in balance"
    strain = 0.5 * (gradient + gradient.T)
    measure = np.prod(nodes.max(0))
    np.testing.assert_allclose(0.5 * u.ravel() @ k @ u.ravel(), measure * _energy_density(strain, nu), rtol=1e-12)
    for axis in range(dim):  # translations cost nothing
        shift = np.zeros_like(nodes)
        shift[:, axis] = 1.0
        assert np.abs(k @ shift.ravel()).max() < 1e-12 * abs(k).max()
    spin = np.zeros_like(nodes)  # nor does an infinitesimal rotation about the last axis
    spin[:, 0], spin[:, 1] = -nodes[:, 1], nodes[:, 0]
    assert np.abs(k @ spin.ravel()).max() < 1e-12 * abs(k).max()


def test_bad_materials_and_meshes_are_named():
    nodes, cells = grid_triangles(2, 2)
    with pytest.raises(ValueError, match=r"^graph.elastic needs a Poisson ratio in \[0, 0.5\), got nu = 0.5; "):
        stiffness(nodes, cells, 0.5)
    flat = nodes.copy()
    flat[:, 1] = 0.0
    with pytest.raises(ValueError, match=r"^graph.elastic: the body mesh has a degenerate cell"):
        stiffness(flat, cells, 0.3)
    body, rest, facets, n_body, _ = _scene()
    with pytest.raises(ValueError, match=r"^graph.elastic needs the material's Poisson ratio: the scene has no "
                                         r"numeric parameter 'nu' \(got None\)"):
        ElasticResponse(rest, facets, n_body, body.cells, None, 0.1)
    with pytest.raises(ValueError, match=r"^graph.elastic needs a simplex body mesh \(3-node cells in 2D\)"):
        ElasticResponse(rest, facets, n_body, np.zeros((1, 4), np.int64), 0.3, 0.1)


def _on_the_floor():
    """The 1 x 1 body of test_penetration's scene standing on its box's floor (y = -1), a punch
    0.4 wide and 0.3 tall over its top middle, 0.05 above it."""
    body, rest, facets, n_body, punch = _scene()
    rest = rest.copy()
    rest[:n_body, 1] -= 1.0
    rest[punch] = [[0.3, 0.05], [0.7, 0.05], [0.7, 0.35], [0.3, 0.35]]
    return body, rest, facets, n_body, punch


def test_the_body_is_held_where_it_touches_the_container():
    body, rest, facets, n_body, _ = _on_the_floor()
    edge = float(np.median(body.edge_lengths))
    held = held_nodes(rest, facets, n_body, HOLD * edge)
    y = rest[:n_body, 1]
    np.testing.assert_array_equal(held, np.flatnonzero(y <= -1.0 + HOLD * edge))
    assert np.isclose(y[held], -1.0).sum() >= 10, "the whole bottom row"
    floating = rest.copy()
    floating[:n_body, 1] += 0.5  # off the floor: nothing holds it
    assert len(held_nodes(floating, facets, n_body, HOLD * edge)) == 0


def _response(rest, facets, n_body, cells, push_along=(0.0, -0.02)):
    """An ElasticResponse of the scene, the push ``push_along`` on the body's top nodes under the
    punch, and its answer."""
    elastic = ElasticResponse(rest, facets, n_body, cells, 0.3, 0.1)
    x, y = rest[:n_body].T
    push = np.zeros_like(rest)
    push[:n_body][(y > -1e-9) & (x > 0.3) & (x < 0.7)] = push_along
    return elastic, push, elastic(push)


def test_the_answer_turns_with_the_scene():
    body, rest, facets, n_body, _ = _on_the_floor()
    _, push, out = _response(rest, facets, n_body, body.cells)
    turn = np.array([[0.0, -1.0], [1.0, 0.0]])  # 90 degrees: the floor becomes the right wall
    elastic = ElasticResponse(rest @ turn.T, facets, n_body, body.cells, 0.3, 0.1)
    np.testing.assert_array_equal(elastic.held, held_nodes(rest, facets, n_body, HOLD * 0.1))
    np.testing.assert_allclose(elastic(push @ turn.T), out @ turn.T, rtol=0, atol=1e-12)


def test_a_body_nothing_holds_follows_a_uniform_push_rigidly():
    body, rest, facets, n_body, _ = _scene()
    rest = rest.copy()
    rest[:n_body] += [0.0, 0.3]  # clear of every wall (the punch is not loaded here)
    elastic = ElasticResponse(rest, facets, n_body, body.cells, 0.3, 0.1)
    assert len(elastic.held) == 0
    push = np.zeros_like(rest)
    push[:n_body] = [0.01, -0.02]
    out = elastic(push)[:n_body]
    x = rest[:n_body] - rest[:n_body].mean(0)
    rigid = np.stack([np.tile([1.0, 0.0], (n_body, 1)), np.tile([0.0, 1.0], (n_body, 1)),
                      np.stack([-x[:, 1], x[:, 0]], 1)], -1).reshape(2 * n_body, 3)  # translations and a turn
    fit, *_ = np.linalg.lstsq(rigid, out.ravel(), rcond=None)
    assert np.abs(rigid @ fit - out.ravel()).max() < 1e-7 * np.abs(out).max(), "a rigid motion"
    np.testing.assert_allclose(fit[:2], push[0], rtol=5e-6)  # along the push (turned by the push's uneven moment)


def _scenario(**options):
    body, rest, facets, n_body, punch = _on_the_floor()
    options = GraphOptions(levels=2, from_rest=True, obstacle_spacing=0.0, contact_radius=1.5, **options)
    return Scenario.build(body.__class__(rest[:n_body], body.cells), options, frame_dt=0.1,
                          node_type=np.full(n_body, NodeType.FREE), obstacle_nodes=rest[n_body:],
                          obstacle_facets=facets - n_body, params={"nu": 0.3}), rest, facets, n_body, punch


def test_a_scenario_frame_carries_the_answer_to_its_penetration():
    scenario, rest, facets, n_body, punch = _scenario(penetration=True, elastic=True)
    velocity = np.zeros_like(scenario.rest_pos)
    velocity[punch] = [0.0, -1.2]
    frame = scenario.frame(scenario.rest_pos, velocity)
    nodes = frame.nodes["scenario_nodes"]
    expected = ElasticResponse(rest, facets, n_body, scenario.cells, 0.3, np.median(
        np.linalg.norm(np.diff(rest[scenario.edges[:, :2]], axis=1)[:, 0], axis=1)))
    full = np.zeros_like(rest)
    full[nodes] = frame.nodes["penetration"]
    np.testing.assert_allclose(frame.nodes["elastic"], expected(full)[nodes], rtol=0, atol=1e-15)
    assert np.abs(frame.nodes["elastic"]).max() > 0.01
    with pytest.raises(ConfigError, match=r"^config key 'graph.elastic' loads the body where the obstacles reach "
                                          r"into it; set 'graph.penetration: true' too"):
        GraphOptions(elastic=True).validate()


def test_a_mirrored_scenario_gets_the_mirrored_answer():
    scenario, rest, facets, n_body, punch = _scenario(penetration=True, elastic=True)
    flip = np.array([-1.0, 1.0])  # train.mirror's reflection: cells and facets reversed to keep their orientation
    mirror = Scenario.build(type(_scene()[0])(rest[:n_body] * flip, scenario.cells[:, ::-1].copy()), scenario.options,
                            frame_dt=0.1, node_type=np.full(n_body, NodeType.FREE), obstacle_nodes=rest[n_body:] * flip,
                            obstacle_facets=(facets - n_body)[:, ::-1].copy(), params={"nu": 0.3})
    velocity = np.zeros_like(rest)
    velocity[punch] = [0.0, -1.2]
    a = scenario.frame(scenario.rest_pos, velocity)
    b = mirror.frame(mirror.rest_pos, velocity)
    np.testing.assert_array_equal(a.nodes["scenario_nodes"], b.nodes["scenario_nodes"])
    np.testing.assert_allclose(b.nodes["elastic"], a.nodes["elastic"] * flip, rtol=0, atol=1e-12)


def test_the_model_reads_it_and_says_when_it_is_missing():
    model = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8, penetration=True, elastic=True)
    plain = LearnedSimulator("bsms_gnn", 2, n_levels=2, contact=True, latent=8, penetration=True)
    assert model.node_normalizer.total.shape[-1] == plain.node_normalizer.total.shape[-1] + 2
    scenario, *_ = _scenario(penetration=True)
    graph = scenario.graph(scenario.rest_pos, np.zeros_like(scenario.rest_pos))
    with pytest.raises(ValueError, match=r"^the model reads the body's elastic answer to the push \('elastic', "
                                         r"graph.elastic\), which this graph lacks"):
        model(graph)
    scenario, *_ = _scenario(penetration=True, elastic=True)
    assert torch.isfinite(model(scenario.graph(scenario.rest_pos, np.zeros_like(scenario.rest_pos)))).all()


def test_training_with_the_elastic_input_runs(tiny_dataset, tmp_path, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, graph={"penetration": True, "elastic": True},
                                         train={"steps": 4, "valid_every": 4}))
    summary = Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    assert np.isfinite(summary["loss"])


def test_a_3d_body_is_held_on_its_floor_and_answers_the_push():
    from test_penetration import CUBE_FACES, cube

    nodes, cells = kuhn_tetrahedra(3)  # the unit cube, its bottom face on the container's floor z = 0
    n_body = len(nodes)
    rest = np.concatenate([nodes, cube((-1.0, -1.0, 0.0), (2.0, 2.0, 2.0))])
    edge = 1.0 / 3
    elastic = ElasticResponse(rest, CUBE_FACES + n_body, n_body, cells, 0.25, edge)
    np.testing.assert_array_equal(elastic.held, np.flatnonzero(nodes[:, 2] <= HOLD * edge + 1e-12))
    assert len(elastic.held) == 32  # the two lowest layers of 4 x 4 nodes
    push = np.zeros_like(rest)
    top = np.flatnonzero((nodes[:, 2] == 1.0) & (np.abs(nodes[:, :2] - 0.5).max(1) < 0.2))
    push[top] = [0.0, 0.0, -0.01]
    out = elastic(push)
    assert not out[elastic.held].any() and not out[n_body:].any()
    assert (out[top, 2] < 0).all() and np.abs(out[:n_body]).max() == np.abs(out[top]).max()


