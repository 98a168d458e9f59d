"""Lean obstacles (bsms.graph.frames, bsms.graph.obstacles, Scenario.graph): a frame's graph holds
the bodies and only the obstacle nodes in reach, its levels stay a valid hierarchy, and wall
contacts are seen on every level."""

from pathlib import Path

import numpy as np
import pytest
import torch
from graph_meshes import side_by_side

from bsms.data import GraphOptions, NodeType, Scenario, saved_graph_options
from bsms.graph import bistride_levels, contact_edges
from bsms.graph.frames import SubHierarchy
from datagen import shapes
from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.scenes import get_scene
from datagen.simulation import resolve_config

ROOT = Path(__file__).resolve().parents[1]


def scenario_of(scene, options: GraphOptions, cache_dir=None) -> Scenario:
    return Scenario.build(scene.body, options, frame_dt=0.01, node_type=scene.node_type, body_id=scene.body_id,
                          obstacle_nodes=scene.obstacle_nodes, obstacle_facets=scene.obstacle_facets,
                          cache_dir=cache_dir)


def on_the_floor(scenario: Scenario, pos: np.ndarray, left_wall: bool = False) -> np.ndarray:
    """``pos`` with every body moved down until it nearly touches the floor (and, optionally, the
    first body moved against the left wall): the frame with the most wall in reach."""
    pos = pos.copy()
    low = scenario.rest_pos[scenario.n_body:].min(axis=0)
    gap = 0.2 * scenario.contact_radius
    for body in np.unique(scenario.body_id[: scenario.n_body]):
        nodes = np.flatnonzero(scenario.body_id[: scenario.n_body] == body)
        pos[nodes, 1] -= pos[nodes, 1].min() - low[1] - gap
        if left_wall and body == 0:
            pos[nodes, 0] -= pos[nodes, 0].min() - low[0] - gap
    return pos


@pytest.mark.parametrize("family", ["glyphs", "disks"])
def test_default_graph_is_at_most_1_2_times_the_bodies(family, tmp_path):
    """Measured on 4 trajectories each (start, all bodies on the floor): glyphs 1.00-1.14,
    disks 1.06-1.08 (every obstacle node, as before: glyphs 2.9-5.0, disks 1.6-1.7)."""
    dconfig = load_dataset_config(ROOT / "configs" / "datasets" / f"{family}.yaml")
    for index in range(4):
        config = resolve_config(trajectory_config(dconfig, "train", index))
        scene = get_scene(config["scene"]).build(config["params"])
        scenario = scenario_of(scene, GraphOptions(levels=6), tmp_path)
        start = scenario.full(scene.x[scene.tracked])
        velocity = np.zeros_like(start)
        for pos in (start, on_the_floor(scenario, start)):
            graph = scenario.graph(pos, velocity)
            assert graph.num_nodes <= 1.2 * scenario.n_body, (index, graph.num_nodes, scenario.n_body)
        assert (graph.node_type == NodeType.OBSTACLE).any(), "bodies on the floor see it"
        assert graph.num_nodes < scenario.n_nodes, "and not the rest of the box"


@pytest.fixture(scope="module")
def letters_in_a_corner():
    """Two letters in a box, the first pressed into the bottom-left corner: (scenario, positions)."""
    scene = get_scene("glyphs").build({**get_scene("glyphs").params({
        "chars": ["L", "T"], "centers": [[0.3, 0.6], [0.7, 0.6]], "velocities": [[0, 0], [0, 0]], "height": 0.3,
        "body_size": 0.03, "mesh_size": 0.06})})
    scenario = scenario_of(scene, GraphOptions(levels=5))
    return scene, scenario, on_the_floor(scenario, scenario.full(scene.x[scene.tracked]), left_wall=True)


def graph_index(graph, level: int, scenario_nodes: np.ndarray) -> np.ndarray:
    """Index in ``level`` of ``graph`` of each scenario node (which must be on that level)."""
    nodes = graph.scenario_nodes[graph[f"nodes_{level}"]].numpy()
    where = np.searchsorted(nodes, scenario_nodes)
    assert (nodes[np.minimum(where, len(nodes) - 1)] == scenario_nodes).all()
    return where


