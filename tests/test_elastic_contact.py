"""ElasticResponse.constrained: the body's answer as a frictionless contact makes it (graph.elastic)."""

import numpy as np
import pytest
from scipy.optimize import nnls
from test_elastic import _on_the_floor, _scenario, kuhn_tetrahedra

from bsms.physics import elastic as elastic_module
from bsms.physics.elastic import REGULARISATION, ElasticResponse


def _top_push(rest, n_body, depth):
    """Every node of the body's top row (y = 0) pushed straight down by ``depth`` (an array over x, or a number)."""
    push = np.zeros_like(rest)
    x, y = rest[:n_body].T
    top = np.flatnonzero(np.isclose(y, 0.0))
    push[top, 1] = -(depth(x[top]) if callable(depth) else depth)
    return push, top


def _contact_forces(elastic, u):
    """(n_body, d) the forces on the free nodes (0 where held): K u with the solver's regularising shift."""
    free = elastic.free_dofs
    k = elastic.stiffness[free][:, free]
    forces = np.zeros(elastic.dim * elastic.n_body)
    forces[free] = k @ u[: elastic.n_body].ravel()[free] + REGULARISATION * k.diagonal().mean() * u[: elastic.n_body].ravel()[free]
    return forces.reshape(elastic.n_body, elastic.dim)


def test_a_column_pressed_evenly_compresses_uniformly_in_closed_form():
    # nu = 0: a column held at its base and pushed down by d along its whole top is in uniaxial
    # strain, u = (0, -d (y + 1)) (y from -1 at the floor to 0 at the top), which P1 cells
    # represent exactly (up to the solver's regularising shift, 1e-9 of the stiffness); the pushed
    # nodes may slide sideways, and nothing makes them
    body, rest, facets, n_body, _ = _on_the_floor()
    elastic = ElasticResponse(rest, facets, n_body, body.cells, 0.0, 0.1, hold=0.05)
    push, top = _top_push(rest, n_body, 0.01)
    out = elastic.constrained(push)
    y = rest[:n_body, 1]
    np.testing.assert_allclose(out[:n_body, 1], -0.01 * (y + 1.0), rtol=0, atol=1e-9)
    np.testing.assert_allclose(out[:n_body, 0], 0.0, rtol=0, atol=1e-10)
    np.testing.assert_allclose(out[top, 1], -0.01, rtol=1e-14)  # the constraint itself: to round-off
    assert not out[n_body:].any()
    np.testing.assert_allclose(elastic.constrained(3 * push), 3 * out, rtol=0, atol=1e-15)  # linear while all push


def test_the_answer_meets_the_contact_conditions():
    # a wedge-shaped push (deep on the left, none on the right) on a Poisson body: every pushed
    # node is moved along its push by at least its depth; the obstacle acts only where the node
    # sits exactly on it, only pushing, only along the push (frictionless); elsewhere no force
    body, rest, facets, n_body, _ = _on_the_floor()
    elastic = ElasticResponse(rest, facets, n_body, body.cells, 0.3, 0.1)
    push, top = _top_push(rest, n_body, lambda x: 0.02 * (1.0 - x) ** 3 + 1e-4)
    out = elastic.constrained(push)[:n_body]
    depth = -push[top, 1]
    reach = -out[top, 1]
    assert (reach >= depth * (1 - 1e-9)).all()
    forces = _contact_forces(elastic, out)
    scale = np.abs(forces).max()
    on = np.abs(reach - depth) <= 1e-12 + 1e-9 * depth
    assert 3 <= on.sum() < len(top), "some of the top row is held on the obstacle, some released"
    assert (forces[top[on], 1] <= 1e-12 * scale).all(), "the obstacle pushes down, never pulls"
    np.testing.assert_allclose(forces[top, 0], 0.0, atol=1e-10 * scale)  # frictionless: no force across the push
    np.testing.assert_allclose(forces[top[~on]], 0.0, atol=1e-10 * scale)  # released nodes: no force
    others = np.setdiff1d(np.arange(n_body), np.concatenate([top, elastic.held]))
    np.testing.assert_allclose(forces[others], 0.0, atol=1e-10 * scale)  # the rest is in balance


def test_the_answer_needs_no_push_and_gives_up_by_name(monkeypatch):
    body, rest, facets, n_body, _ = _on_the_floor()
    elastic = ElasticResponse(rest, facets, n_body, body.cells, 0.3, 0.1)
    assert not elastic.constrained(np.zeros_like(rest)).any()
    push, _ = _top_push(rest, n_body, lambda x: 0.02 * (1.0 - x) ** 3 + 1e-4)
    monkeypatch.setattr(elastic_module, "ACTIVE_SET_TRIES", 1)
    monkeypatch.setattr(elastic_module, "CONTACT_ITERATIONS", 0.01)
    with pytest.raises(RuntimeError, match=r"^graph.elastic: the contact answer did not settle which of 11 pushed "
                                           r"nodes push in 1 iterations$"):
        elastic.constrained(push)


