"""Bi-stride multi-level graphs of a mesh (thesis §4.2), with their transitions (§4.3.2).

:func:`bistride_levels` builds, once per mesh and from its topology alone, the levels of a
BSMS-GNN: level 0 is the mesh graph; level l+1 keeps every other BFS frontier of level l
from a seed per connected component (:mod:`bsms.graph.pooling`) and joins kept nodes within
two hops (all of them, or at most ``max_coarse_degree`` per node: :mod:`bsms.graph.capping`,
for tetrahedral meshes whose coarse levels densify). Each level also stores the down/up
transition operators from/to the level above it (:mod:`bsms.graph.transitions`). Everything is
deterministic for the same inputs, and a hierarchy can be cached on disk (:mod:`bsms.graph.cache`).

Costs: one BFS per level (csgraph), the pooled adjacency R R^T with R = (A+I)[kept, :] for the
coarse edges (compiled bitset rows, :mod:`bsms.graph.native`, or scipy's sparse product), and a
few sparse products for the transitions (a capped level: the integer product, a sort of its pairs
and a few vectorised greedy rounds); MinAve seeding adds the search described in
:mod:`bsms.graph.seeding`. Nothing is dense in the number of nodes.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from bsms.graph.bfs import adjacency_from_edges, bfs_depths, cell_adjacency
from bsms.graph.cache import FORMAT_VERSION, cache_path, hierarchy_key, read_npz, write_npz_atomic
from bsms.graph.capping import capped_coarse_adjacency
from bsms.graph.pooling import bistride_pool, closed_rows, coarse_adjacency
from bsms.graph.seeding import SEEDINGS, component_seeds
from bsms.graph.transitions import Transition, transition_operators
from datagen.config import output_folder
from datagen.mesh import Mesh

__all__ = ["BistrideLevel", "Hierarchy", "bistride_levels", "DEFAULT_MIN_NODES"]

DEFAULT_MIN_NODES = 32
"""``levels="auto"`` stops after the first level with fewer nodes than this."""
_MAX_LEVELS = 64


def edge_index_of(adjacency: sp.csr_matrix) -> np.ndarray:
    """(2, E) int64 directed edges (both directions) of a CSR pattern, sorted by (row, col)."""
    adjacency = adjacency.tocsr()
    adjacency.sort_indices()
    edge_index = np.empty((2, adjacency.nnz), dtype=np.int64)
    edge_index[0] = np.repeat(np.arange(adjacency.shape[0]), np.diff(adjacency.indptr))
    edge_index[1] = adjacency.indices
    return edge_index


@dataclass(frozen=True, eq=False)
class BistrideLevel:
    """One level of a :class:`Hierarchy`; ``n`` = its node count, ``m`` = the previous level's.

    kept: (n,) int64 sorted indices of this level's nodes in the previous level
        (level 0: ``arange(N)``).
    edge_index: (2, E) int64 edges in both directions, no self-loops, sorted.
    node_weights: (n,) float64 accumulated nodal weights w of §4.3.2 (1 on level 0).
    seeds: (C,) int64 BFS seeds, one per component, in the previous level's indices
        (empty on level 0).
    down: previous -> this level, (n, m) weighted averages (None on level 0).
    up: this -> previous level, (m, n) (None on level 0).
    """

    kept: np.ndarray
    edge_index: np.ndarray
    node_weights: np.ndarray
    seeds: np.ndarray
    down: Transition | None = None
    up: Transition | None = None

    @property
    def n_nodes(self) -> int:
        return int(self.kept.size)

    @property
    def n_edges(self) -> int:
        """Number of directed edges (twice the undirected count)."""
        return int(self.edge_index.shape[1])

    @cached_property
    def adjacency(self) -> sp.csr_matrix:
        """(n, n) 0/1 CSR adjacency of this level."""
        n = self.n_nodes
        values = np.ones(self.edge_index.shape[1])
        return sp.csr_matrix((values, (self.edge_index[0], self.edge_index[1])), shape=(n, n))


_LEVEL_ARRAYS = ("kept", "edge_index", "node_weights", "seeds")
_TRANSITION_ARRAYS = ("rows", "cols", "weights")


@dataclass(frozen=True, eq=False)
class Hierarchy:
    """Bi-stride levels of one graph, finest first (see :func:`bistride_levels`).

    levels: the levels, ``levels[0]`` being the input graph.
    component_labels: (N,) int64 connected component of each level-0 node; component c
        keeps at least one node on every level.
    seeding, self_loops, max_coarse_degree: how it was built. key: the cache key (sha256 hex).
    """

    levels: tuple[BistrideLevel, ...]
    component_labels: np.ndarray
    seeding: str
    self_loops: bool
    key: str
    max_coarse_degree: int | None = None

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    @property
    def node_counts(self) -> tuple[int, ...]:
        return tuple(level.n_nodes for level in self.levels)

    @property
    def edge_indices(self) -> tuple[np.ndarray, ...]:
        """(2, E_l) edge index of every level."""
        return tuple(level.edge_index for level in self.levels)

    def finest_indices(self, level: int) -> np.ndarray:
        """(n_level,) level-0 index of each node of ``level``."""
        indices = self.levels[0].kept
        for current in self.levels[1:level + 1]:
            indices = indices[current.kept]
        return indices

    def select(self, values: np.ndarray, level: int) -> np.ndarray:
        """Values of level-0 nodes (N, ...) picked at the nodes of ``level``, e.g. rest positions."""
        return np.asarray(values)[self.finest_indices(level)]

    @cached_property
    def reach(self) -> tuple[sp.csr_matrix, ...]:
        """Per level l < L-1: (n_l, n_{l+1}) 0/1 CSR, sorted indices, of (A_l + I)[:, K]: the kept
        nodes of level l+1 that each level-l node is or touches (what eq. 4.1 carries a contact to)."""
        maps = []
        for finer, coarser in zip(self.levels[:-1], self.levels[1:], strict=True):
            closed = closed_rows(finer.adjacency, coarser.kept).T.tocsr()
            closed.sort_indices()
            maps.append(closed)
        return tuple(maps)

    # ------------------------------------------------------------------ serialisation
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat name -> array mapping (npz-ready, no objects)."""
        meta = {"format": FORMAT_VERSION, "n_levels": self.n_levels, "seeding": self.seeding,
                "self_loops": self.self_loops, "key": self.key}
        if self.max_coarse_degree is not None:
            meta["max_coarse_degree"] = self.max_coarse_degree
        arrays = {"meta": np.array(json.dumps(meta)), "component_labels": self.component_labels}
        for l, level in enumerate(self.levels):
            arrays.update({f"l{l}_{name}": getattr(level, name) for name in _LEVEL_ARRAYS})
            for kind in ("down", "up") if l else ():
                transition = getattr(level, kind)
                arrays.update({f"l{l}_{kind}_{name}": getattr(transition, name)
                               for name in _TRANSITION_ARRAYS})
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Hierarchy:
        meta = json.loads(str(arrays["meta"]))
        if meta.get("format") != FORMAT_VERSION:
            raise ValueError(f"hierarchy format {meta.get('format')} is not {FORMAT_VERSION}; rebuild it")
        levels = []
        for l in range(meta["n_levels"]):
            fields = {name: arrays[f"l{l}_{name}"] for name in _LEVEL_ARRAYS}
            if l:
                m, n = levels[-1].n_nodes, fields["kept"].size
                for kind, shape in (("down", (n, m)), ("up", (m, n))):
                    parts = [arrays[f"l{l}_{kind}_{name}"] for name in _TRANSITION_ARRAYS]
                    fields[kind] = Transition(*parts, shape)
            levels.append(BistrideLevel(**fields))
        return cls(tuple(levels), arrays["component_labels"], meta["seeding"], meta["self_loops"],
                   meta["key"], meta.get("max_coarse_degree"))

    def save(self, path) -> None:
        """Write as ``.npz`` atomically (temporary file, then rename)."""
        write_npz_atomic(path, self.to_arrays())

    @classmethod
    def load(cls, path) -> Hierarchy:
        """Read a file written by :meth:`save` (no pickle involved)."""
        return cls.from_arrays(read_npz(path))


