"""Frame graphs that keep only some of a hierarchy's nodes (lean obstacles, DESIGN phase 2).

A scenario's :class:`~bsms.graph.hierarchy.Hierarchy` is built once over its body nodes and
every obstacle node. Each frame keeps all body (fixed) nodes but only the obstacle (optional)
nodes a body can reach, and :class:`SubHierarchy` restricts every level to them:

- the kept nodes are closed under parents: with a node comes, on every coarser level, its
  parent -- itself where it is a coarse node too, else the coarse node its up transition
  draws most from. So every kept node has a kept coarse node next to it on the next level,
  and a contact (i, j) keeps its coarse image (parent i, parent j) on every level: thesis
  §4.2's guarantee holds on the restricted levels;
- level l keeps the edges and transition entries between its kept nodes; a transition row
  that lost entries is renormalised to sum to 1 (a row that lost none keeps its weights bit
  for bit, so a frame that keeps every node has exactly the full hierarchy's graph);
- contacts are carried down with eq. 4.1 on the restricted levels (:meth:`SubHierarchy.contacts`).

No edge or transition joins fixed and optional nodes (they are different components), and
fixed nodes have the smallest indices, so they come first on every level: each per-level
array is a fixed prefix, reused as it is, followed by optional entries. The optional entries
of all levels are stacked (level l's node i is node ``offset[l] + i``), so a frame filters
them with a few array operations whatever the number of levels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bsms.graph.contact import coarse_images
from bsms.graph.hierarchy import Hierarchy
from bsms.graph.transitions import Transition

__all__ = ["FrameLevel", "SubHierarchy"]


@dataclass(frozen=True, eq=False)
class FrameLevel:
    """One level of a frame's graph (numpy). nodes: (n,) int64 frame level-0 index of each node;
    edge_index: (2, E) int64; down: to the next level, (n', n); up: from it, (n, n') (None on the last)."""

    nodes: np.ndarray
    edge_index: np.ndarray
    down: Transition | None
    up: Transition | None


@dataclass(frozen=True, eq=False)
class _Stacked:
    """One kind of per-level COO array (edges, down or up transitions) of every level.

    prefix[l]: (2, F_l) level l's fixed entries (their indices are the restricted ones);
    index: (2, K) every level's optional entries in stacked numbering; level: (K,) their level;
    weights: (prefix weights per level, (K,) optional weights), or None for edges;
    counts: (nodes of all levels,) optional entries per stacked row.
    """

    prefix: list[np.ndarray]
    index: np.ndarray
    level: np.ndarray
    weights: tuple[list[np.ndarray], np.ndarray] | None
    counts: np.ndarray

    @classmethod
    def of(cls, arrays, weights, rows: list[int], cols: list[int], offsets, fixed, what: str) -> _Stacked:
        """arrays[k]: (2, E) sorted by row, entries between levels rows[k] and cols[k]."""
        prefix, parts, prefix_weights, part_weights = [], [], [], []
        for k, index in enumerate(arrays):
            split = int(np.searchsorted(index[0], fixed[rows[k]]))
            if (index[1, :split] >= fixed[cols[k]]).any() or (index[1, split:] < fixed[cols[k]]).any():
                raise ValueError(f"{what} joins a fixed (body) node to an optional (obstacle) one; optional "
                                 "nodes must form components of their own")
            prefix.append(index[:, :split])
            parts.append(index[:, split:] + np.array([[offsets[rows[k]]], [offsets[cols[k]]]]))
            if weights is not None:
                prefix_weights.append(weights[k][:split])
                part_weights.append(weights[k][split:])
        index = np.concatenate(parts, axis=1) if parts else np.zeros((2, 0), np.int64)
        level = np.repeat(np.arange(len(parts)), [p.shape[1] for p in parts])
        stacked_weights = None if weights is None else (prefix_weights, np.concatenate([np.zeros(0), *part_weights]))
        return cls(prefix, index, level, stacked_weights, np.bincount(index[0], minlength=offsets[-1]))


def _parents(up: Transition, kept: np.ndarray) -> np.ndarray:
    """(m,) the parent of each fine node: a kept node's own coarse copy; for a dropped one the
    coarse node its up row weighs most (ties: the lowest index)."""
    order = np.lexsort((up.cols, -up.weights, up.rows))
    first = order[np.concatenate([[0], np.flatnonzero(np.diff(up.rows[order])) + 1])]
    parents = np.empty(up.shape[0], np.int64)
    parents[up.rows[first]] = up.cols[first]
    parents[kept] = np.arange(kept.size)
    return parents


class SubHierarchy:
    """A hierarchy prepared so that each frame keeps its first ``n_fixed`` level-0 nodes and any
    subset of the others, closed under parents (:meth:`closure`), cheaply (:meth:`levels`)."""

    def __init__(self, hierarchy: Hierarchy, n_fixed: int):
        self.hierarchy, self.n_fixed = hierarchy, int(n_fixed)
        levels = hierarchy.levels
        self.sizes = [level.n_nodes for level in levels]
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)])  # stacked numbering of all levels
        self.finest = np.concatenate([hierarchy.finest_indices(l) for l in range(len(levels))])
        self.level_of = np.repeat(np.arange(len(levels)), self.sizes)
        fixed = [int(np.searchsorted(hierarchy.finest_indices(l), self.n_fixed)) for l in range(len(levels))]
        n = len(levels)
        self.edges = _Stacked.of([level.edge_index for level in levels], None, list(range(n)), list(range(n)),
                                 self.offsets, fixed, "an edge set")
        self.down, self.up = (
            _Stacked.of([np.stack([getattr(c, kind).rows, getattr(c, kind).cols]) for c in levels[1:]],
                        [getattr(c, kind).weights for c in levels[1:]], rows, cols, self.offsets, fixed,
                        f"the {kind} transition")
            for kind, rows, cols in (("down", list(range(1, n)), list(range(n - 1))),
                                     ("up", list(range(n - 1)), list(range(1, n)))))
        parents = [_parents(coarse.up, coarse.kept) for coarse in levels[1:]]
        # for an empty restricted row (only without self-loops): down, a coarse node's own fine
        # copy; up, a node's parent -- the orphan rule of bsms.graph.transitions (stacked numbering)
        self.own_down = np.concatenate([np.zeros(self.sizes[0], np.int64)]
                                       + [c.kept + self.offsets[l] for l, c in enumerate(levels[1:])])
        self.own_up = np.concatenate([p + self.offsets[l + 1] for l, p in enumerate(parents)]
                                     + [np.zeros(self.sizes[-1], np.int64)])
        index, ancestors = np.arange(self.sizes[0]), [np.arange(self.sizes[0])]
        for l, parent in enumerate(parents):
            index = parent[index]
            ancestors.append(hierarchy.finest_indices(l + 1)[index])
        self.ancestors = np.stack(ancestors, axis=1)  # (N, L): level-0 index of each node's ancestor per level
        self._everything = None
        self._last: tuple[np.ndarray, tuple] | None = None  # (present, result) of the last restriction

    @property
    def n_levels(self) -> int:
        return len(self.sizes)

    def closure(self, chosen: np.ndarray) -> np.ndarray:
        """(N,) bool: the fixed nodes, the ``chosen`` level-0 nodes and all their ancestors."""
        present = np.zeros(self.sizes[0], bool)
        present[: self.n_fixed] = True
        present[self.ancestors[np.asarray(chosen, np.int64)].ravel()] = True
        return present

    def levels(self, present: np.ndarray) -> tuple[tuple[FrameLevel, ...], np.ndarray, np.ndarray]:
        """The levels restricted to ``present`` ((N,) bool, closed: from :meth:`closure`).

        -> (levels, keep, local) in stacked numbering: keep (nodes of all levels,) bool, which
        nodes stay; local: their index within their restricted level (-1 elsewhere). The last
        answer is kept: consecutive frames often hold the same obstacle nodes.
        """
        if self._last is not None and np.array_equal(self._last[0], present):
            return self._last[1]
        keep = present[self.finest]
        kept = np.cumsum(keep)
        counts = np.diff(np.concatenate([[0], kept[self.offsets[1:] - 1]]))
        local = np.where(keep, kept - 1 - (np.cumsum(counts) - counts)[self.level_of], -1)
        if present.all():
            if self._everything is None:
                self._everything = self._restrict(keep, local, counts)
            return self._everything, keep, local
        self._last = (present.copy(), (self._restrict(keep, local, counts), keep, local))
        return self._last[1]

    def _restrict(self, keep, local, counts) -> tuple[FrameLevel, ...]:
        nodes = np.split(local[: self.sizes[0]][self.finest[keep]], np.cumsum(counts)[:-1])
        edges = _restricted(self.edges, keep, local, self.n_levels)
        down = up = []
        if self.n_levels > 1:
            down = _transitions(self.down, keep, local, self.own_down, self.n_levels - 1)
            up = _transitions(self.up, keep, local, self.own_up, self.n_levels - 1)
        out = []
        for l in range(self.n_levels):
            if l + 1 == self.n_levels:
                out.append(FrameLevel(nodes[l], edges[l], None, None))
                continue
            shape = (int(counts[l + 1]), int(counts[l]))
            out.append(FrameLevel(nodes[l], edges[l], Transition(*down[l], shape), Transition(*up[l], shape[::-1])))
        return tuple(out)

    def contacts(self, contacts: np.ndarray, keep, local) -> tuple[np.ndarray, ...]:
        """Contact edges on every restricted level (eq. 4.1), in restricted indices.

        contacts: (2, C) int64 level-0 contacts between present nodes, both directions, sorted.
        """
        out, pairs = [local[contacts]], contacts
        for l, reach in enumerate(self.hierarchy.reach):
            pairs = coarse_images(pairs, reach)
            start = self.offsets[l + 1]
            pairs = pairs[:, keep[start + pairs[0]] & keep[start + pairs[1]]]
            out.append(local[start + pairs])
        return tuple(out)


def _split(index: np.ndarray, level: np.ndarray, n_levels: int, *arrays) -> list[list[np.ndarray]]:
    """``arrays`` (last axis: entries, ordered by level) cut into one piece per level."""
    cuts = np.cumsum(np.bincount(level, minlength=n_levels))[:-1]
    return [np.split(array, cuts, axis=-1) for array in (index, *arrays)]


def _restricted(stacked: _Stacked, keep, local, n_levels: int) -> list[np.ndarray]:
    """(2, E_l) per level: the edges between kept nodes, in restricted indices."""
    ok = keep[stacked.index[0]] & keep[stacked.index[1]]
    (pieces,) = _split(local[stacked.index[:, ok]], stacked.level[ok], n_levels)
    return [np.concatenate([prefix, piece], axis=1) for prefix, piece in zip(stacked.prefix, pieces, strict=True)]


def _transitions(stacked: _Stacked, keep, local, own, n_levels: int) -> list[tuple[np.ndarray, ...]]:
    """(rows, cols, weights) per level of a transition restricted to kept rows and columns: rows
    that lost entries sum to 1 again, and a kept row that lost them all (only possible without
    self-loops) takes column ``own[row]`` with weight 1."""
    ok = keep[stacked.index[0]] & keep[stacked.index[1]]
    (rows, cols), weights, level = stacked.index[:, ok], stacked.weights[1][ok], stacked.level[ok]
    after = np.bincount(rows, minlength=keep.size)
    total = np.bincount(rows, weights=weights, minlength=keep.size)
    weights = np.where((after != stacked.counts)[rows], weights / np.where(total > 0, total, 1.0)[rows], weights)
    empty = np.flatnonzero(keep & (after == 0) & (stacked.counts > 0))
    if empty.size:
        rows, cols = np.concatenate([rows, empty]), np.concatenate([cols, own[empty]])
        weights = np.concatenate([weights, np.ones(empty.size)])
        level = np.concatenate([level, stacked.level[np.searchsorted(stacked.index[0], empty)]])
        order = np.argsort(rows, kind="stable")
        rows, cols, weights, level = rows[order], cols[order], weights[order], level[order]
    pieces, weight_pieces = _split(local[np.stack([rows, cols])], level, n_levels, weights)
    return [(np.concatenate([prefix[0], piece[0]]), np.concatenate([prefix[1], piece[1]]),
             np.concatenate([prefix_weights, w]))
            for prefix, piece, prefix_weights, w in zip(stacked.prefix, pieces, stacked.weights[0], weight_pieces,
                                                        strict=True)]
