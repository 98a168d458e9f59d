"""datagen.surface: a part's closed surface (STL ascii and binary, OBJ, meshio files) read, checked
and tetrahedralised; bsms.infer's use of it (a surface for a 3D run meshed at the model's spacing,
refused for a 2D run)."""

from pathlib import Path

import meshio
import numpy as np
import pytest
from surface_files import (
    BOX,
    box_surface,
    icosphere,
    polyhedron_volume,
    triangles,
    write_ascii_stl,
    write_binary_stl,
    write_meshio,
    write_obj,
)

from bsms.infer import InferError, read_mesh
from bsms.infer.surfaces import body_resolution, placed_sizes, tetrahedralise_parts, with_nodes
from datagen.dataset_config import load_dataset_config
from datagen.mesh import MeshError
from datagen.simplex import signed_measures
from datagen.surface import FIX, closed_surface, read_surface, surface_arrays, tetrahedralise, volume_mesh

ROOT = Path(__file__).resolve().parents[1]


def triangle_distance(points, a, b, c):
    """(P,) distance of each point to the nearest of the triangles (a, b, c) (each (T, 3))."""
    best = np.full(len(points), np.inf)
    for k in range(len(a)):
        e0, e1 = b[k] - a[k], c[k] - a[k]
        n = np.cross(e0, e1)
        n /= np.linalg.norm(n)
        d = points - a[k]
        h = d @ n
        q = d - h[:, None] * n  # projection onto the plane, then barycentric coordinates
        m = np.array([[e0 @ e0, e0 @ e1], [e0 @ e1, e1 @ e1]])
        uv = np.linalg.solve(m, np.stack([q @ e0, q @ e1]))
        inside = (uv[0] >= -1e-12) & (uv[1] >= -1e-12) & (uv.sum(0) <= 1 + 1e-12)
        best = np.where(inside, np.minimum(best, np.abs(h)), best)
    return best


def on_box_surface(nodes, lower, upper, tol):
    inside = np.all((nodes >= lower - tol) & (nodes <= upper + tol), axis=1)
    on_a_face = np.any((np.abs(nodes - lower) <= tol) | (np.abs(nodes - upper) <= tol), axis=1)
    return inside & on_a_face


# --------------------------------------------------------------------------- reading and meshing
def _box_file(kind, folder):
    points, quads = box_surface()
    tris = triangles(quads)
    return {
        "stl_ascii": lambda: write_ascii_stl(folder / "box.stl", points, tris),
        "stl_binary": lambda: write_binary_stl(folder / "box.stl", points, tris),
        "obj_quads": lambda: write_obj(folder / "box.obj", points, quads),
        "vtu": lambda: write_meshio(folder / "box.vtu", points, tris),
    }[kind]()


@pytest.mark.parametrize("kind", ["stl_ascii", "stl_binary", "obj_quads", "vtu"])
def test_a_box_in_every_format_fills_exactly_its_volume(kind, tmp_path):
    path = _box_file(kind, tmp_path)
    surface = read_surface(path)
    assert surface.points.shape == (8, 3) and len(surface.triangles) == 12, "STL's repeated vertices merged"
    assert surface.volume == pytest.approx(1.0, rel=1e-14)
    size = 0.25
    mesh = volume_mesh(path, size)
    assert mesh.dim == 3 and mesh.n_components == 1
    assert mesh.cell_measures.sum() == pytest.approx(1.0, rel=1e-12), "planar faces: the volume is exact"
    assert (signed_measures(mesh.nodes, mesh.cells) > 0).all()
    boundary = mesh.nodes[mesh.boundary_node_mask]
    assert on_box_surface(boundary, np.zeros(3), np.array(BOX), 1e-12).all()
    assert 0.75 * size <= mesh.edge_length_stats.mean <= 1.25 * size
    assert mesh.boundary_facets.shape[0] > 12, "the surface remeshed at the size asked for"


def test_a_triangulated_sphere_kept_as_given_fills_its_polyhedrons_volume(tmp_path):
    points, tris = icosphere(3)  # 1280 facets, edges about 0.08
    path = write_binary_stl(tmp_path / "ball.stl", points, tris)
    surface = read_surface(path)
    assert len(surface.points) == len(points)
    mesh = tetrahedralise(surface, 0.1, remesh=False)
    assert mesh.cell_measures.sum() == pytest.approx(polyhedron_volume(surface.points, surface.triangles), rel=1e-12)
    assert (signed_measures(mesh.nodes, mesh.cells) > 0).all()
    kept = {tuple(sorted(map(tuple, mesh.nodes[f]))) for f in mesh.boundary_facets}
    assert kept == {tuple(sorted(map(tuple, surface.points[t]))) for t in surface.triangles}


