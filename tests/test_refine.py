"""datagen.refine: midpoint subdivision keeps the mesh's nodes first, its measure, and its shape
quality; the press scene refines a given mesh to its family's resolution when asked."""

import itertools
import math

import numpy as np
import pytest

from datagen import shapes
from datagen.mesh import Mesh
from datagen.refine import refine_to, subdivide, subdivisions_for
from datagen.scenes import get_scene

PLATE = np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.06], [0.07, 0.06], [0.06, 0.032], [0.05, 0.06], [0.0, 0.06]])


def cube_tets() -> Mesh:
    corners = np.array(list(itertools.product([0.0, 1.0], repeat=3)))
    cells = [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]
    return Mesh.from_arrays(corners * [2.0, 1.0, 0.5], np.array(cells), orient=True)


@pytest.mark.parametrize("mesh", [shapes.polygon(PLATE, size=0.01), cube_tets()], ids=["triangles", "tetrahedra"])
def test_subdivision_keeps_nodes_first_and_measure(mesh):
    fine = subdivide(mesh)
    children = 2 ** mesh.dim
    assert fine.n_cells == children * mesh.n_cells and fine.n_nodes == mesh.n_nodes + len(mesh.edges)
    np.testing.assert_array_equal(fine.nodes[: mesh.n_nodes], mesh.nodes)
    midpoints = fine.nodes[mesh.n_nodes:]
    np.testing.assert_allclose(np.sort(midpoints, axis=0), np.sort(mesh.nodes[mesh.edges].mean(1), axis=0),
                               rtol=0, atol=1e-15)
    assert fine.cell_measures.sum() == pytest.approx(mesh.cell_measures.sum(), rel=1e-14)
    halves = np.isin(np.round(fine.edge_lengths, 12), np.round(mesh.edge_lengths / 2, 12))
    if mesh.dim == 2:
        assert halves.all()  # every edge is half of one of the mesh's
    else:  # and the inner octahedra's diagonals, none longer than the longest edge of the mesh
        assert halves.sum() >= len(fine.edges) - mesh.n_cells  # one diagonal per tetrahedron is not a half
        assert fine.edge_lengths.max() <= mesh.edge_lengths.max() * (1 + 1e-12)


def test_triangles_split_into_four_similar_ones():
    mesh = shapes.polygon(PLATE, size=0.01)
    fine = subdivide(mesh)
    parent = np.repeat(mesh.cell_measures[None], 4, axis=0).ravel()  # children are stacked by corner
    np.testing.assert_allclose(fine.cell_measures, parent / 4, rtol=1e-12)
    np.testing.assert_allclose(np.sort(fine.cell_quality), np.sort(np.tile(mesh.cell_quality, 4)), rtol=1e-12)


def test_tetrahedra_split_into_eight_of_an_eighth_the_volume():
    mesh = cube_tets()
    fine = subdivide(mesh)
    np.testing.assert_allclose(fine.cell_measures, np.full(fine.n_cells, mesh.cell_measures[0] / 8), rtol=1e-12)
    twice = subdivide(fine)
    assert twice.cell_measures.sum() == pytest.approx(1.0, rel=1e-14)  # the 2 x 1 x 0.5 box


@pytest.mark.parametrize(("ratio", "times"), [(1.0, 0), (1.41, 0), (1.6, 1), (2.8, 1), (2.9, 2), (5.6, 2), (6.0, 3)])
def test_subdivisions_bring_the_median_edge_within_sqrt2_of_the_spacing(ratio, times):
    mesh = shapes.polygon(PLATE, size=0.004)
    spacing = float(np.median(mesh.edge_lengths)) / ratio
    assert subdivisions_for(mesh, spacing) == times
    assert ratio / 2**times <= math.sqrt(2) and (times == 0 or ratio / 2 ** (times - 1) > math.sqrt(2))


def test_refine_to_and_bad_spacing():
    mesh = shapes.polygon(PLATE, size=0.004)
    fine, times = refine_to(mesh, 0.0025)
    assert times == 1 and fine.n_nodes == mesh.n_nodes + len(mesh.edges)
    same, none = refine_to(mesh, 0.004)
    assert none == 0 and same is mesh
    with pytest.raises(ValueError, match="spacing must be positive, got 0"):
        subdivisions_for(mesh, 0.0)


def test_the_press_scene_refines_a_given_mesh_to_its_bodies_resolution(tmp_path):
    path = tmp_path / "plate.msh"
    given = shapes.polygon(PLATE, size=0.004)
    given.write(str(path))
    scene = get_scene("press")
    params = {"mesh": str(path), "size": 0.12, "base": "bonded", "body_size": 0.0025, "min_nodes": 0}
    kept = scene.build(scene.params(params))
    refined = scene.build(scene.params({**params, "refine": True}))
    assert kept.body.n_nodes == given.n_nodes and kept.given_cells is None
    assert refined.body.n_nodes == given.n_nodes + len(given.edges)
    np.testing.assert_array_equal(refined.body.nodes[: given.n_nodes], kept.body.nodes)  # its nodes first
    np.testing.assert_array_equal(refined.given_cells, given.cells)
    assert refined.body.cell_measures.sum() == pytest.approx(kept.body.cell_measures.sum(), rel=1e-13)
    # min_nodes asks for a finer spacing on a small body: 1 subdivision at 2.5 mm, 2 for 4000 nodes
    finer = scene.build(scene.params({**params, "refine": True, "min_nodes": 4000}))
    assert finer.body.n_nodes == subdivide(subdivide(given)).n_nodes

