"""datagen.mesh: hand-built meshes with exact expected values, validation messages, I/O."""

import meshio
import numpy as np
import pytest

from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mesh import Mesh, MeshError

# Unit cube split into the six Kuhn tetrahedra around the main diagonal 0-7.
CUBE_NODES = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float)
KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def cube() -> Mesh:
    return Mesh.from_arrays(CUBE_NODES, KUHN, orient=True)


def square_with_centre() -> Mesh:
    nodes = [[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]]
    return Mesh(nodes, [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])


def test_1d_mesh_exact():
    mesh = Mesh([[0.0], [1.0], [3.0]], [[0, 1], [1, 2]])
    assert mesh.dim == 1 and mesh.cell_type == "line"
    np.testing.assert_array_equal(mesh.edges, [[0, 1], [1, 2]])
    np.testing.assert_array_equal(mesh.cell_measures, [1.0, 2.0])
    np.testing.assert_array_equal(mesh.boundary_facets, [[0], [2]])
    np.testing.assert_array_equal(mesh.boundary_normals, [[-1.0], [1.0]])
    np.testing.assert_array_equal(mesh.boundary_node_mask, [True, False, True])
    np.testing.assert_array_equal(mesh.adjacency().toarray(), [[0, 1, 0], [1, 0, 1], [0, 1, 0]])
    np.testing.assert_array_equal(mesh.adjacency(self_loops=True).toarray(), [[1, 1, 0], [1, 1, 1], [0, 1, 1]])
    stats = mesh.edge_length_stats
    assert (stats.min, stats.mean, stats.max) == (1.0, 1.5, 2.0)


