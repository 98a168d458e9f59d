"""Transitions between bi-stride levels (bsms.graph.transitions, thesis §4.3.2)."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from graph_meshes import meshes, path_graph, shape_mesh
from hypothesis import given, settings
from hypothesis import strategies as st

from bsms.graph import SEEDINGS, Transition, bistride_levels

# float64 results of sums of O(1) weights: what rounding leaves (measured: 9e-16 on sums that
# should be 1, 1e-15 relative after a chain of levels); hand-computed fractions: 2e-16
ROUNDOFF = 5e-15
ULPS = 1e-15


def dense(transition: Transition) -> np.ndarray:
    return transition.matrix().toarray()


@given(meshes(), st.sampled_from(SEEDINGS), st.booleans())
@settings(max_examples=20, deadline=None)
def test_weights_are_non_negative_averages_and_constants_survive(mesh, seeding, self_loops):
    hierarchy = bistride_levels(mesh, seeding=seeding, self_loops=self_loops)
    constant = np.full((mesh.n_nodes, 2), [3.5, -1.0])
    values = constant
    for level in hierarchy.levels[1:]:
        for operator in (level.down, level.up):
            assert (operator.weights > 0).all()
            np.testing.assert_allclose(np.bincount(operator.rows, operator.weights, operator.shape[0]), 1.0,
                                       rtol=0, atol=ROUNDOFF)
            assert np.array_equal(operator.rows, np.sort(operator.rows))
        values = level.down.apply(values)
        np.testing.assert_allclose(values, constant[: level.n_nodes], rtol=2 * ROUNDOFF)
    for level in reversed(hierarchy.levels[1:]):
        values = level.up.apply(values)
    np.testing.assert_allclose(values, constant, rtol=ROUNDOFF)


@given(meshes(max_parts=2))
@settings(max_examples=10, deadline=None)
def test_down_reads_only_closed_neighbourhoods_and_up_is_its_transpose(mesh):
    hierarchy = bistride_levels(mesh, levels=3)
    for finer, coarse in pairwise(hierarchy.levels):
        closed = finer.adjacency.toarray() + np.eye(finer.n_nodes)
        down, up = dense(coarse.down), dense(coarse.up)
        assert np.array_equal(down > 0, closed[coarse.kept] > 0)
        # up is C^T renormalised per fine node
        np.testing.assert_allclose(up, down.T / down.T.sum(axis=1, keepdims=True), rtol=ROUNDOFF, atol=0)


def test_six_node_path_by_hand():
    edges, positions = path_graph(6)  # 0 - 1 - 2 - 3 - 4 - 5 at x = 0..5
    hierarchy = bistride_levels(edges, positions, levels=3, seeding="close_center")
    level1, level2 = hierarchy.levels[1], hierarchy.levels[2]
    # centroid x = 2.5: nodes 2 and 3 tie, the lower index wins; BFS depths 2 1 0 1 2 3,
    # three even and three odd nodes: the tie keeps the even frontiers.
    assert level1.seeds.tolist() == [2]
    assert level1.kept.tolist() == [0, 2, 4]
    assert level1.edge_index.tolist() == [[0, 1, 1, 2], [1, 0, 2, 1]]
    # T = A + I: degrees 2 3 3 3 3 2, shares w/deg = 1/2 1/3 1/3 1/3 1/3 1/2
    np.testing.assert_allclose(dense(level1.down), [
        [3 / 5, 2 / 5, 0, 0, 0, 0],
        [0, 1 / 3, 1 / 3, 1 / 3, 0, 0],
        [0, 0, 0, 2 / 7, 2 / 7, 3 / 7],
    ], rtol=ULPS)
    np.testing.assert_allclose(level1.node_weights, [5 / 6, 1, 7 / 6], rtol=ULPS)
    np.testing.assert_allclose(dense(level1.up), [
        [1, 0, 0],
        [6 / 11, 5 / 11, 0],
        [0, 1, 0],
        [0, 7 / 13, 6 / 13],
        [0, 0, 1],
        [0, 0, 1],
    ], rtol=ULPS)
    # level 2: the path 0 - 1 - 2 of nodes at x = 0, 2, 4 keeps its middle node; the weights
    # 5/6 1 7/6 spread over degrees 2 3 2 give shares 5/12 4/12 7/12.
    assert level2.kept.tolist() == [1]
    np.testing.assert_allclose(dense(level2.down), [[5 / 16, 4 / 16, 7 / 16]], rtol=ULPS)
    np.testing.assert_allclose(level2.node_weights, [4 / 3], rtol=ULPS)
    np.testing.assert_allclose(dense(level2.up), [[1], [1], [1]], rtol=ULPS)


def test_six_node_path_by_hand_without_self_loops():
    edges, positions = path_graph(6)
    level1 = bistride_levels(edges, positions, levels=2, seeding="close_center", self_loops=False).levels[1]
    # T = A: degrees 1 2 2 2 2 1, shares 1 1/2 1/2 1/2 1/2 1
    np.testing.assert_allclose(dense(level1.down), [
        [0, 1, 0, 0, 0, 0],
        [0, 1 / 2, 0, 1 / 2, 0, 0],
        [0, 0, 0, 1 / 3, 0, 2 / 3],
    ], rtol=ULPS)
    np.testing.assert_allclose(level1.node_weights, [1 / 2, 1, 3 / 2], rtol=ULPS)
    # kept nodes 0, 2, 4 have no kept neighbour: they take back their own coarse value
    np.testing.assert_allclose(dense(level1.up), [
        [1, 0, 0],
        [2 / 3, 1 / 3, 0],
        [0, 1, 0],
        [0, 3 / 5, 2 / 5],
        [0, 0, 1],
        [0, 0, 1],
    ], rtol=ULPS)


def test_self_loops_give_the_smaller_round_trip_error():
    mesh = shape_mesh("square with holes", 0.06)
    x, y = mesh.nodes.T
    field = np.sin(4 * x) * np.cos(5 * y) + x * y
    errors = {}
    for self_loops in (True, False):
        level = bistride_levels(mesh, levels=2, self_loops=self_loops).levels[1]
        errors[self_loops] = np.linalg.norm(level.up.apply(level.down.apply(field)) - field)
    assert errors[True] < errors[False]


def test_apply_checks_the_row_count():
    level = bistride_levels(shape_mesh("disk", 0.14), levels=2).levels[1]
    with pytest.raises(ValueError, match="rows"):
        level.down.apply(np.ones(level.n_nodes))
    assert level.down.apply(np.ones((level.down.shape[1], 3, 2))).shape == (level.n_nodes, 3, 2)
