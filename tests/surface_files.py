"""Closed surfaces and the files CAD tools write them to (STL ascii and binary, OBJ, meshio), shared
by the surface meshing and inference tests."""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

BOX = (1.0, 2.0, 0.5)


def box_surface(lower=(0.0, 0.0, 0.0), upper=BOX):
    """(8, 3) corners and (12, 3) outward triangles of an axis-aligned box."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    return lower + corners * (upper - lower), quads


def triangles(quads):
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def icosphere(subdivisions=2, radius=1.0):
    """A triangulated sphere: an icosahedron split ``subdivisions`` times, vertices on the sphere."""
    g = (1 + 5**0.5) / 2
    points = [[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g], [0, -1, -g], [0, 1, -g],
              [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]]
    faces = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
             [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
             [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    points = [np.array(p, float) / np.linalg.norm(p) for p in points]
    for _ in range(subdivisions):
        middle, split = {}, []
        for a, b, c in faces:
            ab, bc, ca = (_midpoint(points, middle, u, v) for u, v in ((a, b), (b, c), (c, a)))
            split += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = split
    return radius * np.array(points), np.array(faces)


def _midpoint(points: list, middle: dict, a: int, b: int) -> int:
    """The index of the point on the unit sphere over edge (a, b), added to ``points`` once."""
    key = (min(a, b), max(a, b))
    if key not in middle:
        p = points[a] + points[b]
        points.append(p / np.linalg.norm(p))
        middle[key] = len(points) - 1
    return middle[key]


def polyhedron_volume(points, tris):
    a, b, c = (points[tris[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6)


def write_ascii_stl(path, points, tris):
    """An ASCII STL as CAD tools write it: each facet with its normal and its three vertices."""
    lines = ["solid part"]
    for tri in tris:
        a, b, c = points[tri]
        n = np.cross(b - a, c - a)
        lines += [f"  facet normal {' '.join(f'{v:.9e}' for v in n / np.linalg.norm(n))}", "    outer loop"]
        lines += ["      vertex " + " ".join(repr(float(v)) for v in vertex) for vertex in points[tri]]
        lines += ["    endloop", "  endfacet"]
    Path(path).write_text("\n".join(lines + ["endsolid part", ""]))
    return path


def write_binary_stl(path, points, tris):
    """A binary STL: 80-byte header, facet count, per facet its normal, vertices (float32), 2 bytes."""
    facets = np.zeros(len(tris), dtype=[("normal", "<f4", (3,)), ("facet", "<f4", (3, 3)), ("attr", "<u2")])
    facets["facet"] = points[tris]
    a, b, c = (points[tris[:, k]] for k in range(3))
    facets["normal"] = np.cross(b - a, c - a)
    with open(path, "wb") as f:
        f.write(b"binary STL written by a test".ljust(80, b" "))
        f.write(np.uint32(len(tris)).tobytes())
        f.write(facets.tobytes())
    return path


def write_obj(path, points, faces):
    """An OBJ with 1-based 'f v//vn' faces (quads allowed)."""
    lines = ["v " + " ".join(repr(float(v)) for v in point) for point in points] + ["vn 0 0 1"]
    lines += ["f " + " ".join(f"{i + 1}//1" for i in face) for face in faces]
    Path(path).write_text("\n".join(lines) + "\n")
    return path


def write_meshio(path, points, tris):
    meshio.write(path, meshio.Mesh(points, [("triangle", tris)]))
    return path