def test_a_triangulated_sphere_remeshed_keeps_its_nodes_on_the_given_facets(tmp_path):
    points, tris = icosphere(2, radius=0.5)  # 320 facets
    path = write_ascii_stl(tmp_path / "ball.stl", points, tris)
    surface = read_surface(path)
    size = 0.12
    mesh = tetrahedralise(surface, size)
    boundary = mesh.nodes[mesh.boundary_node_mask]
    a, b, c = (surface.points[surface.triangles[:, k]] for k in range(3))
    assert triangle_distance(boundary, a, b, c).max() <= 1e-9
    polyhedron = polyhedron_volume(surface.points, surface.triangles)
    assert surface.volume == pytest.approx(polyhedron, rel=1e-14)
    # new boundary triangles are chords of the faceted sphere: a little less volume, never more
    assert 0.98 * polyhedron <= mesh.cell_measures.sum() <= polyhedron * (1 + 1e-12)
    assert (signed_measures(mesh.nodes, mesh.cells) > 0).all()
    assert 0.7 * size <= mesh.edge_length_stats.mean <= 1.3 * size


def test_a_hollow_part_keeps_its_cavity_and_separate_parts_stay_apart(tmp_path):
    outer, quads = box_surface()
    inner, _ = box_surface((0.25, 0.5, 0.1), (0.75, 1.5, 0.4))
    apart, _ = box_surface((3.0, 0.0, 0.0), (4.0, 1.0, 1.0))
    tris = triangles(quads)
    path = write_ascii_stl(tmp_path / "parts.stl", np.vstack([outer, inner, apart]),
                           np.vstack([tris, tris[:, ::-1] + 8, tris + 16]))  # the cavity's facets face into it
    surface = read_surface(path)
    assert surface.n_shells == 3 and surface.inside.tolist() == [-1, 0, -1]
    expected = 1.0 - 0.5 * 1.0 * 0.3 + 1.0
    assert surface.volume == pytest.approx(expected, rel=1e-14)
    for remesh in (True, False):
        mesh = tetrahedralise(surface, 0.2, remesh=remesh)
        assert mesh.cell_measures.sum() == pytest.approx(expected, rel=1e-12)
        assert mesh.n_components == 2


def test_near_copies_of_a_vertex_are_merged_and_collapsed_facets_dropped(tmp_path):
    points, quads = box_surface()
    tris = triangles(quads)
    copies = points[tris].reshape(-1, 3) * (1 + 1e-9 * np.random.default_rng(0).standard_normal((36, 3)))
    facets = np.arange(36).reshape(-1, 3)
    collapsed = np.array([[0, 0, 1], [2, 3, 2]])  # a facet on two copies of one vertex, one on a line
    surface = closed_surface(copies, np.vstack([facets, collapsed]), "copies.stl")
    assert surface.points.shape == (8, 3) and len(surface.triangles) == 12
    assert surface.volume == pytest.approx(1.0, rel=1e-8)


def test_which_files_hold_surfaces(tmp_path):
    points, quads = box_surface()
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    write_meshio(tmp_path / "flat.vtu", flat, np.array([[0, 1, 2]]))
    assert surface_arrays(tmp_path / "flat.vtu") is None, "a planar triangle mesh is a 2D mesh"
    meshio.write(tmp_path / "tet.vtu", meshio.Mesh(np.vstack([flat, [0, 0, 1]]), [("tetra", np.array([[0, 1, 2, 3]]))]))
    assert surface_arrays(tmp_path / "tet.vtu") is None
    found = surface_arrays(write_obj(tmp_path / "box.obj", points, quads))
    assert found is not None and found[1].shape == (12, 3)
    assert surface_arrays(write_obj(tmp_path / "flat.obj", flat, [[0, 1, 2]])) is None, "a 2D mesh, as Mesh.read reads it"
    relative = tmp_path / "relative.obj"  # negative indices count back from the last vertex; v/vt/vn corners
    lines = [f"v {x} {y} {z}" for x, y, z in points] + ["vt 0 0"]
    lines += ["f " + " ".join(f"{i - 8}/1/1" for i in quad) for quad in quads]
    relative.write_text("# a part\ng box\n" + "\n".join(lines) + "\n")
    assert read_surface(relative).volume == pytest.approx(1.0, rel=1e-14)
    write_meshio(tmp_path / "flat.stl", flat, np.array([[0, 1, 2]]))
    assert surface_arrays(tmp_path / "flat.stl") is not None, "an STL is always a surface in 3D"
    (tmp_path / "empty.stl").write_text("solid nothing\nendsolid nothing\n")
    with pytest.raises(MeshError, match="holds no triangles"):
        read_surface(tmp_path / "empty.stl")


# --------------------------------------------------------------------------- errors
def test_an_open_surface_is_refused_naming_its_open_edges(tmp_path):
    points, quads = box_surface()
    path = write_ascii_stl(tmp_path / "open.stl", points, triangles(quads[1:]))  # one face removed
    with pytest.raises(MeshError) as info:
        read_surface(path)
    assert str(info.value) == (f"surface file {path} does not bound a solid: 4 edges belong to one triangle only: "
                               f"the surface has holes; {FIX}")
    assert FIX == ("export the part from the CAD tool as a closed solid (a watertight STL, facets oriented "
                   "consistently), or give a tetrahedral mesh (.msh, .vtu) instead")


