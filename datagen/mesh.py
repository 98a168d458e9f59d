"""Simplicial meshes: the shared geometry of the solver, the scenes and the graph hierarchy.

A :class:`Mesh` is ``nodes (N, d)`` float64 and ``cells (C, d+1)`` int64 simplices with
d in {1, 2, 3} (segments, triangles, tetrahedra). It is validated on construction and
immutable afterwards; everything derived from it (adjacency, edges, boundary, components)
is computed on first use and cached.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import warnings
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from datagen.atomic import atomic_path
from datagen.simplex import (
    SIMPLEX_TYPES,
    MeshError,
    as_cells,
    as_nodes,
    check_cells,
    merge_coincident_nodes,
    name_first,
    signed_measures,
    simplex_quality,
)

__all__ = ["Mesh", "MeshError", "EdgeLengthStats"]

_MESHIO_DIM = {"line": 1, "triangle": 2, "tetra": 3}
# Non-simplex meshio cell types a user may reasonably hand us, with their dimension.
_NON_SIMPLEX_DIM = {
    "quad": 2, "polygon": 2, "hexahedron": 3, "wedge": 3, "pyramid": 3,
    "line3": 1, "triangle6": 2, "quad8": 2, "quad9": 2, "tetra10": 3, "hexahedron20": 3,
}


def read_meshio(path: Path):
    """The meshio mesh in the file at ``path``, quietly; MeshError naming the file where it is
    missing or meshio cannot read it."""
    import meshio

    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist")
    chatter = io.StringIO()
    try:  # meshio prints to the console and may even sys.exit on files it cannot parse
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. numpy's overflow where meshio tries an ASCII STL as binary
            return meshio.read(path)
    except (Exception, SystemExit) as exc:
        detail = " ".join(chatter.getvalue().split()) or f"{type(exc).__name__}: {exc}"
        if isinstance(exc, IndexError):  # meshio indexes nodes while it reads some formats
            detail = f"a cell refers to a node the file does not hold ({detail}); re-export the mesh"
        raise MeshError(f"cannot read mesh file {path}: {detail}") from None


def _read_simplices(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, d), cells (C, d+1)) of the top-dimensional simplices in a meshio file, with
    coordinates beyond the mesh dimension dropped when they are zero; MeshError otherwise."""
    raw = read_meshio(path)
    blocks = [(b.type, np.asarray(b.data)) for b in raw.cells if len(b.data)]
    found = sorted({t for t, _ in blocks})
    dims = [_MESHIO_DIM[t] for t, _ in blocks if t in _MESHIO_DIM]
    if not dims:
        raise MeshError(
            f"mesh file {path} has no usable cells: found {found or 'no cells at all'}, but bsms "
            "needs simplices (line, triangle or tetra); triangulate the mesh first"
        )
    dim = max(dims)
    higher = [t for t in found if _NON_SIMPLEX_DIM.get(t, 0) >= dim]
    if higher:
        raise MeshError(
            f"mesh file {path} mixes cell types: {found}; bsms reads one simplex type "
            f"({SIMPLEX_TYPES[dim]} here) and cannot use {higher}: convert them to simplices"
        )
    cells = np.concatenate([data for t, data in blocks if _MESHIO_DIM.get(t) == dim])
    points = np.asarray(raw.points, dtype=np.float64)
    if points.shape[1] < dim:
        raise MeshError(f"mesh file {path} has {points.shape[1]}D points but {SIMPLEX_TYPES[dim]} cells")
    extra = points[:, dim:]
    if extra.size and np.abs(extra).max() > 0:
        raise MeshError(
            f"mesh file {path} holds a {dim}D mesh ({SIMPLEX_TYPES[dim]} cells) embedded in "
            f"{points.shape[1]}D with non-zero coordinates beyond axis {dim}; bsms needs it in "
            f"its own {dim}D coordinates (e.g. z = 0 for a planar mesh)"
        )
    return points[:, :dim], cells


@dataclass(frozen=True)
class EdgeLengthStats:
    """Statistics of the unique mesh edge lengths."""

    min: float
    mean: float
    max: float
    std: float


