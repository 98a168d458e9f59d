"""Closed triangulated surfaces (a part's STL or OBJ) and the tetrahedral meshes of their insides.

A CAD tool exports a part as its boundary: triangles in 3D, every vertex repeated for each
facet in an STL. :func:`surface_arrays` reads such a file (STL ascii or binary; an OBJ, or any
file meshio reads, whose top cells are triangles -- quads and polygons split into triangles --
with points off the plane z = 0: a planar one is a 2D mesh). :func:`closed_surface` merges the
vertices that are copies of one point (closer than :data:`MERGE_RTOL` times the diagonal of the
part's bounding box), drops the facets that collapse in doing so, and checks that what is left
bounds a solid: every edge shared by exactly two triangles (closed and manifold), every vertex
on one fan of triangles, the facets of each closed piece oriented consistently and enclosing a
volume; otherwise one :class:`~datagen.mesh.MeshError` names the file, what is wrong and how to
fix it. :func:`tetrahedralise` meshes the inside with gmsh at a target edge length (the
calibration and options of :mod:`datagen.shapes`): the surface is split into patches at feature
edges sharper than :data:`FEATURE_ANGLE` and remeshed at that length (nodes stay on the given
triangles), or, with ``remesh=False``, kept as the boundary as given. Pieces inside others are
cavities.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from datagen.mesh import Mesh, MeshError, read_meshio
from datagen.shapes import _check_sizes, _gmsh_session, _mesh

__all__ = ["ClosedSurface", "FEATURE_ANGLE", "MERGE_RTOL", "SURFACE_SUFFIXES", "closed_surface",
           "read_surface", "surface_arrays", "tetrahedralise", "volume_mesh"]

SURFACE_SUFFIXES = (".stl",)
"""File suffixes that always hold a surface in 3D, whatever its coordinates (other files of
triangles hold one where a point lies off the plane z = 0, else they are 2D meshes)."""
MERGE_RTOL = 1e-6
"""Vertices closer than this times the part's bounding-box diagonal are copies of one point."""
FEATURE_ANGLE = 40.0
"""Degrees between neighbouring facets' normals above which their edge is kept as a feature edge
when the surface is remeshed."""
FIX = ("export the part from the CAD tool as a closed solid (a watertight STL, facets oriented consistently), "
       "or give a tetrahedral mesh (.msh, .vtu) instead")


def _is_face(cell_type: str) -> bool:
    """meshio's names of the linear faces read as triangles (quads and polygons split into fans)."""
    return cell_type in ("triangle", "quad") or cell_type.startswith("polygon")