# ---------------------------------------------------------------------- input checking
def _graph_of(mesh_or_edges, positions) -> tuple[sp.csr_matrix, np.ndarray]:
    """(adjacency (N, N), positions (N, d)) from a Mesh or from (E, 2) edges + positions."""
    if isinstance(mesh_or_edges, Mesh):
        adjacency = cell_adjacency(mesh_or_edges.cells, mesh_or_edges.n_nodes)  # = mesh.adjacency()
        n_nodes = mesh_or_edges.n_nodes
        positions = mesh_or_edges.nodes if positions is None else positions
    elif positions is None:
        raise ValueError("positions are required with an edge list: pass positions of shape (N, d), "
                         "one row per node (they also fix the node count N)")
    else:
        n_nodes = np.shape(positions)[0] if np.ndim(positions) == 2 else -1
        adjacency = None
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[0] != n_nodes or positions.shape[1] < 1:
        raise ValueError(f"positions must have shape (N, d) with one row per node (N = {n_nodes}); "
                         f"got shape {positions.shape}")
    if not np.isfinite(positions).all():
        raise ValueError("positions contain NaN or inf; pass finite node coordinates")
    if adjacency is None:
        adjacency = adjacency_from_edges(_checked_edges(mesh_or_edges, n_nodes), n_nodes)
    return adjacency, positions