def test_2d_mesh_exact():
    mesh = square_with_centre()
    np.testing.assert_array_equal(mesh.edges, [[0, 1], [0, 3], [0, 4], [1, 2], [1, 4], [2, 3], [2, 4], [3, 4]])
    np.testing.assert_allclose(mesh.cell_measures, 0.25, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(mesh.boundary_node_mask, [True, True, True, True, False])
    np.testing.assert_array_equal(mesh.node_degree, [3, 3, 3, 3, 4])
    # Counter-clockwise outer boundary, one facet per side, exact outward normals.
    facets = {tuple(f): tuple(n) for f, n in zip(mesh.boundary_facets, mesh.boundary_normals, strict=True)}
    assert facets == {(0, 1): (0.0, -1.0), (1, 2): (1.0, 0.0), (2, 3): (0.0, 1.0), (3, 0): (-1.0, 0.0)}
    np.testing.assert_array_equal(mesh.boundary_facet_measures, [1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(mesh.boundary_node_normals[0], [-np.sqrt(0.5), -np.sqrt(0.5)])
    np.testing.assert_array_equal(mesh.boundary_node_normals[4], [0.0, 0.0])
    adjacency = mesh.adjacency().toarray()
    np.testing.assert_array_equal(adjacency, adjacency.T)
    assert adjacency.sum() == 2 * len(mesh.edges) and np.trace(adjacency) == 0
    np.testing.assert_array_equal(np.diag(mesh.adjacency(self_loops=True).toarray()), 1)


def test_3d_cube_exact():
    mesh = cube()
    assert mesh.n_cells == 6 and mesh.cell_type == "tetra"
    np.testing.assert_allclose(mesh.cell_measures, 1 / 6, rtol=1e-14)
    assert len(mesh.edges) == 19  # 12 cube edges, 6 face diagonals, 1 main diagonal
    assert len(mesh.boundary_facets) == 12
    assert mesh.boundary_node_mask.all()
    np.testing.assert_allclose(mesh.boundary_facet_measures, 0.5, rtol=1e-14)
    # Every boundary triangle lies on a cube face and its normal points out of that face.
    centroids = mesh.nodes[mesh.boundary_facets].mean(axis=1)
    for centroid, normal in zip(centroids, mesh.boundary_normals, strict=True):
        axis = int(np.argmax(np.abs(normal)))
        np.testing.assert_allclose(np.abs(normal), np.eye(3)[axis], atol=1e-15)
        side = 1.0 if centroid[axis] > 0.5 else -1.0
        assert normal[axis] == side and centroid[axis] in (0.0, 1.0)
    # The orientation of each facet's nodes gives its outward normal (right-hand rule).
    x = mesh.nodes[mesh.boundary_facets]
    cross = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    assert ((cross * mesh.boundary_normals).sum(axis=1) > 0).all()


def test_divergence_theorem_on_boundary():
    """Sum of facet measure times outward normal vanishes for any closed boundary."""
    for mesh in (square_with_centre(), cube()):
        total = (mesh.boundary_normals * mesh.boundary_facet_measures[:, None]).sum(axis=0)
        np.testing.assert_allclose(total, 0.0, atol=1e-14)


def test_components_and_quality():
    nodes = [[0, 0], [1, 0], [0, 1], [5, 5], [6, 5], [5, 6]]
    mesh = Mesh(nodes, [[0, 1, 2], [3, 4, 5]])
    assert mesh.n_components == 2
    np.testing.assert_array_equal(mesh.component_labels, [0, 0, 0, 1, 1, 1])
    equilateral = Mesh([[0, 0], [1, 0], [0.5, np.sqrt(3) / 2]], [[0, 1, 2]])
    np.testing.assert_allclose(equilateral.cell_quality, [1.0], rtol=1e-14)
    assert mesh.cell_quality[0] < 1.0


def test_arrays_are_read_only_and_cached():
    mesh = square_with_centre()
    with pytest.raises(ValueError):
        mesh.nodes[0, 0] = 3.0
    with pytest.raises(ValueError):
        mesh.cells[0, 0] = 3
    assert mesh.edges is mesh.edges and mesh.adjacency() is mesh.adjacency()
    assert mesh.nodes.dtype == np.float64 and mesh.cells.dtype == np.int64


def test_topology_hash_depends_on_connectivity_only():
    a = square_with_centre()
    b = Mesh(a.nodes * 2.0 + 1.0, a.cells)
    c = Mesh(a.nodes, a.cells[::-1])
    assert a.topology_hash == b.topology_hash != c.topology_hash


@pytest.mark.parametrize(
    ("nodes", "cells", "message"),
    [
        ([[0, 0], [1, 0], [np.nan, 1]], [[0, 1, 2]], "non-finite coordinates (NaN or inf) at nodes [2]"),
        ([[0, 0], [1, 0], [0, 1]], [[0, 1, 2, 2]], "wrong cell arity: cells have 4 nodes each, but nodes have 2"),
        ([[0, 0], [1, 0], [0, 1]], [[0, 1, 3]], "node indices out of range [0, 3) in cells [0]"),
        ([[0, 0], [1, 0], [0, 1]], [[0, -1, 2]], "node indices out of range [0, 3) in cells [0]"),
        ([[0, 0], [1, 0], [0, 1], [3, 3]], [[0, 1, 2]], "nodes [3] are used by no cell"),
        ([[0, 0], [1, 0], [0, 1], [1, 1]], [[0, 1, 2], [1, 2, 3]], "inverted cells (negative signed area): cells [1]"),
        ([[0, 0], [1, 0], [2, 0], [0, 1]], [[0, 1, 2], [0, 1, 3]], "degenerate cells (zero area): cells [0]"),
        ([[0.0], [1.0], [1.0]], [[0, 1], [1, 2]], "degenerate cells (zero length): cells [1]"),
        (np.zeros((3, 4)), [[0, 1, 2]], "mesh nodes must have shape (N, d) with N >= 1 and d in 1, 2, 3"),
        ([[0, 0], [1, 0], [0, 1]], [[0.0, 1.0, 2.0]], "mesh cells must be an integer array"),
    ],
)
def test_validation_errors(nodes, cells, message):
    with pytest.raises(MeshError) as info:
        Mesh(nodes, cells)
    assert message in str(info.value)


def test_inverted_tetrahedron_is_named():
    nodes = CUBE_NODES[[0, 1, 2, 4]]
    with pytest.raises(MeshError, match=r"inverted cells \(negative signed volume\): cells \[0\]"):
        Mesh(nodes, [[0, 2, 1, 3]])
    assert Mesh(nodes, [[0, 1, 2, 3]]).cell_measures[0] == pytest.approx(1 / 6)


def test_error_lists_first_five_and_counts_the_rest():
    nodes = np.array([[i, 0.0] for i in range(10)] + [[0.0, 1.0]])
    cells = [[i + 1, i, 10] for i in range(9)]  # all clockwise
    with pytest.raises(MeshError, match=r"cells \[0, 1, 2, 3, 4\] and 4 more, 9 of 9 cells"):
        Mesh(nodes, cells)
    assert Mesh.from_arrays(nodes, cells, orient=True).cell_measures.min() > 0


def test_from_arrays_drops_unused_nodes_in_order():
    mesh = Mesh.from_arrays([[9, 9], [0, 0], [1, 0], [0, 1]], [[1, 2, 3]], drop_unused=True)
    np.testing.assert_array_equal(mesh.nodes, [[0, 0], [1, 0], [0, 1]])
    np.testing.assert_array_equal(mesh.cells, [[0, 1, 2]])


def test_non_manifold_mesh_is_reported():
    nodes = [[0, 0], [1, 0], [0.5, 1], [0.5, -1], [0.2, 0.5]]
    mesh = Mesh(nodes, [[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge 0-1 shared by three triangles
    with pytest.raises(MeshError, match="non-manifold mesh"):
        _ = mesh.boundary_facets


# ----------------------------------------------------------------------------- I/O
@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".xdmf", ".vtk", ".obj"])
def test_round_trip_2d(tmp_path, suffix):
    mesh = square_with_centre()
    mesh.write(tmp_path / f"m{suffix}")
    back = Mesh.read(tmp_path / f"m{suffix}")
    assert back.dim == 2
    np.testing.assert_allclose(back.nodes, mesh.nodes, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(back.cells, mesh.cells)


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".xdmf"])
def test_round_trip_3d_and_1d(tmp_path, suffix):
    for mesh in (cube(), Mesh([[0.0], [0.5], [2.0]], [[0, 1], [1, 2]])):
        path = tmp_path / f"m{mesh.dim}{suffix}"
        mesh.write(path, point_data={"id": np.arange(mesh.n_nodes, dtype=float)})
        back = Mesh.read(path)
        assert back.dim == mesh.dim
        np.testing.assert_allclose(back.nodes, mesh.nodes, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(back.cells, mesh.cells)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_read_ignores_lower_dimensional_cells_and_their_nodes(tmp_path):
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [7, 7, 0]], dtype=float)
    cells = [("vertex", np.array([[3]])), ("line", np.array([[0, 1]])), ("triangle", np.array([[0, 1, 2]]))]
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(points, cells))
    mesh = Mesh.read(tmp_path / "m.vtu")
    assert mesh.dim == 2 and mesh.n_nodes == 3 and mesh.n_cells == 1


def test_read_flips_a_consistently_clockwise_file(tmp_path):
    points = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    meshio.write(tmp_path / "cw.vtu", meshio.Mesh(points, [("triangle", np.array([[0, 2, 1], [0, 3, 2]]))]))
    mesh = Mesh.read(tmp_path / "cw.vtu")
    assert (mesh.cell_measures > 0).all()


@pytest.mark.parametrize(
    ("points", "cells", "message"),
    [
        ([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [("quad", [[0, 1, 2, 3]])],
         "has no usable cells: found ['quad'], but bsms needs simplices"),
        ([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]], [("quad", [[0, 1, 2, 3]]), ("triangle", [[1, 4, 2]])],
         "mixes cell types: ['quad', 'triangle']"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 1]], [("triangle", [[0, 1, 2]])],
         "embedded in 3D with non-zero coordinates beyond axis 2"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [("triangle", [[0, 1, 2], [1, 2, 3]])],
         "inverted cells (negative signed area): cells [1]"),
    ],
)
def test_read_errors(tmp_path, points, cells, message):
    path = tmp_path / "bad.vtu"
    meshio.write(path, meshio.Mesh(np.array(points, dtype=float), [(t, np.array(c)) for t, c in cells]))
    with pytest.raises(MeshError) as info:
        Mesh.read(path)
    assert message in str(info.value) and str(path) in str(info.value)