def _triangles_of(raw) -> np.ndarray | None:
    """(F, 3) triangles of a meshio mesh whose top cells are linear faces, or None where it holds
    cells of any other kind above lines (tetrahedra, hexahedra, quadratic faces)."""
    blocks = [(b.type, np.asarray(b.data)) for b in raw.cells if len(b.data)]
    others = [t for t, _ in blocks if not _is_face(t) and t != "vertex" and not t.startswith("line")]
    faces = [d for t, d in blocks if _is_face(t)]
    if not faces or others:
        return None
    fans = [np.stack([d[:, 0], d[:, k], d[:, k + 1]], axis=1) for d in faces for k in range(1, d.shape[1] - 1)]
    return np.concatenate(fans).astype(np.int64)


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of a Wavefront OBJ file: its ``v`` vertices and ``f`` faces (``v``,
    ``v/vt``, ``v//vn``, ``v/vt/vn`` corners, 1-based or negative (relative) indices, polygons split
    into fans); texture coordinates, normals, groups and materials are ignored."""
    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist")
    points, fans = [], []
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        words = line.split("#", 1)[0].split()
        try:
            if words[:1] == ["v"] and len(words) >= 4:
                points.append([float(w) for w in words[1:4]])
            elif words[:1] == ["f"] and len(words) >= 4:
                corners = [int(w.split("/", 1)[0]) for w in words[1:]]
                corners = [c - 1 if c > 0 else len(points) + c for c in corners]  # -1: the last vertex so far
                fans += [(corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1)]
            elif words[:1] in (["v"], ["f"]):
                raise ValueError("a vertex needs three coordinates, a face three corners")
        except ValueError as exc:
            raise MeshError(f"cannot read surface file {path}: line {number}: {exc}") from None
    if not fans:
        raise MeshError(f"surface file {path} holds no faces; {FIX}")
    return np.array(points, dtype=np.float64).reshape(-1, 3), np.array(fans, dtype=np.int64)


def surface_arrays(path) -> tuple[np.ndarray, np.ndarray] | None:
    """(points (N, 3), triangles (F, 3)) as a file at ``path`` holds them, where it holds a surface
    in 3D: an STL file, or an OBJ file or any meshio file whose top cells are triangles (or quads
    and polygons) with some point off the plane z = 0; None for any other mesh (tetrahedra, or a
    planar mesh that :meth:`Mesh.read` reads as 2D). MeshError where the file cannot be read."""
    path = Path(path)
    if path.suffix.lower() == ".obj":  # meshio's reader refuses files with fewer normals than vertices
        points, triangles = _read_obj(path)
    else:
        raw = read_meshio(path)
        triangles = _triangles_of(raw)
        if triangles is None and path.suffix.lower() in SURFACE_SUFFIXES:
            raise MeshError(f"surface file {path} holds no triangles; {FIX}")
        points = np.asarray(raw.points, dtype=np.float64)
        if triangles is None or points.ndim != 2 or points.shape[1] < 2:
            return None
        points = np.pad(points, ((0, 0), (0, max(0, 3 - points.shape[1]))))[:, :3]
    if path.suffix.lower() in SURFACE_SUFFIXES or np.any(points[:, 2] != 0):
        return points, triangles
    return None


@dataclass(frozen=True)
class ClosedSurface:
    """A checked closed surface: ``points`` (N, 3) float64, ``triangles`` (F, 3) int64 (every
    vertex used), ``shell`` (F,) the closed piece each triangle belongs to, ``inside`` (S,) for
    each piece the piece it lies directly inside (-1: none), ``path`` the file it came from."""

    points: np.ndarray
    triangles: np.ndarray
    shell: np.ndarray
    inside: np.ndarray
    path: Path | None = None

    @property
    def n_shells(self) -> int:
        return len(self.inside)

    @property
    def depth(self) -> np.ndarray:
        """(S,) how many pieces enclose each piece: even for outer walls, odd for cavities."""
        depth = np.zeros(self.n_shells, dtype=np.int64)
        for s in range(self.n_shells):
            parent = self.inside[s]
            while parent >= 0:
                depth[s] += 1
                parent = self.inside[parent]
        return depth

    @property
    def shell_volumes(self) -> np.ndarray:
        """(S,) the volume each piece encloses (positive, whatever its orientation)."""
        return np.abs(np.bincount(self.shell, _signed_volumes(self.points, self.triangles), self.n_shells))

    @property
    def volume(self) -> float:
        """The solid's volume: the outer pieces' volumes less their cavities'."""
        sign = np.where(self.depth % 2 == 0, 1.0, -1.0)
        return float(sign @ self.shell_volumes)

    @property
    def extent(self) -> float:
        """The largest extent of its bounding box."""
        return float(np.ptp(self.points, axis=0).max())