def test_wall_contacts_reach_every_level_through_the_parents(letters_in_a_corner):
    _, scenario, pos = letters_in_a_corner
    graph = scenario.graph(pos, np.zeros_like(pos))
    contacts = graph.scenario_nodes[graph.contact_index_0].numpy()
    every = contact_edges(pos, scenario.body_id, scenario.contact_radius, self_contact=False)
    assert np.array_equal(contacts, every), "every contact within the radius, as with every obstacle node"
    walls = scenario.node_type[contacts[1]] == NodeType.OBSTACLE
    assert walls.sum() >= 20 and (scenario.node_type[contacts[0, walls]] != NodeType.OBSTACLE).all()
    ancestors = scenario.levels.ancestors
    for level in range(1, scenario.levels.n_levels):
        found = graph[f"contact_index_{level}"].numpy()
        kinds = graph.node_type[graph[f"nodes_{level}"]].numpy()[found]
        assert ((kinds[0] == NodeType.OBSTACLE) != (kinds[1] == NodeType.OBSTACLE)).sum() >= 4, level
        # the image (parent of the body node, parent of the wall node) of every wall contact is there
        image = np.stack([graph_index(graph, level, ancestors[c, level]) for c in contacts[:, walls]])
        keys = set(map(tuple, found.T.tolist()))
        assert all(tuple(pair) in keys for pair in image.T.tolist()), level


def test_legacy_option_keeps_every_obstacle_node_and_the_full_hierarchy(letters_in_a_corner):
    scene, scenario, pos = letters_in_a_corner
    full = scenario_of(scene, GraphOptions(levels=5, obstacle_margin=None))
    graph = full.graph(pos, np.zeros_like(pos))
    assert graph.num_nodes == full.n_nodes > scenario.graph(pos, np.zeros_like(pos)).num_nodes
    for l, level in enumerate(full.hierarchy.levels):
        assert np.array_equal(graph[f"edge_index_{l}"].numpy(), level.edge_index)
        if l:
            down = graph.transition("down", l - 1)
            assert np.array_equal(down.rows.numpy(), level.down.rows)
            assert np.array_equal(down.weights.numpy(), level.down.weights.astype(np.float32))
    assert saved_graph_options({"levels": 3})["obstacle_margin"] is None, "runs saved before lean obstacles"
    assert saved_graph_options({"obstacle_margin": 2.0})["obstacle_margin"] == 2.0


def reference_contacts(levels, contacts0: np.ndarray) -> list[set]:
    """Eq. 4.1 on restricted levels, densely: C_{l+1} = ((A_l + I) C_l (A_l + I))[K, K] off the diagonal."""
    n0 = len(levels[0].nodes)
    current = np.zeros((n0, n0), bool)
    current[contacts0[0], contacts0[1]] = True
    out = [current]
    for finer, coarser in zip(levels[:-1], levels[1:], strict=True):
        n = len(finer.nodes)
        closed = np.eye(n)
        closed[finer.edge_index[0], finer.edge_index[1]] = 1
        kept = np.searchsorted(finer.nodes, coarser.nodes)
        current = (closed @ out[-1] @ closed)[np.ix_(kept, kept)] > 0
        np.fill_diagonal(current, False)
        out.append(current)
    return [set(zip(*np.nonzero(c), strict=True)) for c in out]


