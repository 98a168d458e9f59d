"""Contact edges (bsms.graph.contact): proximity queries and their coarse levels (eq. 4.1)."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
import scipy.sparse as sp
from graph_meshes import SHAPES_2D, SHAPES_3D, SIZES, shape_mesh, side_by_side
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import Delaunay

from bsms.graph import SEEDINGS, bistride_levels, coarsen_contacts, contact_edges


def pair_set(edge_index: np.ndarray) -> set[tuple[int, int]]:
    return {(int(i), int(j)) for i, j in edge_index.T}


def brute_force_contacts(positions, body_id, radius, exclude, self_contact):
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    close = (distance <= radius) & ~np.eye(len(positions), dtype=bool)
    same = body_id[:, None] == body_id[None]
    excluded = np.zeros_like(close)
    excluded[exclude[:, 0], exclude[:, 1]] = excluded[exclude[:, 1], exclude[:, 0]] = True
    keep = close & (~same | (self_contact & ~excluded))
    rows, cols = np.nonzero(keep)
    return set(zip(rows.tolist(), cols.tolist(), strict=True))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("self_contact", [True, False])
def test_contact_edges_match_brute_force(dim, self_contact):
    rng = np.random.default_rng(dim)
    positions = rng.random((300, dim))
    body_id = rng.integers(0, 3, 300)
    exclude = Delaunay(positions).simplices[:, :2]
    found = contact_edges(positions, body_id, 0.12, exclude, self_contact=self_contact)
    expected = brute_force_contacts(positions, body_id, 0.12, exclude, self_contact)
    assert found.dtype == np.int64 and found.shape[0] == 2
    assert pair_set(found) == expected and len(expected) > 50
    assert np.array_equal(np.lexsort((found[1], found[0])), np.arange(found.shape[1]))


def test_no_contact_between_mesh_neighbours():
    mesh = shape_mesh("annulus", 0.09)
    contacts = contact_edges(mesh.nodes, np.zeros(mesh.n_nodes, int), 1.0, mesh.edges)
    adjacency = mesh.adjacency().toarray() > 0
    assert contacts.shape[1] > 0
    assert not adjacency[contacts[0], contacts[1]].any()


def two_bodies(kinds: tuple[str, str], size: float, gap: float):
    parts = [shape_mesh(kind, size) for kind in kinds]
    mesh = side_by_side(parts, gap)
    body_id = np.repeat(np.arange(2), [part.n_nodes for part in parts])
    return mesh, body_id


def closed_to_kept(finer, coarse) -> sp.csr_matrix:
    """(n_fine, n_coarse): 1 where a fine node is a kept node or next to one."""
    closed = finer.adjacency + sp.identity(finer.n_nodes, format="csr")
    return (closed[:, coarse.kept] > 0).astype(float).tocsr()


bodies_2d = st.tuples(st.sampled_from(sorted(SHAPES_2D)), st.sampled_from(sorted(SHAPES_2D)))
bodies_3d = st.tuples(st.sampled_from(sorted(SHAPES_3D)), st.sampled_from(sorted(SHAPES_3D)))


@given(st.one_of(bodies_2d, bodies_3d), st.sampled_from(SIZES), st.sampled_from(SEEDINGS), st.booleans())
@settings(max_examples=20, deadline=None)
def test_every_contact_has_a_coarse_image_on_every_level(kinds, size, seeding, self_contact):
    mesh, body_id = two_bodies(kinds, size, gap=0.6 * size)
    hierarchy = bistride_levels(mesh, seeding=seeding)
    contacts = contact_edges(mesh.nodes, body_id, 3.0 * size, mesh.edges, self_contact=self_contact)
    assert (body_id[contacts[0]] != body_id[contacts[1]]).any()
    per_level = coarsen_contacts(hierarchy, contacts)
    assert len(per_level) == hierarchy.n_levels and pair_set(per_level[0]) == pair_set(contacts)
    for l, (finer, coarse) in enumerate(pairwise(hierarchy.levels)):
        (i, j), coarse_contacts = per_level[l], per_level[l + 1]
        near = closed_to_kept(finer, coarse)
        coarse_matrix = sp.csr_matrix((np.ones(coarse_contacts.shape[1]), coarse_contacts),
                                      shape=(coarse.n_nodes, coarse.n_nodes))
        has_image = np.asarray((near @ coarse_matrix @ near.T)[i, j]).ravel() > 0  # some (i', j')
        collapsed = np.asarray((near @ near.T)[i, j]).ravel() > 0  # one kept node next to i and j
        bodies = hierarchy.select(body_id, l)
        between = bodies[i] != bodies[j]
        assert has_image[between].all()
        assert (has_image | collapsed).all()
        coarse_bodies = hierarchy.select(body_id, l + 1)[coarse_contacts]
        assert set(map(frozenset, bodies[[i[between], j[between]]].T.tolist())) == set(
            map(frozenset, coarse_bodies[:, coarse_bodies[0] != coarse_bodies[1]].T.tolist()))


def test_coarse_contacts_follow_equation_4_1():
    mesh, body_id = two_bodies(("disk", "square with holes"), 0.09, 0.05)
    hierarchy = bistride_levels(mesh, levels=4)
    contacts = contact_edges(mesh.nodes, body_id, 0.08, mesh.edges)
    per_level = coarsen_contacts(hierarchy, contacts)
    current = np.zeros((mesh.n_nodes, mesh.n_nodes))
    current[contacts[0], contacts[1]] = 1
    for l, (finer, coarse) in enumerate(pairwise(hierarchy.levels)):
        closed = finer.adjacency.toarray() + np.eye(finer.n_nodes)
        current = (closed @ current @ closed)[np.ix_(coarse.kept, coarse.kept)] > 0
        np.fill_diagonal(current, False)
        found = np.zeros_like(current)
        found[per_level[l + 1][0], per_level[l + 1][1]] = True
        assert np.array_equal(found, current)
        current = current.astype(float)


def test_no_contacts_stay_empty():
    hierarchy = bistride_levels(shape_mesh("disk", 0.14))
    empty = np.zeros((2, 0), dtype=np.int64)
    assert all(level.shape == (2, 0) for level in coarsen_contacts(hierarchy, empty))


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"body_id": np.zeros(5, int)}, "body_id must be"),
    ({"body_id": np.zeros(10)}, "body_id must be"),
    ({"radius": 0.0}, "radius must be"),
    ({"radius": float("nan")}, "radius must be"),
    ({"exclude": np.zeros((2, 7), int)}, r"exclude must be an integer \(E, 2\)"),
    ({"positions": np.zeros(10)}, r"positions must be a finite \(N, d\)"),
])
def test_bad_contact_arguments_raise_one_clear_error(kwargs, message):
    arguments = {"positions": np.zeros((10, 2)), "body_id": np.zeros(10, int), "radius": 0.1, **kwargs}
    with pytest.raises(ValueError, match=message):
        contact_edges(**arguments)


def test_bad_contacts_for_coarsening_raise_one_clear_error():
    hierarchy = bistride_levels(shape_mesh("disk", 0.14))
    with pytest.raises(ValueError, match=r"\(2, C\)"):
        coarsen_contacts(hierarchy, np.zeros((5, 2), dtype=int))
    with pytest.raises(ValueError, match="level-0 nodes"):
        coarsen_contacts(hierarchy, np.array([[0], [hierarchy.levels[0].n_nodes]]))