def _checked_edges(edges, n_nodes: int) -> np.ndarray:
    edges = np.asarray(edges)
    if edges.ndim != 2 or edges.shape[1] != 2 or not np.issubdtype(edges.dtype, np.integer):
        raise ValueError("mesh_or_edges must be a Mesh or an integer (E, 2) array of node pairs "
                         f"(for a (2, E) edge_index pass edge_index.T); got {edges.dtype} {edges.shape}")
    if edges.size and (edges.min() < 0 or edges.max() >= n_nodes):
        raise ValueError(f"edge node indices must lie in [0, {n_nodes}) (N = len(positions)); "
                         f"got [{edges.min()}, {edges.max()}]")
    return edges


def _is_count(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _check_options(levels, seeding, seed, min_nodes, max_coarse_degree) -> None:
    if levels != "auto" and not (_is_count(levels) and 1 <= levels <= _MAX_LEVELS):
        raise ValueError(f"levels must be 'auto' or an integer from 1 to {_MAX_LEVELS} "
                         f"(the number of levels, the mesh included); got {levels!r}")
    if seeding not in SEEDINGS:
        raise ValueError(f"seeding must be one of {', '.join(map(repr, SEEDINGS))}; got {seeding!r}")
    if not (_is_count(min_nodes) and min_nodes >= 1):
        raise ValueError(f"min_nodes must be an integer >= 1; got {min_nodes!r}")
    if not (_is_count(seed) and seed >= 0):
        raise ValueError(f"seed must be an integer >= 0; got {seed!r}")
    if max_coarse_degree is not None and not (_is_count(max_coarse_degree) and max_coarse_degree >= 1):
        raise ValueError("max_coarse_degree must be None (no cap) or an integer >= 1 (coarse edges per node); "
                         f"got {max_coarse_degree!r}")


# ---------------------------------------------------------------------- building
def _wants_another_level(levels, min_nodes: int, n_levels: int, n_nodes: int, n_components: int) -> bool:
    if levels != "auto":
        return n_levels < levels
    # pooling shrinks a level exactly when some component still has two nodes or more
    return n_nodes >= min_nodes and n_nodes > n_components and n_levels < _MAX_LEVELS


def _coarse_level(adjacency: sp.csr_matrix, closed: sp.csr_matrix, seeds: np.ndarray, kept: np.ndarray,
                  max_coarse_degree: int | None) -> sp.csr_matrix:
    """The adjacency of the level of nodes ``kept``: all kept pairs within two hops (eq. 4.1), or
    under a degree cap (:mod:`bsms.graph.capping`)."""
    if max_coarse_degree is None:
        return coarse_adjacency(closed)
    depth = bfs_depths(adjacency, seeds)[kept]
    return capped_coarse_adjacency(closed, depth, max_coarse_degree)[0]


def build_hierarchy(adjacency: sp.csr_matrix, positions: np.ndarray, levels, seeding: str, seed: int,
                    min_nodes: int, self_loops: bool, key: str = "",
                    max_coarse_degree: int | None = None) -> Hierarchy:
    """The levels of ``adjacency`` ((N, N) symmetric 0/1 CSR, no diagonal), no input checks.

    positions: (N, d), used by ``close_center`` only. See :func:`bistride_levels`.
    """
    n_components, labels = csgraph.connected_components(adjacency, directed=False)
    labels = labels.astype(np.int64)
    n = adjacency.shape[0]
    weights = np.ones(n)
    built = [BistrideLevel(np.arange(n, dtype=np.int64), edge_index_of(adjacency), weights, np.zeros(0, np.int64))]
    component_labels = labels
    while _wants_another_level(levels, min_nodes, len(built), built[-1].n_nodes, n_components):
        rng = np.random.default_rng([seed, len(built)])
        seeds = component_seeds(adjacency, labels, n_components, positions, seeding, rng)
        kept = bistride_pool(adjacency, labels, seeds)
        closed = closed_rows(adjacency, kept)
        degree = np.diff(adjacency.indptr)
        down, up, weights = transition_operators(closed, kept, degree, weights, self_loops)
        adjacency = _coarse_level(adjacency, closed, seeds, kept, max_coarse_degree)
        built.append(BistrideLevel(kept, edge_index_of(adjacency), weights, seeds, down, up))
        labels, positions = labels[kept], positions[kept]
    return Hierarchy(tuple(built), component_labels, seeding, self_loops, key, max_coarse_degree)


def bistride_levels(mesh_or_edges, positions=None, levels="auto", seeding: str = "min_ave", seed: int = 0,
                    *, min_nodes: int = DEFAULT_MIN_NODES, self_loops: bool = True,
                    max_coarse_degree: int | None = None, cache_dir=None) -> Hierarchy:
    """Bi-stride levels of a mesh graph, with their down/up transitions.

    mesh_or_edges: a :class:`datagen.mesh.Mesh`, or (E, 2) int node pairs (any order,
        duplicates allowed) whose nodes are the rows of ``positions``.
    positions: (N, d) node coordinates; optional for a Mesh (default: its nodes). Only
        ``close_center`` seeding reads them.
    levels: number of levels, the mesh included (``1`` = the mesh alone), or ``"auto"``:
        pool until a level has fewer than ``min_nodes`` nodes, or every component is down
        to one node (pooling cannot shrink it further).
    seeding: ``"min_ave"`` (minimum mean hop distance, thesis Algorithm 3), ``"close_center"``
        (nearest the centroid, Algorithm 2) or ``"random"`` -- per level and component.
    seed: random seed of ``"random"`` seeding and of the sampled MinAve search on large
        components (:mod:`bsms.graph.seeding`); the result is deterministic for a given seed.
    self_loops: whether a kept node's own value enters its down/up averages
        (:mod:`bsms.graph.transitions` gives the measurement behind the default).
    max_coarse_degree: None (the thesis' levels: every kept pair within two hops is joined), or
        at most this many edges per node on the coarse levels, chosen from the topology
        (:mod:`bsms.graph.capping`; for tetrahedral meshes, whose coarse levels densify otherwise).
    cache_dir: a folder to load the hierarchy from, or store it in, keyed by a hash of
        (topology, levels, min_nodes, seeding, seed, self_loops[, max_coarse_degree when set]
        [, positions for close_center]).

    Raises ValueError naming the argument for a bad ``levels``, ``seeding``, ``seed``,
    ``min_nodes``, ``max_coarse_degree``, positions of the wrong shape or non-finite, or
    malformed edges.
    """
    _check_options(levels, seeding, seed, min_nodes, max_coarse_degree)
    levels = levels if levels == "auto" else int(levels)
    adjacency, positions = _graph_of(mesh_or_edges, positions)
    adjacency.sort_indices()
    options = {"levels": levels, "min_nodes": int(min_nodes) if levels == "auto" else None,
               "seeding": seeding, "seed": int(seed), "self_loops": bool(self_loops)}
    if max_coarse_degree is not None:  # uncapped hierarchies keep the keys they always had
        options["max_coarse_degree"] = int(max_coarse_degree)
    key = hierarchy_key(adjacency, positions if seeding == "close_center" else None, options)
    path = cache_path(output_folder(cache_dir, "cache_dir"), key) if cache_dir is not None else None
    if path is not None and path.is_file():
        try:
            cached = Hierarchy.load(path)
            if cached.key == key:
                return cached
        except (OSError, ValueError, KeyError) as exc:
            warnings.warn(f"ignoring unreadable hierarchy cache {path} ({exc}); rebuilding it", stacklevel=2)
    hierarchy = build_hierarchy(adjacency, positions, levels, seeding, int(seed), int(min_nodes),
                                bool(self_loops), key, None if max_coarse_degree is None else int(max_coarse_degree))
    if path is not None:
        hierarchy.save(path)
    return hierarchy