@pytest.mark.parametrize("self_loops", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_any_subset_of_optional_nodes_gives_a_valid_hierarchy(self_loops, seed):
    """Random subsets of the optional nodes of a body + wall graph: transitions stay weighted
    averages, every node has an up row, and contacts follow eq. 4.1 on the restricted levels."""
    rng = np.random.default_rng(seed)
    parts = [shapes.disk(0.3, 0.08), shapes.glyph("S", 0.08, height=0.6)]
    body = side_by_side(parts, 0.1)
    wall = shapes.rectangle(2.0, 0.3, 0.1, origin=(-0.3, -0.6))
    edges = np.concatenate([body.edges, wall.edges + body.n_nodes])
    positions = np.concatenate([body.nodes, wall.nodes])
    hierarchy = bistride_levels(edges, positions, levels=4, seeding="min_ave", self_loops=self_loops)
    sub = SubHierarchy(hierarchy, body.n_nodes)
    chosen = body.n_nodes + rng.choice(wall.n_nodes, size=wall.n_nodes // 4, replace=False)
    present = sub.closure(chosen)
    assert present[: body.n_nodes].all() and present[chosen].all() and not present.all()
    levels, keep, local = sub.levels(present)
    for l, level in enumerate(levels[:-1]):
        for t, n_rows in ((level.down, len(levels[l + 1].nodes)), (level.up, len(level.nodes))):
            sums = np.bincount(t.rows, weights=t.weights, minlength=n_rows)
            np.testing.assert_allclose(sums, 1.0, rtol=0, atol=4e-16)  # measured 2.2e-16
            assert (t.weights > 0).all() and t.cols.max() < t.shape[1]
    ids = np.repeat([0, 1, 2], [parts[0].n_nodes, parts[1].n_nodes, wall.n_nodes])
    pos = positions[present]
    level0 = contact_edges(pos, ids[present], 0.25)
    per_level = sub.contacts(np.flatnonzero(present)[level0], keep, local)
    expected = reference_contacts(levels, level0)
    assert len(expected[0]) > 20 and all(len(e) for e in expected)
    for found, reference in zip(per_level, expected, strict=True):
        assert set(map(tuple, found.T.tolist())) == reference
    other = sub.closure(chosen[: len(chosen) // 2])
    assert sub.levels(present)[0] is levels, "the same nodes again: the kept answer"
    fresh = SubHierarchy(hierarchy, body.n_nodes).levels(other)[0]
    for ours, theirs in zip(sub.levels(other)[0], fresh, strict=True):  # other nodes: restricted anew
        assert np.array_equal(ours.nodes, theirs.nodes) and np.array_equal(ours.edge_index, theirs.edge_index)


def test_every_node_present_is_the_full_hierarchy_bit_for_bit():
    body = shapes.glyph("R", 0.08, height=0.6)
    wall = shapes.rectangle(1.0, 0.2, 0.1, origin=(0.0, -0.5))
    edges = np.concatenate([body.edges, wall.edges + body.n_nodes])
    hierarchy = bistride_levels(edges, np.concatenate([body.nodes, wall.nodes]), levels=4)
    sub = SubHierarchy(hierarchy, body.n_nodes)
    levels, _, _ = sub.levels(np.ones(hierarchy.levels[0].n_nodes, bool))
    for l, level in enumerate(levels):
        assert np.array_equal(level.edge_index, hierarchy.levels[l].edge_index)
        assert np.array_equal(level.nodes, hierarchy.finest_indices(l))
        if l + 1 < len(levels):
            for kind in ("down", "up"):
                ours, theirs = getattr(level, kind), getattr(hierarchy.levels[l + 1], kind)
                for part in ("rows", "cols", "weights"):
                    assert np.array_equal(getattr(ours, part), getattr(theirs, part)), (l, kind, part)


def test_graph_sizes_follow_the_bodies(letters_in_a_corner):
    """Lifted off the floor the letters leave the walls out of the graph; pressed into the corner
    they bring them back."""
    _, scenario, pos = letters_in_a_corner
    lifted = pos.copy()
    lifted[: scenario.n_body, 1] += 0.3
    lifted[scenario.body_id == 0, 0] += 0.15
    air, floor = (scenario.graph(p, np.zeros_like(p)) for p in (lifted, pos))
    assert air.num_nodes == scenario.n_body and air.contact_index_0.shape[1] == 0
    assert floor.num_nodes > scenario.n_body
    assert torch.equal(floor.scenario_nodes[: scenario.n_body], torch.arange(scenario.n_body))


def test_graph_self_contact_joins_close_nodes_of_one_body_that_are_not_mesh_neighbours():
    """graph.self_contact: a body alone gets contact edges between its own nodes within the radius
    that no mesh edge joins (a body folding onto itself); without it, none."""
    body = shapes.disk(0.5, 0.1)
    free = np.full(body.n_nodes, NodeType.FREE)
    pos = body.nodes.copy()
    for self_contact in (True, False):
        options = GraphOptions(levels=2, obstacles=False, self_contact=self_contact)
        scenario = Scenario.build(body, options, frame_dt=0.01, node_type=free)
        graph = scenario.graph(pos, np.zeros_like(pos))
        contacts = graph.scenario_nodes[graph.contact_index_0].numpy()
        if not self_contact:
            assert contacts.shape[1] == 0
            continue
        expected = contact_edges(pos, np.zeros(body.n_nodes, np.int64), scenario.contact_radius, body.edges)
        assert contacts.shape[1] > 0 and np.array_equal(contacts, expected)
        meshed = {tuple(edge) for edge in body.edges.tolist()} | {tuple(edge[::-1]) for edge in body.edges.tolist()}
        assert not meshed & set(map(tuple, contacts.T.tolist()))
