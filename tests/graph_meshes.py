"""Small gmsh meshes and hypothesis strategies shared by the bsms.graph tests.

Each shape is meshed once per (kind, size) and reused (gmsh calls cost 10-100 ms); a drawn
mesh is one to three shapes side by side, so it may have several components and holes.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from hypothesis import strategies as st

from datagen import shapes
from datagen.mesh import Mesh

SHAPES_2D = {
    "rectangle": lambda size: shapes.rectangle(1.0, 0.6, size),
    "disk": lambda size: shapes.disk(0.5, size),
    "annulus": lambda size: shapes.annulus(0.2, 0.5, size),
    "square with holes": lambda size: shapes.polygon(
        [(0, 0), (1, 0), (1, 1), (0, 1)],
        holes=[[(0.2, 0.2), (0.45, 0.2), (0.45, 0.45), (0.2, 0.45)], [(0.6, 0.55), (0.8, 0.55), (0.7, 0.8)]],
        size=size),
    "glyph": lambda size: shapes.glyph("Bi", size=size / 1.5, height=1.0),
}
SHAPES_3D = {
    "box": lambda size: shapes.box((1.0, 0.6, 0.5), size * 1.5),
    "sphere": lambda size: shapes.sphere(0.5, size * 2.0),
}
SIZES = (0.06, 0.09, 0.14)


@cache
def shape_mesh(kind: str, size: float) -> Mesh:
    """The named shape, meshed at ``size`` (cached)."""
    return {**SHAPES_2D, **SHAPES_3D}[kind](size)


def side_by_side(parts: list[Mesh], gap: float) -> Mesh:
    """Disjoint union of meshes, each shifted along x to start ``gap`` after the previous one."""
    nodes, cells, offset, x = [], [], 0, 0.0
    for part in parts:
        shift = np.zeros(part.dim)
        shift[0] = x - part.nodes[:, 0].min()
        nodes.append(part.nodes + shift)
        cells.append(part.cells + offset)
        offset += part.n_nodes
        x = nodes[-1][:, 0].max() + gap
    return Mesh(np.concatenate(nodes), np.concatenate(cells))


@st.composite
def meshes(draw, dims=(2, 3), max_parts: int = 3) -> Mesh:
    """A mesh of 1..max_parts shapes of one dimension, at sizes from :data:`SIZES`."""
    dim = draw(st.sampled_from(dims))
    kinds = sorted(SHAPES_2D if dim == 2 else SHAPES_3D)
    parts = draw(st.lists(st.tuples(st.sampled_from(kinds), st.sampled_from(SIZES)),
                          min_size=1, max_size=max_parts))
    return side_by_side([shape_mesh(kind, size) for kind, size in parts], gap=0.2)


def path_graph(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(edges (n-1, 2), positions (n, 1)) of the path 0 - 1 - ... - n-1 on the x axis."""
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    return edges, np.arange(n, dtype=np.float64)[:, None]