class Mesh:
    """A validated simplicial mesh.

    Args:
        nodes: (N, d) coordinates, d in {1, 2, 3}; stored as read-only float64.
        cells: (C, d+1) node indices of positively oriented simplices; stored as int64.

    Raises:
        MeshError: naming the problem and the first offending cells or nodes, for wrong
            shapes or arity, non-finite coordinates, indices out of range, nodes used by no
            cell, inverted (negative measure) or degenerate (zero measure) cells, cells
            repeated over the same nodes, and coincident nodes (copies of one point, closer
            than 1e-8 times the median cell size, which cut the mesh apart along them).
    """

    def __init__(self, nodes, cells):
        nodes = as_nodes(nodes)
        cells = as_cells(cells, len(nodes), nodes.shape[1])
        measures = check_cells(nodes, cells)
        nodes.setflags(write=False)
        cells.setflags(write=False)
        measures.setflags(write=False)
        self._nodes, self._cells, self._measures = nodes, cells, measures

    @classmethod
    def from_arrays(cls, nodes, cells, *, drop_unused: bool = False, orient: bool = False,
                    merge_coincident: bool = False) -> Mesh:
        """Build a mesh from raw arrays, optionally repairing what a generator leaves behind.

        merge_coincident: join nodes that are copies of one point (see :func:`coincident_nodes`);
            each group keeps its smallest index, and the copies become unused nodes (so
            drop them with ``drop_unused``).
        drop_unused: remove nodes that no cell uses (renumbering the rest in order).
        orient: reorder the nodes of every negatively oriented cell. Only for meshes known to
            be untangled (from a mesher); it would hide genuinely inverted cells.
        """
        nodes = as_nodes(nodes)
        cells = as_cells(cells, len(nodes), nodes.shape[1])
        if merge_coincident:
            cells = merge_coincident_nodes(nodes, cells)
        if drop_unused:
            used = np.unique(cells)
            renumber = np.full(len(nodes), -1, dtype=np.int64)
            renumber[used] = np.arange(used.size)
            nodes, cells = nodes[used], renumber[cells]
        if orient:
            cells = cells.copy()
            flip = signed_measures(nodes, cells) < 0
            cells[flip, -2:] = cells[flip][:, [-1, -2]]
        return cls(nodes, cells)

    # ----------------------------------------------------------------- basic data
    @property
    def nodes(self) -> np.ndarray:
        """(N, d) float64 node coordinates (read-only)."""
        return self._nodes

    @property
    def cells(self) -> np.ndarray:
        """(C, d+1) int64 node indices, positively oriented (read-only)."""
        return self._cells

    @property
    def dim(self) -> int:
        return self._nodes.shape[1]

    @property
    def n_nodes(self) -> int:
        return self._nodes.shape[0]

    @property
    def n_cells(self) -> int:
        return self._cells.shape[0]

    @property
    def cell_measures(self) -> np.ndarray:
        """(C,) positive lengths / areas / volumes."""
        return self._measures

    @property
    def cell_type(self) -> str:
        """meshio name of the cells: 'line', 'triangle' or 'tetra'."""
        return SIMPLEX_TYPES[self.dim]

    def __repr__(self) -> str:
        return f"Mesh(dim={self.dim}, n_nodes={self.n_nodes}, n_cells={self.n_cells})"

    @cached_property
    def topology_hash(self) -> str:
        """sha256 of (node count, cells): equal for meshes with the same connectivity."""
        digest = hashlib.sha256()
        digest.update(np.int64(self.n_nodes).tobytes())
        digest.update(np.ascontiguousarray(self._cells).tobytes())
        return digest.hexdigest()

    # ----------------------------------------------------------------- edges and adjacency
    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) int64 unique undirected edges, ``i < j``, sorted lexicographically."""
        k = self.dim + 1
        pairs = np.concatenate(
            [self._cells[:, [a, b]] for a in range(k) for b in range(a + 1, k)], axis=0
        )
        pairs.sort(axis=1)
        keys = np.sort(pairs[:, 0] * self.n_nodes + pairs[:, 1])  # sort + drop repeats: np.unique is slower
        keys = keys[np.r_[True, keys[1:] != keys[:-1]]]
        edges = np.stack([keys // self.n_nodes, keys % self.n_nodes], axis=1)
        edges.setflags(write=False)
        return edges

    @cached_property
    def edge_lengths(self) -> np.ndarray:
        """(E,) length of each edge in :attr:`edges`."""
        lengths = np.linalg.norm(self._nodes[self.edges[:, 1]] - self._nodes[self.edges[:, 0]], axis=1)
        lengths.setflags(write=False)
        return lengths

    @cached_property
    def edge_length_stats(self) -> EdgeLengthStats:
        lengths = self.edge_lengths
        return EdgeLengthStats(
            min=float(lengths.min()), mean=float(lengths.mean()),
            max=float(lengths.max()), std=float(lengths.std()),
        )

    @cached_property
    def _adjacency(self) -> sp.csr_matrix:
        n = self.n_nodes
        rows = np.concatenate([self.edges[:, 0], self.edges[:, 1]])
        cols = np.concatenate([self.edges[:, 1], self.edges[:, 0]])
        adj = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
        adj.sort_indices()
        return adj

    @cached_property
    def _adjacency_self_loops(self) -> sp.csr_matrix:
        adj = (self._adjacency + sp.identity(self.n_nodes, format="csr")).tocsr()
        adj.sort_indices()
        return adj

    def adjacency(self, self_loops: bool = False) -> sp.csr_matrix:
        """(N, N) node-node adjacency through shared cells, CSR with ones as values.

        self_loops: include the diagonal (a node is its own neighbour). The matrix is cached
        and shared: do not modify it in place.
        """
        return self._adjacency_self_loops if self_loops else self._adjacency

    @cached_property
    def node_degree(self) -> np.ndarray:
        """(N,) number of mesh neighbours of each node."""
        return np.diff(self._adjacency.indptr)

    # ----------------------------------------------------------------- components
    @cached_property
    def _components(self) -> tuple[int, np.ndarray]:
        count, labels = csgraph.connected_components(self._adjacency, directed=False)
        labels = labels.astype(np.int64)
        labels.setflags(write=False)
        return int(count), labels

    @property
    def n_components(self) -> int:
        """Number of connected components (through shared edges)."""
        return self._components[0]

    @property
    def component_labels(self) -> np.ndarray:
        """(N,) component index of each node, numbered by first appearance."""
        return self._components[1]

    # ----------------------------------------------------------------- boundary
    @cached_property
    def _boundary(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d, k = self.dim, self.dim + 1
        # Facet j of a cell is the cell without its j-th node; that node is the "opposite" one.
        local = np.array([[m for m in range(k) if m != j] for j in range(k)])
        facets = self._cells[:, local].reshape(-1, d)  # (C*k, d), cell-major
        opposite = self._cells.reshape(-1)
        owner = np.repeat(np.arange(self.n_cells), k)
        sorted_facets = np.sort(facets, axis=1)
        order = np.lexsort(sorted_facets.T[::-1])  # equal facets become neighbours
        ordered = sorted_facets[order]
        run = np.r_[True, (ordered[1:] != ordered[:-1]).any(axis=1)]
        run_id = np.cumsum(run) - 1
        counts = np.bincount(run_id)
        shared = np.empty(len(facets), dtype=np.int64)
        shared[order] = counts[run_id]
        if (counts > 2).any():
            bad = np.unique(owner[shared > 2])
            raise MeshError(
                f"non-manifold mesh: some facets are shared by more than two cells, in {name_first(bad, 'cells')}"
            )
        on_boundary = shared == 1
        facets, opposite, owner = facets[on_boundary], opposite[on_boundary], owner[on_boundary]
        x = self._nodes
        away = x[facets].mean(axis=1) - x[opposite]  # points out of the owning cell
        if d == 1:
            normals = np.sign(away)
        elif d == 2:
            tangent = x[facets[:, 1]] - x[facets[:, 0]]
            normals = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
        else:
            normals = np.cross(x[facets[:, 1]] - x[facets[:, 0]], x[facets[:, 2]] - x[facets[:, 0]])
        inward = (normals * away).sum(axis=1) < 0
        normals[inward] *= -1
        if d >= 2:  # order facet nodes so that their orientation gives the outward normal
            facets = facets.copy()
            facets[inward, -2:] = facets[inward][:, [-1, -2]]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        for arr in (facets, normals, owner):
            arr.setflags(write=False)
        return facets, normals, owner

    @property
    def boundary_facets(self) -> np.ndarray:
        """(F, d) node indices of the boundary facets (points, segments or triangles).

        Ordered so that their orientation matches the outward normal (in 2D the domain lies
        to the left of each segment: outer boundaries run counter-clockwise).
        """
        return self._boundary[0]

    @property
    def boundary_normals(self) -> np.ndarray:
        """(F, d) outward unit normals of :attr:`boundary_facets`."""
        return self._boundary[1]

    @property
    def boundary_facet_cells(self) -> np.ndarray:
        """(F,) the cell each boundary facet belongs to."""
        return self._boundary[2]

    @cached_property
    def boundary_facet_measures(self) -> np.ndarray:
        """(F,) size of each boundary facet (1 for points, length, area)."""
        facets = self.boundary_facets
        if self.dim == 1:
            return np.ones(len(facets))
        x = self._nodes[facets]
        if self.dim == 2:
            return np.linalg.norm(x[:, 1] - x[:, 0], axis=1)
        return 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)

    @cached_property
    def boundary_node_mask(self) -> np.ndarray:
        """(N,) True for nodes on a boundary facet."""
        mask = np.zeros(self.n_nodes, dtype=bool)
        mask[self.boundary_facets.ravel()] = True
        mask.setflags(write=False)
        return mask

    @cached_property
    def boundary_node_normals(self) -> np.ndarray:
        """(N, d) unit outward normals at boundary nodes (facet-measure weighted mean), 0 inside."""
        acc = np.zeros_like(self._nodes)
        weighted = self.boundary_normals * self.boundary_facet_measures[:, None]
        for j in range(self.boundary_facets.shape[1]):
            np.add.at(acc, self.boundary_facets[:, j], weighted)
        norm = np.linalg.norm(acc, axis=1, keepdims=True)
        normals = np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)
        normals.setflags(write=False)
        return normals

    # ----------------------------------------------------------------- quality
    @cached_property
    def cell_quality(self) -> np.ndarray:
        """(C,) measure over that of the regular simplex with the same RMS edge length.

        1 for equilateral cells, towards 0 for slivers.
        """
        return simplex_quality(self._nodes, self._cells)

    # ----------------------------------------------------------------- I/O
    @classmethod
    def read(cls, path, *, orient: bool = False, merge_coincident: bool = False) -> Mesh:
        """Read the top-dimensional simplices of any meshio-readable file.

        Lower-dimensional cells (boundary lines, points) are ignored and nodes they alone use
        are dropped; coordinate columns that are zero beyond the mesh dimension are dropped
        (a planar mesh stored with z = 0 becomes 2D). A file whose cells are all negatively
        oriented is flipped as a whole (a convention); ``orient=True`` flips every negative
        cell, for files known to be untangled but inconsistently ordered. Coincident nodes
        (a mesh exported without merging its seams) are an error unless ``merge_coincident``.
        """
        path = Path(path)
        points, cells = _read_simplices(path)
        dim = points.shape[1]
        try:
            cells = as_cells(cells, len(points), dim)
        except MeshError as exc:
            raise MeshError(f"mesh file {path}: {exc}") from None
        measures = signed_measures(points, cells)
        if (measures < 0).all():
            cells = cells.copy()
            cells[:, -2:] = cells[:, [-1, -2]]
        try:
            return cls.from_arrays(points, cells, drop_unused=True, orient=orient,
                                   merge_coincident=merge_coincident)
        except MeshError as exc:
            raise MeshError(f"mesh file {path}: {exc}") from None

    def write(self, path, *, point_data: dict | None = None, cell_data: dict | None = None,
              file_format: str | None = None) -> None:
        """Write through meshio (format from the suffix unless given); points are padded to 3D.

        point_data / cell_data: name -> (N, ...) / (C, ...) arrays. Single-file formats are
        written to a temporary name and renamed, so a crash never leaves a partial file.
        """
        import meshio

        path = Path(path)
        points = np.zeros((self.n_nodes, 3))
        points[:, : self.dim] = self._nodes
        out = meshio.Mesh(
            points,
            [(self.cell_type, np.asarray(self._cells))],
            point_data=dict(point_data or {}),
            cell_data={k: [np.asarray(v)] for k, v in (cell_data or {}).items()},
        )
        if path.suffix.lower() in (".xdmf", ".xmf"):  # writes a companion .h5 named after it
            meshio.write(path, out, file_format=file_format)
            return
        default = "gmsh" if path.suffix.lower() == ".msh" else None  # meshio would pick ANSYS first
        with atomic_path(path, suffix=path.suffix) as tmp:  # the suffix tells meshio the format
            meshio.write(tmp, out, file_format=file_format or default)