def test_read_missing_and_corrupt_files(tmp_path):
    with pytest.raises(MeshError, match="does not exist"):
        Mesh.read(tmp_path / "nope.vtu")
    (tmp_path / "junk.vtu").write_text("not a mesh")
    with pytest.raises(MeshError, match="cannot read mesh file .*junk.vtu"):
        Mesh.read(tmp_path / "junk.vtu")


def test_read_inconsistent_orientation_with_orient(tmp_path):
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(points, [("triangle", np.array([[0, 1, 2], [1, 2, 3]]))]))
    assert (Mesh.read(tmp_path / "m.vtu", orient=True).cell_measures > 0).all()


# ----------------------------------------------------------------------------- extra layer
@pytest.mark.parametrize(
    ("make", "outside_nodes", "layer_cells"),
    [
        # Each square corner: one copy per side + a bisector copy; 4 quads x 2 + 4 corner fans x 2.
        (square_with_centre, 12, 16),
        # Each cube corner: 3 face copies, 3 edge bisectors, 1 apex; 12 facet prisms x 3 tets,
        # 12 crease edges x 2 wedges x 3 tets, 8 corners x 6 cone tets.
        (cube, 8 * 7, 36 + 72 + 48),
        (lambda: Mesh([[0.0], [1.0], [2.0]], [[0, 1], [1, 2]]), 2, 2),
    ],
)
def test_extra_layer_structure(make, outside_nodes, layer_cells):
    mesh = make()
    ext = with_extra_layer(mesh)
    big = ext.mesh
    # Physical nodes and cells keep their indices and come first.
    np.testing.assert_array_equal(big.nodes[: mesh.n_nodes], mesh.nodes)
    np.testing.assert_array_equal(big.cells[: mesh.n_cells], mesh.cells)
    assert ext.n_physical_nodes == mesh.n_nodes and ext.n_physical_cells == mesh.n_cells
    assert int(ext.node_outside.sum()) == outside_nodes and int(ext.cell_outside.sum()) == layer_cells
    # Every physical boundary node gains a neighbour outside; interior nodes gain nothing.
    adjacency = big.adjacency().tocsr()
    outside_neighbours = adjacency[: mesh.n_nodes][:, ext.node_outside].sum(axis=1).A1
    np.testing.assert_array_equal(outside_neighbours > 0, mesh.boundary_node_mask)
    # Conforming and gap-free: the new boundary consists of outside nodes only (a gap or a
    # quad cut two ways would leave facets with physical nodes on the boundary).
    assert ext.node_outside[big.boundary_facets].all()
    np.testing.assert_allclose(big.cell_measures[~ext.cell_outside].sum(), mesh.cell_measures.sum())


