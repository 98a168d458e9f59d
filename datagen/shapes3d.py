"""Tetrahedralised solids made by extrusion, with the gmsh Python package (the 3D press family's bodies).

Every function returns a :class:`~datagen.mesh.Mesh` of positively oriented tetrahedra; ``size``
is the target mean edge length, as in :mod:`datagen.shapes` (whose gmsh session, size field and
outline helpers these use: one meshing thread, a fixed seed, so the same arguments always give
the same mesh). The solids:

- :func:`extrude`: a 2D outline with holes (any polygon, a letter's rings from
  :func:`glyph_rings`, an L or T profile from :func:`section_outline`) in the x-y plane, extruded
  along +z by ``depth``; its volume is the outline's area times ``depth`` to round-off.
- :func:`holed_block` and :func:`slotted_block`: a block with a round through hole or a
  round-ended through slot along one axis.
- :func:`cylinder`: a round bar standing along y.

:func:`with_nodes` meshes a solid at the spacing that gives it about a requested node count.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from .mesh import Mesh
from .shapes import _as_ring, _check_sizes, _gmsh_session, _mesh, _nest, _plane_with_holes, _resample_ring, _text_rings

__all__ = ["extrude", "glyph_rings", "section_outline", "holed_block", "slotted_block", "cylinder", "with_nodes",
           "NODES_PER_VOLUME"]

# A gmsh tetrahedralisation of spacing s (datagen.shapes' calibrated size) holds about
# NODES_PER_VOLUME * V / s^3 + (surface nodes) nodes; the interior density, measured on blocks.
NODES_PER_VOLUME = 1.7


def _extruded(gmsh, surfaces: list[int], depth: float, size: float) -> Mesh:
    """The OCC plane ``surfaces`` (fused into one piece where there are several) extruded along +z."""
    occ = gmsh.model.occ
    dimtags = [(2, s) for s in surfaces]
    if len(dimtags) > 1:
        dimtags, _ = occ.fuse(dimtags[:1], dimtags[1:])
    occ.extrude(dimtags, 0.0, 0.0, float(depth))
    occ.synchronize()
    return _mesh(gmsh, 3, size, None)


def _check_depth(depth) -> None:
    if not (isinstance(depth, (int, float)) and math.isfinite(depth) and depth > 0):
        raise ValueError(f"extrusion depth must be a positive number, got {depth!r}")


def extrude(outer, holes: Sequence = (), depth: float = 1.0, size: float = 0.1) -> Mesh:
    """The polygon ``outer`` (K, 2) with ``holes`` (rings inside it) in the x-y plane, extruded along
    +z from z = 0 to ``depth`` and tetrahedralised. Every vertex of the rings is a mesh node."""
    _check_sizes(size, None)
    _check_depth(depth)
    outer = _as_ring(outer, "extruded outer ring")
    holes = [_as_ring(hole, f"extruded hole {k}") for k, hole in enumerate(holes)]
    with _gmsh_session("extrusion") as gmsh:
        return _extruded(gmsh, [_plane_with_holes(gmsh, outer, holes)], depth, size)


def glyph_rings(text: str, spacing: float, *, height: float = 1.0,
                font: str = "DejaVu Sans") -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """The outlines of ``text`` (matplotlib's bundled font, em height ``height``), each an
    (outer ring, holes) pair, their curves resampled to ``spacing`` with corners kept."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"glyph text must be a non-empty string, got {text!r}")
    out = []
    for outer, holes in _nest(_text_rings(text, height, font)):
        rings = [_resample_ring(ring, spacing) for ring in [outer, *holes]]
        if min(len(r) for r in rings) < 3:
            raise ValueError(f"glyph {text!r}: spacing {spacing} is too coarse for height {height}")
        out.append((rings[0], rings[1:]))
    return out


def extrude_rings(shapes: Sequence[tuple[np.ndarray, Sequence[np.ndarray]]], depth: float, size: float) -> Mesh:
    """Several (outer, holes) outlines (e.g. :func:`glyph_rings`) extruded together by ``depth``;
    outlines that touch or overlap become one piece."""
    _check_sizes(size, None)
    _check_depth(depth)
    if not shapes:
        raise ValueError("extrude_rings needs at least one (outer, holes) outline")
    with _gmsh_session("extruded outlines") as gmsh:
        surfaces = [_plane_with_holes(gmsh, _as_ring(outer, "outer ring"), [_as_ring(h, "hole") for h in holes])
                    for outer, holes in shapes]
        return _extruded(gmsh, surfaces, depth, size)


def section_outline(kind: str, width: float, height: float, flange: float, web: float) -> list[list[float]]:
    """The profile of a structural section, counter-clockwise from the origin: ``L`` (an angle: a
    leg ``width`` long and ``flange`` thick on y = 0, a leg ``height`` tall and ``web`` thick on
    x = 0) or ``T`` (a tee: a flange ``width`` wide and ``flange`` thick on top of a web ``web``
    wide, ``height`` tall in all, the web's foot on y = 0 centred at x = width / 2)."""
    if kind not in ("L", "T"):
        raise ValueError(f"section kind must be 'L' or 'T', got {kind!r}")
    if not (0 < flange < height and 0 < web < width):
        raise ValueError(f"section needs 0 < flange < height and 0 < web < width, got flange {flange}, "
                         f"height {height}, web {web}, width {width}")
    if kind == "L":
        ring = [(0, 0), (width, 0), (width, flange), (web, flange), (web, height), (0, height)]
    else:
        a, b, top = (width - web) / 2, (width + web) / 2, height - flange
        ring = [(a, 0), (b, 0), (b, top), (width, top), (width, height), (0, height), (0, top), (a, top)]
    return [[float(x), float(y)] for x, y in ring]


def _cyclic(nodes: np.ndarray, axis: int) -> np.ndarray:
    """Local coordinates whose z is the world's ``axis``, as world coordinates (a cyclic permutation
    of the axes: a rotation, so tetrahedra keep their orientation)."""
    return nodes[:, [(k - axis + 2) % 3 for k in range(3)]]


def _local_extent(extent: Sequence[float], axis: int) -> list[float]:
    return [float(extent[(j + axis + 1) % 3]) for j in range(3)]


def _check_block(extent: Sequence[float], axis: int) -> None:
    if len(extent) != 3 or not all(isinstance(e, (int, float)) and math.isfinite(e) and e > 0 for e in extent):
        raise ValueError(f"block extent must be three positive lengths, got {extent!r}")
    if axis not in (0, 1, 2):
        raise ValueError(f"block feature axis must be 0 (x), 1 (y) or 2 (z), got {axis!r}")


def _cut_block(name: str, extent: Sequence[float], axis: int, size: float, tool: Callable) -> Mesh:
    """The block [0, extent] with the plane outline ``tool(gmsh, a, b)`` (a surface in the local
    x-y plane of a face a x b) cut out of its face and the rest extruded through along ``axis``."""
    _check_sizes(size, None)
    _check_block(extent, axis)
    a, b, depth = _local_extent(extent, axis)
    with _gmsh_session(name) as gmsh:
        occ = gmsh.model.occ
        face = occ.addRectangle(0.0, 0.0, 0.0, a, b)
        cut, _ = occ.cut([(2, face)], [(2, tool(gmsh, a, b))])
        local = _extruded(gmsh, [tag for _, tag in cut], depth, size)
    return Mesh.from_arrays(_cyclic(local.nodes, axis), local.cells, orient=True)


def holed_block(extent: Sequence[float], radius: float, size: float, *, axis: int = 2,
                offset: Sequence[float] = (0.0, 0.0)) -> Mesh:
    """The block [0, extent] (x, y, z lengths) with a round hole of ``radius`` through it along
    ``axis``, its centre ``offset`` (in the face's two other axes, in cyclic order after ``axis``)
    from the middle of the face."""
    def hole(gmsh, a, b):
        centre = (a / 2 + float(offset[0]), b / 2 + float(offset[1]))
        if not (radius > 0 and min(centre[0], a - centre[0], centre[1], b - centre[1]) > radius):
            raise ValueError(f"holed_block: a hole of radius {radius} at {centre} does not fit in the {a} x {b} face")
        return gmsh.model.occ.addDisk(centre[0], centre[1], 0.0, float(radius), float(radius))

    return _cut_block("holed block", extent, axis, size, hole)


def slotted_block(extent: Sequence[float], width: float, length: float, size: float, *, axis: int = 2) -> Mesh:
    """The block [0, extent] with a slot through it along ``axis``: a stadium ``length`` long (along
    the next axis in cyclic order) and ``width`` wide, its ends round, centred in the face."""
    def slot(gmsh, a, b):
        if not (0 < width <= length and length < a and width < b):
            raise ValueError(f"slotted_block: a slot {length} x {width} does not fit in the {a} x {b} face "
                             "(need 0 < width <= length)")
        occ, r = gmsh.model.occ, 0.5 * float(width)
        if length == width:
            return occ.addDisk(a / 2, b / 2, 0.0, r, r)
        ends = [occ.addDisk(a / 2 + s * (length / 2 - r), b / 2, 0.0, r, r) for s in (-1, 1)]
        middle = occ.addRectangle((a - length) / 2 + r, (b - width) / 2, 0.0, float(length) - 2 * r, float(width))
        fused, _ = occ.fuse([(2, middle)], [(2, e) for e in ends])
        return fused[0][1]

    return _cut_block("slotted block", extent, axis, size, slot)


def cylinder(radius: float, height: float, size: float) -> Mesh:
    """A round bar of ``radius`` standing along +y from y = 0 to ``height``, its axis through x = z = 0."""
    _check_sizes(size, None)
    if not (radius > 0 and height > 0):
        raise ValueError(f"cylinder radius and height must be positive, got {radius}, {height}")
    with _gmsh_session("cylinder") as gmsh:
        gmsh.model.occ.addCylinder(0.0, 0.0, 0.0, 0.0, float(height), 0.0, float(radius))
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 3, size, None)