def _signed_volumes(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(F,) signed volume of the tetrahedron each triangle spans with the origin (their sum over a
    closed surface is the volume it encloses, positive for outward normals)."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def _merged(points: np.ndarray, triangles: np.ndarray, path) -> tuple[np.ndarray, np.ndarray]:
    """The vertices used, copies of one point merged, and the triangles on them with the facets
    that collapse (two corners on one vertex) dropped."""
    if len(triangles) == 0:
        raise MeshError(f"surface file {path} holds no triangles; {FIX}")
    if triangles.min() < 0 or triangles.max() >= len(points):
        raise MeshError(f"surface file {path}: a facet refers to a vertex the file does not hold; {FIX}")
    if not np.isfinite(points[np.unique(triangles)]).all():
        raise MeshError(f"surface file {path} holds non-finite coordinates (NaN or inf); {FIX}")
    used = np.unique(triangles)
    x = points[used]
    tol = MERGE_RTOL * float(np.linalg.norm(np.ptp(x, axis=0)))
    pairs = cKDTree(x).query_pairs(tol, output_type="ndarray")
    n = len(x)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = csgraph.connected_components(graph, directed=False)
    first = np.full(labels.max() + 1, n)
    np.minimum.at(first, labels, np.arange(n))  # each group becomes its first vertex
    renumber = np.full(len(points), -1, dtype=np.int64)
    renumber[used] = first[labels]
    tri = renumber[triangles]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
    keys = np.sort(tri, axis=1)
    _, once = np.unique(keys, axis=0, return_index=True)
    tri = tri[np.sort(once)]  # a facet repeated over the same vertices: one copy
    if len(tri) == 0:
        raise MeshError(f"surface file {path}: every facet collapses to a line or a point; {FIX}")
    kept = np.unique(tri)
    compact = np.full(n, -1, dtype=np.int64)
    compact[kept] = np.arange(len(kept))
    return x[kept], compact[tri]


def _edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per directed edge of every triangle (3F, in the order (t0 t1), (t1 t2), (t2 t0) per
    triangle): the index of its undirected edge, whether it runs from the smaller vertex to the
    larger; and (E,) how many triangles share each undirected edge."""
    directed = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)
    forward = directed[:, 0] < directed[:, 1]
    keys = np.sort(directed, axis=1)
    _, edge, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return edge.reshape(-1), forward, counts


def _vertex_fans(triangles: np.ndarray, edge: np.ndarray, counts: np.ndarray) -> int:
    """How many vertices have their triangles in more than one fan (pieces of surface that touch
    at that vertex only), on a surface whose edges are all shared by two triangles."""
    n_tri = len(triangles)
    corner_vertex = triangles.reshape(-1)  # corner 3t + k is vertex triangles[t, k]
    order = np.argsort(edge, kind="stable")  # directed edges in pairs of the same undirected edge
    first, second = order[0::2], order[1::2]
    rows, cols = [], []
    for a, b in ((first, second), (second, first)):
        # directed edge 3t + k runs from corner 3t + k to corner 3t + (k + 1) % 3
        start = a
        end = (a // 3) * 3 + (a % 3 + 1) % 3
        for corner in (start, end):  # join the corners of the two triangles at the same vertex
            other = np.where(corner_vertex[b] == corner_vertex[corner], b, (b // 3) * 3 + (b % 3 + 1) % 3)
            rows.append(corner)
            cols.append(other)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_tri, 3 * n_tri))
    _, labels = csgraph.connected_components(graph, directed=False)
    fans = np.bincount(np.unique(np.stack([corner_vertex, labels], axis=1), axis=0)[:, 0])
    return int((fans > 1).sum())


def _edges_that(n: int, verb: str, verb_one: str) -> str:
    """'12 edges belong' / '1 edge belongs'."""
    return f"{n} edges {verb}" if n != 1 else f"1 edge {verb_one}"


def _problems(triangles: np.ndarray) -> list[str]:
    """What keeps the triangles from bounding a solid, in words (empty when nothing does)."""
    edge, forward, counts = _edges(triangles)
    problems = []
    if (counts == 1).any():
        problems.append(f"{_edges_that(int((counts == 1).sum()), 'belong', 'belongs')} to one triangle only: the "
                        "surface has holes")
    if (counts > 2).any():
        problems.append(f"{_edges_that(int((counts > 2).sum()), 'are', 'is')} shared by more than two triangles: the "
                        "surface is not manifold (pieces that touch along an edge, or walls inside the part)")
    if problems:
        return problems
    fans = _vertex_fans(triangles, edge, counts)
    if fans:
        vertices = f"{fans} vertices join" if fans != 1 else "1 vertex joins"
        problems.append(f"{vertices} pieces of the surface that touch only there: the surface is not manifold")
    same_way = np.bincount(edge, forward.astype(np.int64), len(counts))
    if (same_way != 1).any():
        problems.append(f"{_edges_that(int((same_way != 1).sum()), 'run', 'runs')} the same way in both their "
                        "triangles: the facets are not oriented consistently (some face inward)")
    return problems


def _winding(point: np.ndarray, points: np.ndarray, triangles: np.ndarray) -> float:
    """How many times the closed surface (points, triangles) winds around ``point`` (the solid
    angle of its triangles seen from there over 4 pi): +-1 inside, 0 outside."""
    a, b, c = (points[triangles[:, k]] - point for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    div = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb \
        + np.einsum("ij,ij->i", b, c) * la
    return float(2.0 * np.arctan2(det, div).sum() / (4.0 * math.pi))


def _nesting(points: np.ndarray, triangles: np.ndarray, shell: np.ndarray, n_shells: int) -> np.ndarray:
    """(S,) the piece each piece lies directly inside (-1: none), the innermost of those around it."""
    around = [[j for j in range(n_shells)
               if j != i and abs(_winding(points[triangles[shell == i][0, 0]], points, triangles[shell == j])) > 0.5]
              for i in range(n_shells)]
    return np.array([max(found, key=lambda j: len(around[j])) if found else -1 for found in around], dtype=np.int64)


def closed_surface(points, triangles, path=None) -> ClosedSurface:
    """The surface of ``triangles`` over ``points`` (N, 3), its copies of one point merged and the
    facets that collapse dropped, checked to bound a solid (module docstring); MeshError naming
    ``path``, every problem found and the fix otherwise."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if points.ndim != 2 or points.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
        raise MeshError(f"surface file {path}: need (N, 3) points and (F, 3) triangles, got {points.shape} and "
                        f"{triangles.shape}")
    points, triangles = _merged(points, triangles, path)
    problems = _problems(triangles)
    n = len(points)
    pairs = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]]])
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_shells, labels = csgraph.connected_components(graph, directed=False)
    shell = labels[triangles[:, 0]].astype(np.int64)
    volumes = np.abs(np.bincount(shell, _signed_volumes(points, triangles), n_shells))
    flat = volumes <= 1e-9 * float(np.ptp(points, axis=0).max()) ** 3
    if flat.any() and not problems:
        problems.append(f"{int(flat.sum())} of its {n_shells} closed pieces enclose no volume (flat, two-sided "
                        "sheets)")
    if problems:
        raise MeshError(f"surface file {path} does not bound a solid: {', and '.join(problems)}; {FIX}")
    return ClosedSurface(points, triangles, shell, _nesting(points, triangles, shell, n_shells),
                         None if path is None else Path(path))


