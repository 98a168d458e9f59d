"""graph.push: the penetration input puts a node back through the facets that swept over it."""

import numpy as np
import pytest
from test_penetration import CUBE_FACES, cube, square
from test_penetration import _scene as _penetration_scene

from bsms.config import ConfigError
from bsms.data import GraphOptions, NodeType, Scenario
from bsms.physics.penetration import Penetration, inside_outline
from datagen import shapes


def _scene():
    """The punch scene of test_penetration on a body meshed at 0.05, the punch 0.6 tall: a node
    pressed under it is inside, whatever its depth, and many lie nearer a side than the underside."""
    return _penetration_scene(spacing=0.05, top=1.55)


def _inside_punch(points, low_x, high_x, underside, top):
    """Where the input counts a node inside (the even-odd rule: a node on a side may count)."""
    a, b = square(low_x, underside, high_x, top)
    return inside_outline(points, a, b)


@pytest.mark.parametrize("reverse", [False, True])
def test_a_punch_pressed_straight_down_pushes_every_node_down_to_its_underside(reverse):
    _, rest, facets, n_body, punch = _scene()
    if reverse:  # the punch's outline the other way round: outward normals are found, not assumed
        facets = np.concatenate([facets[:4], facets[4:][::-1, ::-1]])
    coming = rest.copy()
    coming[punch] += [0.0, -0.12]  # underside at y = 0.83: nodes within 0.17 of the top are inside
    free = np.arange(len(rest)) < n_body
    nearest = Penetration(rest, facets, n_body)(rest, coming, free)
    leading = Penetration(rest, facets, n_body, push="leading")(rest, coming, free)
    x, y = rest[:n_body].T
    inside = _inside_punch(rest[:n_body], 0.4, 0.6, 0.83, 1.43)
    expected = np.zeros((n_body, 2))
    expected[inside, 1] = 0.83 - y[inside]
    np.testing.assert_allclose(leading[:n_body], expected, rtol=0, atol=1e-14)
    assert not leading[n_body:].any()
    sideways = inside & (np.abs(nearest[:n_body, 0]) > 0)  # the nearest point of these is across a side
    assert sideways.sum() >= 4, "the case the option is for: nodes nearer a side than the underside"


def test_a_punch_pressed_at_an_angle_pushes_through_its_underside_and_its_leading_side():
    _, rest, facets, n_body, punch = _scene()
    coming = rest.copy()
    coming[punch] += [0.05, -0.12]  # down and to the right: the right side leads as the underside does
    free = np.arange(len(rest)) < n_body
    out = Penetration(rest, facets, n_body, push="leading")(rest, coming, free)[:n_body]
    x, y = rest[:n_body].T
    inside = _inside_punch(rest[:n_body], 0.45, 0.65, 0.83, 1.43)
    down, right = y[inside] - 0.83, 0.65 - x[inside]
    expected = np.zeros((inside.sum(), 2))
    expected[:, 1] = np.where(down <= right, -down, 0.0)
    expected[:, 0] = np.where(down <= right, 0.0, right)
    assert (down > right).sum() >= 2 and (down <= right).sum() >= 2
    np.testing.assert_allclose(out[inside], expected, rtol=0, atol=1e-14)
    assert not out[~inside].any()


def test_an_obstacle_that_has_not_moved_is_the_nearest_point_as_before():
    _, rest, facets, n_body, punch = _scene()
    placed = rest.copy()
    placed[punch] += [0.0, -0.12]  # set down in the body at rest: no travel from where it stands
    free = np.arange(len(rest)) < n_body
    nearest = Penetration(placed, facets, n_body)(placed, placed, free)
    leading = Penetration(placed, facets, n_body, push="leading")(placed, placed, free)
    assert np.count_nonzero(np.abs(nearest).sum(1)) >= 8
    np.testing.assert_array_equal(leading, nearest)


def test_a_3d_punch_pressed_down_pushes_every_node_down_to_its_underside():
    body = shapes.box((1.0, 1.0, 1.0), 0.25)
    nodes = body.nodes - body.nodes.min(0)
    n_body = len(nodes)
    rest = np.concatenate([nodes, cube((-1, -1, -1), (2, 2, 2)), cube((0.3, 0.3, 0.9), (0.7, 0.7, 1.3))])
    facets = np.concatenate([CUBE_FACES + n_body, CUBE_FACES[:, ::-1] + n_body + 8])  # the punch's inward-wound
    coming = rest.copy()
    coming[n_body + 8:] += [0.0, 0.0, -0.35]  # underside at z = 0.55, top at 0.95
    free = np.arange(len(rest)) < n_body
    out = Penetration(rest, facets, n_body, push="leading")(rest, coming, free)[:n_body]
    x, y, z = nodes.T
    inside = (x > 0.3) & (x < 0.7) & (y > 0.3) & (y < 0.7) & (z > 0.55) & (z < 0.95)
    nearest = Penetration(rest, facets, n_body)(rest, coming, free)[:n_body]
    assert inside.sum() >= 4 and np.abs(nearest[inside][:, :2]).max() > 0  # some nearer a side
    expected = np.zeros_like(out)
    expected[inside, 2] = 0.55 - z[inside]
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-14)