def with_nodes(make: Callable[[float], Mesh], volume: float, nodes: int, tolerance: float = 0.1) -> Mesh:
    """``make(spacing)`` at the spacing that gives about ``nodes`` nodes: a first guess from the
    solid's ``volume`` (:data:`NODES_PER_VOLUME`), then the guess corrected by the count it gave (the
    cube root of the ratio), and where that is still more than ``tolerance`` off, once more along
    the power law through the two counts (thin solids: the surface's nodes grow as spacing^-2).
    Deterministic; the mesh of the three whose count is nearest ``nodes``."""
    if not (volume > 0 and nodes >= 8):
        raise ValueError(f"with_nodes needs a positive volume and at least 8 nodes, got {volume}, {nodes}")
    spacing = [(NODES_PER_VOLUME * volume / nodes) ** (1 / 3)]
    meshes = [make(spacing[0])]
    spacing.append(spacing[0] * (meshes[0].n_nodes / nodes) ** (1 / 3))
    meshes.append(make(spacing[1]))
    counts = [m.n_nodes for m in meshes]
    if abs(counts[1] / nodes - 1) > tolerance and counts[0] != counts[1] and spacing[0] != spacing[1]:
        power = math.log(counts[0] / counts[1]) / math.log(spacing[1] / spacing[0])
        if power > 0:
            meshes.append(make(spacing[1] * (counts[1] / nodes) ** (1 / power)))
    return min(meshes, key=lambda m: abs(m.n_nodes - nodes))