def test_guessed_active_sets_give_the_least_squares_answer_and_the_next_frame_starts_from_it(monkeypatch):
    body, rest, facets, n_body, _ = _on_the_floor()
    push, _ = _top_push(rest, n_body, lambda x: 0.02 * (1.0 - x) ** 3 + 1e-4)
    monkeypatch.setattr(elastic_module, "ACTIVE_SET_TRIES", 0)  # straight to non-negative least squares
    exact = ElasticResponse(rest, facets, n_body, body.cells, 0.3, 0.1).constrained(push)
    monkeypatch.undo()
    calls = []
    monkeypatch.setattr(elastic_module, "nnls", lambda *a, **k: calls.append(1) or nnls(*a, **k))
    elastic = ElasticResponse(rest, facets, n_body, body.cells, 0.3, 0.1)
    first = elastic.constrained(push)
    np.testing.assert_allclose(first, exact, rtol=0, atol=1e-14)
    released = elastic._released.copy()
    assert released.sum() >= 3
    np.testing.assert_array_equal(elastic.constrained(push), first)  # the last frame's guess is right at once
    np.testing.assert_array_equal(elastic._released, released)
    assert not calls, "the active-set guesses settled it"


def test_a_3d_body_pressed_meets_its_push_and_is_in_balance_elsewhere():
    from test_penetration import CUBE_FACES, cube

    nodes, cells = kuhn_tetrahedra(3)  # the unit cube on the container's floor z = 0
    n_body = len(nodes)
    rest = np.concatenate([nodes, cube((-1.0, -1.0, 0.0), (2.0, 2.0, 2.0))])
    elastic = ElasticResponse(rest, CUBE_FACES + n_body, n_body, cells, 0.25, 1.0 / 3)
    push = np.zeros_like(rest)
    top = np.flatnonzero((nodes[:, 2] == 1.0) & (np.abs(nodes[:, :2] - 0.5).max(1) < 0.2))
    push[top] = [0.0, 0.0, -0.01]
    out = elastic.constrained(push)
    np.testing.assert_allclose(out[top, 2], -0.01, rtol=1e-13)
    assert not out[elastic.held].any() and not out[n_body:].any()
    forces = _contact_forces(elastic, out)
    scale = np.abs(forces).max()
    assert (forces[top, 2] < 0).all()  # the punch pushes every node it reaches
    np.testing.assert_allclose(forces[top, :2], 0.0, atol=1e-12 * scale)
    others = np.setdiff1d(np.arange(n_body), np.concatenate([top, elastic.held]))
    np.testing.assert_allclose(forces[others], 0.0, atol=1e-12 * scale)


def _pressed(scenario, punch, depth):
    velocity = np.zeros_like(scenario.rest_pos)
    velocity[punch] = [0.0, -10 * depth]  # the punch's coming step (it starts 0.05 above the body)
    return scenario.rest_pos, velocity


def test_graph_elastic_is_the_contact_answer_in_every_frame():
    scenario, rest, facets, n_body, punch = _scenario(penetration=True, elastic=True)
    states = [_pressed(scenario, punch, depth) for depth in (0.0, 0.1, 0.2)]
    solves = []
    factor = scenario.elastic._solver()
    scenario.elastic._factor = type("Counted", (), {"solve": lambda self, b: solves.append(b.shape[1]) or factor.solve(b)})()
    together = scenario.frames(states)
    assert len(solves) == 1 and solves[0] == 2 * scenario.elastic._count, "every pushed node solved for at once"
    alone = [scenario.frame(*state) for state in states]
    for a, b in zip(together, alone, strict=True):
        nodes = a.nodes["scenario_nodes"]
        full = np.zeros_like(rest)
        full[nodes] = a.nodes["penetration"]
        np.testing.assert_array_equal(a.nodes["elastic"], scenario.elastic.constrained(full)[nodes])
        np.testing.assert_array_equal(a.nodes["elastic"], b.nodes["elastic"])
    deepest = together[-1].nodes
    loaded = np.any(deepest["penetration"] != 0, axis=1)
    assert loaded.sum() >= 3 and not together[0].nodes["elastic"].any()
    reach = (deepest["elastic"][loaded] * deepest["penetration"][loaded]).sum(1)
    assert (reach >= (deepest["penetration"][loaded] ** 2).sum(1) * (1 - 1e-9)).all()  # every push met


def test_a_rollout_solves_for_each_pushed_node_once_and_training_keeps_nothing():
    scenario, rest, facets, n_body, punch = _scenario(penetration=True, elastic=True)
    elastic = scenario.elastic
    solves = []
    factor = elastic._solver()
    elastic._factor = type("Counted", (), {"solve": lambda self, b: solves.append(b.shape[1]) or factor.solve(b)})()
    frames = [scenario.frame(*_pressed(scenario, punch, depth)) for depth in (0.1, 0.15, 0.2, 0.2, 0.15)]
    # the first two depths reach 4 new nodes each (two unit forces per node in 2D), the rest none
    assert solves == [8, 8] and elastic._count == 8
    elastic._factor, elastic.cache_limit = factor, 0
    elastic._forget()
    for depth, cached in zip((0.1, 0.15, 0.2, 0.2, 0.15), frames, strict=True):
        alone = scenario.frame(*_pressed(scenario, punch, depth)).nodes["elastic"]
        np.testing.assert_allclose(alone, cached.nodes["elastic"], rtol=0, atol=1e-15)
    assert elastic._count == 0
    elastic.cache_limit = 6  # room for the first depth's 4 nodes, not for the next 4: solved alone, not kept
    for depth, cached in zip((0.1, 0.15), frames, strict=False):
        alone = scenario.frame(*_pressed(scenario, punch, depth)).nodes["elastic"]
        np.testing.assert_allclose(alone, cached.nodes["elastic"], rtol=0, atol=1e-15)
    assert elastic._count == 4
