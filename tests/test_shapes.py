"""datagen.shapes: valid meshes of the requested size, deterministic, with the right topology."""

import math
import multiprocessing

import numpy as np
import pytest

from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mesh import Mesh


def holes(mesh: Mesh) -> int:
    """Number of holes of a planar mesh, from its Euler characteristic V - E + F = components - holes."""
    return mesh.n_components - (mesh.n_nodes - len(mesh.edges) + mesh.n_cells)


SHAPES = {
    "rectangle": (lambda: shapes.rectangle(2.0, 1.0, 0.1, origin=(1.0, -1.0)), 0.1),
    "disk": (lambda: shapes.disk(1.0, 0.1, center=(0.5, 0.5)), 0.1),
    "annulus": (lambda: shapes.annulus(0.4, 1.0, 0.1), 0.1),
    "polygon": (lambda: shapes.polygon([[0, 0], [2, 0], [2, 2], [0, 2]], [[[0.5, 0.5], [1.5, 0.5], [1, 1.5]]], 0.1), 0.1),
    "wavy_channel": (lambda: shapes.wavy_channel(size=0.25), 0.25),
    "glyph": (lambda: shapes.glyph("R8", 0.03), 0.03),
    "box": (lambda: shapes.box((1.0, 0.5, 0.5), 0.125), 0.125),
    "sphere": (lambda: shapes.sphere(0.5, 0.125), 0.125),
}


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_shape_is_valid_with_requested_size(name):
    make, size = SHAPES[name]
    mesh = make()
    assert isinstance(mesh, Mesh)
    assert mesh.dim == (3 if name in ("box", "sphere") else 2)
    mean = mesh.edge_length_stats.mean
    assert abs(mean - size) < 0.3 * size, f"{name}: mean edge {mean:.4f} for size {size}"
    assert mesh.cell_quality.min() > 0.1
    with_extra_layer(mesh)  # the solver's background needs it; must not fail on any shape


@pytest.mark.parametrize("name", ["disk", "glyph", "sphere"])
def test_shapes_are_deterministic(name):
    make, _ = SHAPES[name]
    a, b = make(), make()
    np.testing.assert_array_equal(a.nodes, b.nodes)
    np.testing.assert_array_equal(a.cells, b.cells)


def test_areas_and_volumes():
    rect = shapes.rectangle(2.0, 1.0, 0.2, origin=(1.0, -1.0))
    assert rect.cell_measures.sum() == pytest.approx(2.0, rel=1e-12)
    np.testing.assert_allclose(rect.nodes.min(axis=0), [1.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(rect.nodes.max(axis=0), [3.0, 0.0], atol=1e-12)
    ring = shapes.annulus(0.4, 1.0, 0.05)
    assert ring.cell_measures.sum() == pytest.approx(math.pi * (1.0 - 0.16), rel=5e-3)
    assert holes(ring) == 1
    ball = shapes.sphere(0.5, 0.1)
    assert ball.cell_measures.sum() == pytest.approx(4 / 3 * math.pi * 0.125, rel=0.03)
    assert np.linalg.norm(ball.nodes, axis=1).max() == pytest.approx(0.5, rel=1e-9)
    cuboid = shapes.box((1.0, 0.5, 0.25), 0.125, origin=(0, 1, 2))
    assert cuboid.cell_measures.sum() == pytest.approx(0.125, rel=1e-12)


def test_wavy_channel_follows_eq_36():
    length, width, inlet, outlet = 20.0, 2.0, 4.0, 1.0
    mesh = shapes.wavy_channel(width=width, length=length, inlet=inlet, outlet=outlet, size=0.25)
    # Each horizontal slice has width `width`, so the area is exact even for the polyline walls.
    assert mesh.cell_measures.sum() == pytest.approx(width * (length + inlet + outlet), rel=1e-9)
    x, y = mesh.nodes[mesh.boundary_node_mask].T
    wall = np.where((y > 0) & (y <= length), np.sin(np.pi / 5 * y) * np.sin(np.pi / 20 * y), 0.0)
    on_wall = np.minimum(np.abs(x - wall), np.abs(x - wall - width))
    on_ends = np.isclose(y, -outlet) | np.isclose(y, length + inlet)
    assert on_wall[~on_ends].max() < 1e-9  # wall nodes sit on the analytic walls
    assert y.min() == pytest.approx(-outlet) and y.max() == pytest.approx(length + inlet)


@pytest.mark.parametrize(("text", "expected"), [("A", 1), ("B", 2), ("C", 0), ("o", 1), ("8", 2)])
def test_glyph_holes(text, expected):
    mesh = shapes.glyph(text, 0.03)
    assert mesh.n_components == 1
    assert holes(mesh) == expected


def test_glyph_string_is_multi_component():
    mesh = shapes.glyph("iB", 0.03)
    assert mesh.n_components == 3  # the dot, the stem of i, the B
    assert holes(mesh) == 2


def test_boundary_size_refines_the_boundary():
    mesh = shapes.disk(1.0, 0.2, boundary_size=0.05)
    facet_lengths = mesh.boundary_facet_measures
    assert abs(facet_lengths.mean() - 0.05) < 0.3 * 0.05
    interior = ~mesh.boundary_node_mask[mesh.edges].any(axis=1)
    centre_edges = interior & (np.linalg.norm(mesh.nodes[mesh.edges].mean(axis=1), axis=1) < 0.3)
    assert mesh.edge_lengths[centre_edges].mean() > 2 * facet_lengths.mean()


def test_disk_normals_are_radial():
    mesh = shapes.disk(1.0, 0.1)
    centres = mesh.nodes[mesh.boundary_facets].mean(axis=1)
    radial = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    assert (mesh.boundary_normals * radial).sum(axis=1).min() > 0.99


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: shapes.disk(1.0, -0.1), "size must be a positive number"),
        (lambda: shapes.rectangle(0.0, 1.0, 0.1), "width and height must be positive"),
        (lambda: shapes.annulus(1.0, 0.5, 0.1), "0 < inner_radius < outer_radius"),
        (lambda: shapes.polygon([[0, 0], [1, 0]], size=0.1), "polygon outer ring must be a finite (K, 2) array"),
        (lambda: shapes.glyph("   ", 0.1), "glyph text must be a non-empty string"),
        (lambda: shapes.box((1.0, 1.0), 0.1), "box extent must be three positive lengths"),
        (lambda: shapes.disk(1.0, 0.1, boundary_size=0.0), "boundary_size must be a positive number"),
    ],
)
def test_bad_arguments(call, message):
    with pytest.raises(ValueError) as info:
        call()
    assert message in str(info.value)


def _disk_arrays(_):
    mesh = shapes.disk(1.0, 0.2)
    return mesh.nodes.copy(), mesh.cells.copy()


def test_worker_processes_and_repeated_calls_agree():
    here = _disk_arrays(None)
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        results = pool.map(_disk_arrays, range(2))
    for nodes, cells in results:
        np.testing.assert_array_equal(nodes, here[0])
        np.testing.assert_array_equal(cells, here[1])


def test_caller_gmsh_session_is_left_alone():
    import gmsh

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.model.add("users_model")
        gmsh.option.setNumber("Mesh.Algorithm", 5)
        shapes.disk(1.0, 0.3)
        assert gmsh.isInitialized()
        assert gmsh.model.getCurrent() == "users_model"
        assert gmsh.option.getNumber("Mesh.Algorithm") == 5
    finally:
        gmsh.finalize()