def test_a_non_manifold_surface_is_refused(tmp_path):
    points, quads = box_surface((0, 0, 0), (1, 1, 1))
    tris = triangles(quads)
    touching = {"edge": (1.0, 1.0, 0.0), "vertex": (1.0, 1.0, 1.0)}
    expected = {
        "edge": "1 edge is shared by more than two triangles: the surface is not manifold (pieces that touch along "
                "an edge, or walls inside the part)",
        "vertex": "1 vertex joins pieces of the surface that touch only there: the surface is not manifold",
    }
    for where, corner in touching.items():
        other, _ = box_surface(corner, np.add(corner, 1.0))
        path = write_ascii_stl(tmp_path / f"{where}.stl", np.vstack([points, other]), np.vstack([tris, tris + 8]))
        with pytest.raises(MeshError) as info:
            read_surface(path)
        assert str(info.value) == f"surface file {path} does not bound a solid: {expected[where]}; {FIX}"


def test_inconsistently_oriented_facets_are_refused(tmp_path):
    points, quads = box_surface()
    tris = triangles(quads)
    tris[3] = tris[3, ::-1]
    path = write_obj(tmp_path / "flipped.obj", points, tris)
    with pytest.raises(MeshError) as info:
        read_surface(path)
    assert str(info.value) == (f"surface file {path} does not bound a solid: 3 edges run the same way in both their "
                               f"triangles: the facets are not oriented consistently (some face inward); {FIX}")


def test_a_self_intersecting_surface_is_refused_by_gmsh_with_the_reason(tmp_path):
    points, quads = box_surface((0, 0, 0), (1, 1, 1))
    overlapping, _ = box_surface((0.5, 0.5, 0.5), (1.5, 1.5, 1.5))
    tris = triangles(quads)
    path = write_ascii_stl(tmp_path / "overlap.stl", np.vstack([points, overlapping]), np.vstack([tris, tris + 8]))
    surface = read_surface(path)  # each piece is closed: only meshing finds that they cross
    with pytest.raises(MeshError) as info:
        tetrahedralise(surface, 0.25)
    message = str(info.value)
    assert message.startswith(f"gmsh could not tetrahedralise the surface in {path} (")
    assert message.endswith("): the surface may intersect itself (facets crossing each other, or parts that "
                            "overlap); repair it in the CAD tool, or give a tetrahedral mesh (.msh, .vtu) instead")


# --------------------------------------------------------------------------- inference
def test_a_surface_given_to_a_2d_run_is_refused(tmp_path):
    points, quads = box_surface()
    path = write_binary_stl(tmp_path / "part.stl", points, triangles(quads))
    with pytest.raises(InferError) as info:
        read_mesh(path, 2, "runs/press")
    assert str(info.value) == (f"mesh file {path} is a surface in 3D (triangles off the plane z = 0) but run "
                               "runs/press was trained on 2D meshes; give a 2D mesh (.msh, .vtu; a 2D mesh with z = 0)")
    open_path = write_ascii_stl(tmp_path / "open.stl", points, triangles(quads[1:]))
    with pytest.raises(InferError, match="4 edges belong to one triangle only"):
        read_mesh(open_path, 3, "runs/balls")


def test_a_surface_for_a_3d_run_is_meshed_at_the_familys_spacing_where_the_family_scales_it(tmp_path):
    dconfig = load_dataset_config(ROOT / "configs" / "datasets" / "balls_quick.yaml")
    sizes, params = placed_sizes(dconfig, {}, 1)
    spacing = body_resolution(dconfig, params)["spacing"]
    assert spacing == dconfig["params"]["body_size"] == 0.075 and sizes == [params["sizes"][0]]
    points, quads = box_surface()
    part = tmp_path / "part.stl"
    surface = read_mesh(write_ascii_stl(part, 10.0 * points, triangles(quads)), 3, "runs/balls")  # a 20 mm part
    volumes = tetrahedralise_parts({part: surface}, [[part]], dconfig, {}, {part: tmp_path / "part_tetrahedra.vtu"})
    done = volumes[part]
    scale = sizes[0] / 20.0
    assert done.size == pytest.approx(spacing / scale) and done.spacing == spacing
    assert 0.7 * spacing <= done.mesh.edge_length_stats.mean * scale <= 1.3 * spacing
    assert done.mesh.cell_measures.sum() == pytest.approx(1000.0 * 1.0, rel=1e-12)
    assert done.file.is_file() and read_mesh(done.file, 3, "runs/balls").n_nodes == done.mesh.n_nodes
    assert done.record()["nodes"] == done.mesh.n_nodes


def test_a_family_that_meshes_its_bodies_to_a_node_count_gets_parts_of_about_that_count(tmp_path):
    dconfig = load_dataset_config(ROOT / "configs" / "datasets" / "balls_quick.yaml")
    assert body_resolution(dconfig, {"nodes": 600}) == {"nodes": 600}, "the placed scene's parameters first"
    assert body_resolution(dconfig, {}) == {"spacing": 0.075}
    points, tris = icosphere(2)
    mesh, size = with_nodes(read_surface(write_binary_stl(tmp_path / "ball.stl", 40.0 * points, tris)), 600)
    assert abs(mesh.n_nodes / 600 - 1) <= 0.15
    assert 0.7 * size <= mesh.edge_length_stats.mean <= 1.3 * size
