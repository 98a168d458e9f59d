"""The coarse-degree cap of the bi-stride hierarchy (``max_coarse_degree``, bsms.graph.capping)."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
import scipy.sparse as sp
from graph_meshes import shape_mesh, side_by_side
from scipy.sparse import csgraph

from bsms.config import ConfigError, build
from bsms.graph import bistride_levels, coarsen_contacts, contact_edges
from bsms.graph.bfs import bfs_depths
from bsms.graph.cache import hierarchy_key
from bsms.graph.capping import capped_coarse_adjacency, greedy_degree_cap, path_counts
from bsms.graph.pooling import closed_rows
from bsms.options import GraphOptions


def two_solids():
    """A box and a sphere side by side (two components), tetrahedra."""
    parts = [shape_mesh("box", 0.14), shape_mesh("sphere", 0.14)]
    return side_by_side(parts, gap=0.05), np.repeat([0, 1], [part.n_nodes for part in parts])


def edge_set(level) -> set[tuple[int, int]]:
    return set(map(tuple, level.edge_index.T.tolist()))


def degrees(level) -> np.ndarray:
    return np.bincount(level.edge_index[0], minlength=level.n_nodes)


def two_hop_pairs(finer, kept) -> set[tuple[int, int]]:
    """Kept pairs within two hops of ``finer``, (A + I)^2 [K, K] without the diagonal (eq. 4.1)."""
    closed = (finer.adjacency + sp.identity(finer.n_nodes, format="csr")).tocsr()
    square = (closed @ closed)[kept][:, kept].tocoo()
    return {(i, j) for i, j in zip(square.row.tolist(), square.col.tolist(), strict=True) if i != j}


def same_levels(a, b) -> bool:
    return a.n_levels == b.n_levels and all(
        np.array_equal(x.kept, y.kept) and np.array_equal(x.edge_index, y.edge_index)
        and np.array_equal(x.node_weights, y.node_weights) for x, y in zip(a.levels, b.levels, strict=True))


def rebuilt(finer, coarse, cap):
    """Level ``coarse`` rebuilt from ``finer`` under ``cap``: (adjacency, reconnecting pairs)."""
    depth = bfs_depths(finer.adjacency, coarse.seeds)[coarse.kept]
    return capped_coarse_adjacency(closed_rows(finer.adjacency, coarse.kept), depth, cap)


# ---------------------------------------------------------------------- the default: no cap
def test_default_is_the_thesis_hierarchy_with_its_old_cache_key():
    mesh, _ = two_solids()
    default, explicit = bistride_levels(mesh, levels="auto"), bistride_levels(mesh, levels="auto", max_coarse_degree=None)
    assert same_levels(default, explicit) and default.key == explicit.key and default.max_coarse_degree is None
    for finer, coarse in pairwise(default.levels):
        assert edge_set(coarse) == two_hop_pairs(finer, coarse.kept)
    old_options = {"levels": "auto", "min_nodes": 32, "seeding": "min_ave", "seed": 0, "self_loops": True}
    adjacency = default.levels[0].adjacency
    adjacency.sort_indices()
    assert default.key == hierarchy_key(adjacency, None, old_options)  # caches built before the cap stay valid


@pytest.mark.parametrize("kind", ["rectangle", "annulus", "glyph", "box"])
def test_a_cap_at_the_natural_coarse_degree_changes_nothing(kind):
    mesh = shape_mesh(kind, 0.09)
    plain = bistride_levels(mesh, levels="auto")
    natural = max(int(degrees(level).max()) for level in plain.levels[1:] if level.n_edges)
    for cap in (natural, natural + 5):
        assert same_levels(bistride_levels(mesh, levels="auto", max_coarse_degree=cap), plain)
    assert not same_levels(bistride_levels(mesh, levels="auto", max_coarse_degree=natural - 1), plain)


# ---------------------------------------------------------------------- with a cap
@pytest.mark.parametrize("cap", [1, 2, 6, 12])
def test_capped_levels_keep_the_bound_components_and_symmetry(cap):
    mesh, _ = two_solids()
    hierarchy = bistride_levels(mesh, levels="auto", max_coarse_degree=cap)
    assert hierarchy.max_coarse_degree == cap and hierarchy.n_levels >= 4
    labels = hierarchy.component_labels
    reconnected = 0
    for l, (finer, coarse) in enumerate(pairwise(hierarchy.levels), start=1):
        adjacency, extra = rebuilt(finer, coarse, cap)
        edges = edge_set(coarse)
        assert edges == set(zip(*adjacency.nonzero(), strict=True))  # the build is this rule, level by level
        assert edges == {(j, i) for i, j in edges} and all(i != j for i, j in edges)
        assert edges <= two_hop_pairs(finer, coarse.kept)  # only pairs bi-stride would join
        at_node = np.bincount(extra.ravel(), minlength=coarse.n_nodes)
        assert (degrees(coarse) <= cap + at_node).all()  # the guarantee: cap, plus reconnecting edges
        level_labels = hierarchy.select(labels, l)
        n_pieces, pieces = csgraph.connected_components(coarse.adjacency, directed=False)
        assert n_pieces == np.unique(level_labels).size  # one piece per mesh component
        assert all(np.unique(level_labels[pieces == p]).size == 1 for p in range(n_pieces))
        reconnected += extra.shape[1]
    assert (reconnected > 0) == (cap <= 2)  # caps of 1 and 2 split levels (and are rejoined); 6 and 12 did not


def test_capped_hierarchies_are_smaller_deterministic_and_cached_apart(tmp_path):
    mesh, _ = two_solids()
    plain = bistride_levels(mesh, levels=4, cache_dir=tmp_path)
    capped = bistride_levels(mesh, levels=4, max_coarse_degree=8, cache_dir=tmp_path)
    assert capped.key != plain.key != bistride_levels(mesh, levels=4, max_coarse_degree=9).key
    assert len(list(tmp_path.glob("*.npz"))) == 2
    again = bistride_levels(mesh, levels=4, max_coarse_degree=8, cache_dir=tmp_path)  # read from the cache
    assert again.max_coarse_degree == 8 and same_levels(again, capped)
    assert same_levels(bistride_levels(mesh, levels=4, max_coarse_degree=8), capped)
    assert sum(level.n_edges for level in capped.levels[1:]) < sum(level.n_edges for level in plain.levels[1:])


def test_contact_edges_reach_every_capped_level():
    mesh, body_id = two_solids()
    contacts = contact_edges(mesh.nodes, body_id, 0.2, mesh.edges)
    assert contacts.shape[1] > 0
    for cap in (None, 4):
        hierarchy = bistride_levels(mesh, levels=5, max_coarse_degree=cap)
        per_level = coarsen_contacts(hierarchy, contacts)
        assert len(per_level) == hierarchy.n_levels
        for l, pairs in enumerate(per_level):
            bodies = hierarchy.select(body_id, l)[pairs]
            assert (bodies[0] != bodies[1]).any(), (cap, l)  # the two bodies still touch on every level


def test_path_counts_count_common_closed_neighbours():
    mesh = shape_mesh("disk", 0.14)
    hierarchy = bistride_levels(mesh, levels=2)
    kept = hierarchy.levels[1].kept
    closed = (mesh.adjacency() + sp.identity(mesh.n_nodes)).toarray() > 0
    expected = closed[kept].astype(int) @ closed[kept].T.astype(int)
    np.fill_diagonal(expected, 0)
    assert np.array_equal(path_counts(closed_rows(hierarchy.levels[0].adjacency, kept)).toarray(), expected)


def test_greedy_rounds_give_the_sequential_greedy():
    rng = np.random.default_rng(0)
    for _ in range(100):
        n = int(rng.integers(2, 30))
        pairs = np.array([(a, b) for a in range(n) for b in range(a + 1, n)])
        pairs = pairs[rng.permutation(len(pairs))[: int(rng.integers(1, len(pairs) + 1))]]
        cap = int(rng.integers(1, 6))
        room, expected = np.full(n, cap), []
        for a, b in pairs:
            expected.append(bool(room[a] and room[b]))
            room[[a, b]] -= expected[-1]
        assert np.array_equal(greedy_degree_cap(pairs[:, 0], pairs[:, 1], n, cap), expected)


# ---------------------------------------------------------------------- bad values
@pytest.mark.parametrize("value", [0, -3, 2.5, True, "12"])
def test_bad_caps_raise_one_clear_error(value):
    with pytest.raises(ValueError, match="max_coarse_degree must be None"):
        bistride_levels(shape_mesh("rectangle", 0.14), max_coarse_degree=value)
    with pytest.raises(ConfigError, match=r"config key 'graph\.max_coarse_degree' must be an integer"):
        build(GraphOptions, {"max_coarse_degree": value}, prefix="graph")


def test_graph_options_carry_the_cap_to_the_scenario():
    from bsms.data import Scenario

    mesh = shape_mesh("box", 0.14)
    scenario = Scenario.build(mesh, build(GraphOptions, {"levels": 3, "max_coarse_degree": 5}, prefix="graph"),
                              frame_dt=0.01)
    assert scenario.hierarchy.max_coarse_degree == 5
    assert max(int(degrees(level).max()) for level in scenario.hierarchy.levels[1:]) <= 5