@pytest.mark.parametrize(
    "make",
    [
        lambda: shapes.rectangle(1.0, 0.7, 0.1),
        lambda: shapes.polygon([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], size=0.2),
        lambda: shapes.glyph("B", 0.04),
        lambda: shapes.box((1.0, 0.8, 0.6), 0.2),
        lambda: shapes.sphere(1.0, 0.3),
    ],
)
def test_extra_layer_on_shapes_is_conforming(make):
    mesh = make()
    ext = with_extra_layer(mesh)
    assert ext.node_outside[ext.mesh.boundary_facets].all()
    assert ext.mesh.cell_quality[ext.cell_outside].min() > 0.1
    assert ext.node_outside.sum() >= mesh.boundary_node_mask.sum()  # at least one copy per boundary node


def test_prism_split_cuts_shared_quads_alike():
    from datagen.layer import split_prisms

    rng = np.random.default_rng(0)
    for _ in range(200):
        ids = rng.permutation(9)  # two prisms sharing the quad (1, 2, 5, 4) of the first
        first = ids[[0, 1, 2, 3, 4, 5]]
        second = ids[[1, 2, 6, 4, 5, 7]]
        quad = set(ids[[1, 2, 4, 5]])
        cut = []
        for prism in (first, second):
            faces = {frozenset(f) for tet in split_prisms(prism[None]) for f in
                     (tet[[0, 1, 2]], tet[[0, 1, 3]], tet[[0, 2, 3]], tet[[1, 2, 3]])}
            cut.append({f for f in faces if f <= quad})
        assert cut[0] == cut[1] and len(cut[0]) == 2


def test_extra_layer_outside_points_leave_the_domain():
    mesh = square_with_centre()
    outside = with_extra_layer(mesh).mesh.nodes[mesh.n_nodes:]
    assert (np.abs(outside - 0.5).max(axis=1) > 0.5 + 0.5).all()  # at least one edge length out