def read_surface(path) -> ClosedSurface:
    """The closed surface in the file at ``path`` (:func:`surface_arrays`, :func:`closed_surface`)."""
    found = surface_arrays(path)
    if found is None:
        raise MeshError(f"mesh file {path} holds no surface in 3D (triangles off the plane z = 0); give an STL or "
                        "OBJ file of the part, or read a volume mesh with Mesh.read")
    return closed_surface(*found, path)


def _add_surface(gmsh, surface: ClosedSurface, remesh: bool) -> dict[int, list[int]]:
    """The surface as gmsh's discrete entities, one per piece (node tags = point index + 1), split
    into patches at feature edges and reparametrised for remeshing where ``remesh``; the patches'
    surface tags per piece."""
    vertex_shell = np.empty(len(surface.points), dtype=np.int64)
    vertex_shell[surface.triangles] = surface.shell[:, None]
    patches: dict[int, list[int]] = {}
    for s in range(surface.n_shells):
        tag = gmsh.model.addDiscreteEntity(2)
        nodes = np.flatnonzero(vertex_shell == s)
        gmsh.model.mesh.addNodes(2, tag, nodes + 1, surface.points[nodes].ravel())
        gmsh.model.mesh.addElementsByType(tag, 2, [], (surface.triangles[surface.shell == s] + 1).ravel())
        patches[s] = [tag]
    if not remesh:
        return patches
    gmsh.model.mesh.classifySurfaces(math.radians(FEATURE_ANGLE), True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    patches = {}
    for _, patch in gmsh.model.getEntities(2):
        nodes, _, _ = gmsh.model.mesh.getNodes(2, patch, includeBoundary=True)
        mine = nodes[(nodes >= 1) & (nodes <= len(surface.points))].astype(np.int64) - 1
        if len(mine):
            patches.setdefault(int(np.bincount(vertex_shell[mine]).argmax()), []).append(patch)
    return patches


def tetrahedralise(surface: ClosedSurface, size: float, *, remesh: bool = True) -> Mesh:
    """The tetrahedral mesh of the solid ``surface`` bounds, of mean edge length about ``size``
    (gmsh, calibrated as :mod:`datagen.shapes`): its boundary the surface remeshed at ``size`` with
    feature edges kept (``remesh``), or the given triangles themselves. MeshError where gmsh fails
    (most often a surface that intersects itself)."""
    _check_sizes(size, None)
    where = surface.path if surface.path is not None else "the surface"
    with _gmsh_session(f"surface of {where}") as gmsh:
        try:
            patches = _add_surface(gmsh, surface, remesh)
            loops = {s: gmsh.model.geo.addSurfaceLoop(tags) for s, tags in patches.items()}
            if len(loops) != surface.n_shells:
                raise RuntimeError(f"{surface.n_shells} closed pieces became {len(loops)} surface loops")
            depth = surface.depth
            for s in np.flatnonzero(depth % 2 == 0):
                cavities = np.flatnonzero(surface.inside == s)
                gmsh.model.geo.addVolume([loops[int(s)]] + [loops[int(c)] for c in cavities])
            gmsh.model.geo.synchronize()
            return _mesh(gmsh, 3, size, None)
        except Exception as exc:
            detail = " ".join(str(exc).split()) or type(exc).__name__
            raise MeshError(f"gmsh could not tetrahedralise the surface in {where} ({detail}): the surface may "
                            "intersect itself (facets crossing each other, or parts that overlap); repair it in the "
                            "CAD tool, or give a tetrahedral mesh (.msh, .vtu) instead") from None


def volume_mesh(path, size: float, *, remesh: bool = True) -> Mesh:
    """The tetrahedral mesh, at mean edge length about ``size``, of the solid the surface file at
    ``path`` bounds (:func:`read_surface`, :func:`tetrahedralise`)."""
    return tetrahedralise(read_surface(path), size, remesh=remesh)
