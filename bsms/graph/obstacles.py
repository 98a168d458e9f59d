"""Obstacle geometry in the learned graph, and the wall nodes each frame needs (lean obstacles).

Walls and containers are stored as facets (segments in 2D, triangles in 3D). They enter the
graph as nodes of their own, subdivided so that a body node near a wall always finds wall
nodes within the contact radius (:func:`subdivide_obstacles`). Moving obstacles (kinematic,
prescribed motion) are stored as the positions of their stored nodes per frame; the subdivided
nodes follow them through the linear map of the subdivision (:meth:`Subdivision.moved`). A
frame's graph then holds only the obstacle nodes within reach of a body, wherever the obstacles
are in that frame (:class:`ObstacleReach`): a wall nobody is near costs nothing. Nodes are
numbered body first, obstacles after, as in a scenario.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from bsms.graph.contact import contact_edges

__all__ = ["Subdivision", "subdivide_obstacles", "subdivide_facets", "facet_edges", "ObstacleReach", "KeptTree"]


@dataclass(frozen=True)
class Subdivision:
    """Obstacle geometry subdivided for the graph, and how its nodes follow the stored ones.

    stored: (M, d) the stored obstacle nodes (at rest / frame 0); nodes (M_sub, d), facets
    (F_sub, k): the subdivided geometry; weights: (M_sub, M) sparse map from stored to
    subdivided nodes -- each subdivided node is a barycentric combination of the corners of
    the facet it lies on (rows sum to 1), so ``nodes`` = weights @ ``stored`` up to round-off.
    """

    stored: np.ndarray
    nodes: np.ndarray
    facets: np.ndarray
    weights: sparse.csr_matrix

    def moved(self, positions: np.ndarray) -> np.ndarray:
        """(..., M_sub, d) subdivided nodes of stored obstacle nodes at ``positions`` (..., M, d):
        ``nodes + weights @ (positions - stored)`` -- ``nodes`` bit for bit where the stored nodes
        are at rest, and exact (to round-off) for any motion affine on each facet (rigid motion)."""
        positions = np.asarray(positions, np.float64)
        if positions.shape[-2:] != self.stored.shape:
            raise ValueError(f"obstacle positions have shape {positions.shape}; the obstacle geometry has "
                             f"{len(self.stored)} stored nodes in {self.stored.shape[1]}D: give (..., "
                             f"{len(self.stored)}, {self.stored.shape[1]}) positions of the stored obstacle nodes")
        shift = np.moveaxis(positions - self.stored, -2, 0)  # (M, ..., d)
        moved = (self.weights @ shift.reshape(len(self.stored), -1)).reshape((len(self.nodes), *shift.shape[1:]))
        return self.nodes + np.moveaxis(moved, 0, -2)


def subdivide_obstacles(nodes: np.ndarray, facets: np.ndarray, spacing: float) -> Subdivision:
    """Obstacle geometry with no facet edge longer than ``spacing`` (2D: original nodes first;
    ``spacing`` <= 0 keeps it as stored), with the map from stored to subdivided nodes.

    nodes (M, d); facets (F, k) with k = 2 (segments) or 3 (triangles). Each facet is split
    uniformly into n pieces per edge (segments: n per segment; triangles: one n for all, so
    shared edges get the same points); points shared by facets are merged.
    """
    nodes = np.asarray(nodes, np.float64)
    k = facets.shape[1]
    kept = Subdivision(nodes, nodes, facets, sparse.identity(len(nodes), format="csr"))
    if len(facets) == 0 or k not in (2, 3) or spacing <= 0:
        return kept
    corners = nodes[facets]  # (F, k, d)
    lengths = np.linalg.norm(corners[:, [1, 2, 0][:k]] - corners, axis=-1) if k == 3 else \
        np.linalg.norm(corners[:, 1] - corners[:, 0], axis=-1)[:, None]
    if lengths.max() <= spacing:
        return kept
    if k == 2:
        return _subdivide_segments(nodes, facets, np.maximum(1, np.ceil(lengths[:, 0] / spacing).astype(int)))
    return _subdivide_triangles(nodes, facets, int(np.ceil(lengths.max() / spacing)))


def subdivide_facets(nodes: np.ndarray, facets: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, facets) of :func:`subdivide_obstacles`: the subdivided geometry alone."""
    subdivision = subdivide_obstacles(nodes, facets, spacing)
    return subdivision.nodes, subdivision.facets