def test_the_scenario_passes_the_option_on_and_bad_values_are_named():
    body, rest, facets, n_body, punch = _scene()
    options = GraphOptions(levels=2, from_rest=True, penetration=True, push="leading", obstacle_spacing=0.0)
    scenario = Scenario.build(body.__class__(rest[:n_body], body.cells), options, frame_dt=0.1,
                              node_type=np.full(n_body, NodeType.FREE), obstacle_nodes=rest[n_body:],
                              obstacle_facets=facets - n_body)
    assert scenario.penetration.push == "leading"
    velocity = np.zeros_like(scenario.rest_pos)
    velocity[n_body + 4:] = [0.0, -1.2]  # 0.12 down over the coming frame
    frame = scenario.frame(scenario.rest_pos, velocity)
    pushed = frame.nodes["penetration"][frame.nodes["scenario_nodes"] < n_body]
    assert (pushed[:, 1] < 0).sum() >= 8 and not pushed[:, 0].any()
    with pytest.raises(ConfigError, match=r"^config key 'graph.push' says how the penetration input puts a node "
                                          r"back; set 'graph.penetration: true' too, or leave 'graph.push' out$"):
        GraphOptions(push="leading").validate()
    with pytest.raises(ValueError, match=r"^graph.push must be one of nearest, leading, collider, got 'sideways'$"):
        Penetration(rest, facets, n_body, push="sideways")


def _collider_expected(points, low, high, travel):
    """The collider push of ``points`` inside a box punch spanning ``low``-``high`` moved by
    ``travel`` from rest: its nearest face's vector, no longer than the travel along that face's
    outward normal (0 where the face trails or runs along the travel)."""
    d = points.shape[1]
    depths = np.concatenate([points - low, high - points], 1)  # to the faces of outward normal -e_k, then +e_k
    normals = np.concatenate([-np.eye(d), np.eye(d)])
    face = depths.argmin(1)
    along = normals[face] @ np.asarray(travel, float)
    return normals[face] * np.clip(np.minimum(depths[np.arange(len(face)), face], along), 0.0, None)[:, None]


def test_the_collider_push_is_the_nearest_faces_cut_to_the_travel_along_it():
    """A wide punch pressed straight down: a node nearest its underside is pushed down by its
    depth, but never further than the punch travelled (the nodes the punch held at rest); a node
    nearest a side, which the side passed by, is not pushed -- as the solver's collider leaves it."""
    _, rest, facets, n_body, punch = _scene()
    rest[punch, 0] = np.where(rest[punch, 0] < 0.5, 0.2, 0.8)  # 0.2-0.8 wide
    coming = rest.copy()
    coming[punch] += [0.0, -0.12]  # from y = 0.95 (0.05 into the body at rest) to 0.83
    free = np.arange(len(rest)) < n_body
    out = Penetration(rest, facets, n_body, push="collider")(rest, coming, free)[:n_body]
    inside = _inside_punch(rest[:n_body], 0.2, 0.8, 0.83, 1.43)
    expected = _collider_expected(rest[:n_body][inside], [0.2, 0.83], [0.8, 1.43], [0.0, -0.12])
    down = rest[:n_body][inside, 1] - 0.83
    assert ((expected == 0).all(1).sum() >= 4 and np.isclose(expected[:, 1], -0.12).sum() >= 4
            and (down < 0.12).sum() >= 4), "every case: beside a side, cut to the travel, the whole depth"
    np.testing.assert_allclose(out[inside], expected, rtol=0, atol=1e-14)
    assert not out[~inside].any()


def test_the_collider_push_of_a_punch_pressed_at_an_angle_moves_nodes_by_its_sideways_travel():
    _, rest, facets, n_body, punch = _scene()
    coming = rest.copy()
    coming[punch] += [0.03, -0.12]  # the right side leads by 0.03, the left trails
    free = np.arange(len(rest)) < n_body
    out = Penetration(rest, facets, n_body, push="collider")(rest, coming, free)[:n_body]
    inside = _inside_punch(rest[:n_body], 0.43, 0.63, 0.83, 1.43)
    expected = _collider_expected(rest[:n_body][inside], [0.43, 0.83], [0.63, 1.43], [0.03, -0.12])
    assert np.isclose(expected[:, 0], 0.03).sum() >= 2 and (expected == 0).all(1).sum() >= 4
    np.testing.assert_allclose(out[inside], expected, rtol=0, atol=1e-14)
    assert not out[~inside].any()


def test_the_collider_push_of_an_obstacle_that_has_not_moved_is_the_nearest_point():
    _, rest, facets, n_body, punch = _scene()
    placed = rest.copy()
    placed[punch] += [0.0, -0.12]
    free = np.arange(len(rest)) < n_body
    nearest = Penetration(placed, facets, n_body)(placed, placed, free)
    np.testing.assert_array_equal(Penetration(placed, facets, n_body, push="collider")(placed, placed, free), nearest)


def test_the_collider_push_of_a_3d_punch_leaves_the_nodes_its_sides_passed_by():
    body = shapes.box((1.0, 1.0, 1.0), 0.25)
    nodes = body.nodes - body.nodes.min(0)
    n_body = len(nodes)
    rest = np.concatenate([nodes, cube((-1, -1, -1), (2, 2, 2)), cube((0.3, 0.3, 0.9), (0.7, 0.7, 1.3))])
    facets = np.concatenate([CUBE_FACES + n_body, CUBE_FACES[:, ::-1] + n_body + 8])
    coming = rest.copy()
    coming[n_body + 8:] += [0.0, 0.0, -0.25]  # underside at z = 0.65, top at 1.05
    free = np.arange(len(rest)) < n_body
    out = Penetration(rest, facets, n_body, push="collider")(rest, coming, free)[:n_body]
    x, y, z = nodes.T
    inside = (x > 0.3) & (x < 0.7) & (y > 0.3) & (y < 0.7) & (z > 0.65)
    expected = np.zeros_like(out)
    expected[inside] = _collider_expected(nodes[inside], [0.3, 0.3, 0.65], [0.7, 0.7, 1.05], [0.0, 0.0, -0.25])
    assert (expected[inside] == 0).all(1).sum() >= 4 and (expected[inside, 2] < 0).sum() >= 1
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-14)