def _subdivide_triangles(nodes: np.ndarray, triangles: np.ndarray, n: int) -> Subdivision:
    """Every triangle split into n^2 by the barycentric lattice (i, j), i + j <= n, points merged."""
    lattice = np.array([(i, j) for i in range(n + 1) for j in range(n + 1 - i)])
    index = {tuple(p): q for q, p in enumerate(lattice)}
    small = []
    for i in range(n):
        for j in range(n - i):
            small.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j < n - 1:
                small.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    small = np.array(small)
    weights = np.column_stack([n - lattice.sum(1), lattice[:, 0], lattice[:, 1]]) / n  # (L, 3)
    points = np.einsum("lc,fcd->fld", weights, nodes[triangles]).reshape(-1, nodes.shape[1])
    fine = (small[None] + len(lattice) * np.arange(len(triangles))[:, None, None]).reshape(-1, 3)
    scale = max(float(np.abs(points).max()), 1.0)
    _, first, inverse = np.unique(np.round(points / (1e-9 * scale)).astype(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
    facet, point = np.divmod(first, len(lattice))  # the facet and lattice point each kept point came from
    rows = np.repeat(np.arange(len(first)), 3)
    matrix = sparse.csr_matrix((weights[point].reshape(-1), (rows, triangles[facet].reshape(-1))),
                               shape=(len(first), len(nodes)))
    return Subdivision(nodes, points[first], inverse.reshape(-1)[fine], matrix)


def _subdivide_segments(nodes: np.ndarray, segments: np.ndarray, pieces: np.ndarray) -> Subdivision:
    """Every segment split into its number of ``pieces``; the stored nodes first, as they are."""
    points, out = [nodes], []
    rows, cols, values = [np.arange(len(nodes))], [np.arange(len(nodes))], [np.ones(len(nodes))]
    count = len(nodes)
    for (a, b), n in zip(segments, pieces, strict=True):
        fraction = np.arange(1, n) / n
        inner = nodes[a] + np.outer(fraction, nodes[b] - nodes[a])
        ids = np.concatenate([[a], count + np.arange(n - 1), [b]])
        points.append(inner)
        rows += [ids[1:-1]] * 2
        cols += [np.full(n - 1, a), np.full(n - 1, b)]
        values += [1.0 - fraction, fraction]
        count += n - 1
        out.append(np.stack([ids[:-1], ids[1:]], axis=1))
    matrix = sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                               shape=(count, len(nodes)))
    return Subdivision(nodes, np.concatenate(points), np.concatenate(out), matrix)


def facet_edges(facets: np.ndarray) -> np.ndarray:
    """(E, 2) unique sorted node pairs of the edges of ``facets`` (F, k)."""
    k = facets.shape[1]
    pairs = np.concatenate([facets[:, [a, b]] for a in range(k) for b in range(a + 1, k)])
    return np.unique(np.sort(pairs, axis=1), axis=0)


class KeptTree:
    """A KD-tree of some points, built again only when they move: ``tree(points)`` returns the
    tree of ``points``, the kept one while they equal the last ones given (frames from rest keep
    the body at rest; static walls stay where they are)."""

    def __init__(self):
        self._kept: tuple[np.ndarray, cKDTree] | None = None

    def __call__(self, points: np.ndarray) -> cKDTree:
        if self._kept is None or not np.array_equal(self._kept[0], points):
            self._kept = (points.copy(), cKDTree(points))
        return self._kept[1]


class ObstacleReach:
    """Which obstacle nodes a frame's graph holds, and the frame's level-0 contact edges.

    n_body: body nodes (the first n_body of N scenario nodes; the rest are obstacle nodes);
    body_id: (N,) body of each node (obstacles: one id of their own); contact_radius: contact
    distance; reach: obstacle nodes within this distance of a body node enter the frame
    (>= contact_radius), or None: every obstacle node, every frame; self_contact, edges
    ((E, 2) mesh and facet edges): as :func:`~bsms.graph.contact.contact_edges`; excluded:
    scenario indices of obstacle nodes no frame holds and no contact reaches (``graph.clearance``:
    the container's), or None.
    """

    def __init__(self, n_body: int, body_id: np.ndarray, contact_radius: float, reach: float | None,
                 self_contact: bool = False, edges: np.ndarray | None = None, excluded: np.ndarray | None = None):
        if reach is not None and reach < contact_radius:
            raise ValueError(f"reach ({reach}) must be at least the contact radius ({contact_radius})")
        self.n_body, self.body_id, self.radius, self.reach = int(n_body), np.asarray(body_id), contact_radius, reach
        self.self_contact, self.edges = self_contact, edges
        self.excluded = np.zeros(0, np.int64) if excluded is None else np.asarray(excluded, np.int64)
        self.several_bodies = len(np.unique(self.body_id[: self.n_body])) > 1
        self._body_tree, self._obstacle_tree = KeptTree(), KeptTree()

    def frame(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(chosen, contacts) of positions ``pos`` (N, d) of all scenario nodes: the obstacle
        nodes in reach (scenario indices, sorted) and the (2, C) contact edges, both directions,
        sorted by (row, col) -- between different bodies and between bodies and obstacles
        (with self_contact, every pair :func:`contact_edges` finds, to be cut to the frame's nodes)."""
        n = len(pos)
        obstacles = np.setdiff1d(np.arange(self.n_body, n), self.excluded, assume_unique=True)
        body_obstacle, chosen = np.zeros((2, 0), np.int64), obstacles
        if len(obstacles) and (self.reach is not None or not self.self_contact):
            near = self._body_tree(pos[: self.n_body]).sparse_distance_matrix(
                self._obstacle_tree(pos[obstacles]), self.radius if self.reach is None else self.reach,
                output_type="ndarray")
            touching = near[near["v"] <= self.radius]
            body_obstacle = np.stack([touching["i"], obstacles[touching["j"]]]).astype(np.int64)
            if self.reach is not None:
                chosen = obstacles[np.unique(near["j"])]
        if self.self_contact:
            pairs = contact_edges(pos, self.body_id, self.radius, exclude=self.edges, self_contact=True)
            return chosen, pairs[:, ~np.isin(pairs, self.excluded).any(axis=0)]
        pairs = [body_obstacle]
        if self.several_bodies:
            pairs.append(contact_edges(pos[: self.n_body], self.body_id[: self.n_body], self.radius,
                                       self_contact=False))
        both = np.concatenate([*pairs, body_obstacle[::-1]], axis=1)
        return chosen, both[:, np.argsort(both[0] * n + both[1], kind="stable")]
