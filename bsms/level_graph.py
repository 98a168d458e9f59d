"""Multi-level graphs of frames, one at a time or many joined into one batch.

A frame of a scenario is first a :class:`FrameArrays` (numpy: per-node arrays, the levels of
its graph -- :class:`~bsms.graph.frames.FrameLevel` -- and its contact edges per level).
:func:`level_graph` turns one or several of them into a :class:`LevelGraph` (a PyG ``Data``)
in one pass: each field of all frames is concatenated once, its indices shifted by the node
counts before it on the level they point into. PyG's ``Batch`` joins single LevelGraphs the
same way (training does); building the joined graph directly skips its per-graph, per-key work.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch_geometric.data import Data

from bsms.graph import Transition
from bsms.graph.frames import FrameLevel
from datagen.trajectory import NodeType

__all__ = ["LevelGraph", "FrameArrays", "level_graph", "frame_graph", "hierarchy_levels"]


# How PyG's Batch offsets each index field of a LevelGraph: field prefix -> which level's node
# count (relative to the field's own level l) the field's values index. The transitions are
# stored as their triplets, ``{down,up}_{rows,cols,weights}_{l}`` (weights are never offset).
_OFFSETS = {
    "edge_index": 0, "contact_index": 0, "down_rows": 1, "down_cols": 0, "up_rows": 0, "up_cols": 1,
}
# per-node fields and their dtype (scenario_nodes: the scenario node of each graph node, never offset)
_NODE_FIELDS = {
    "rest_pos": torch.float32, "pos": torch.float32, "velocity": torch.float32, "node_type": torch.long,
    "target": torch.float32, "loss_mask": torch.bool, "constants": torch.float32, "frame_dt": torch.float32,
    "scenario_nodes": torch.long, "fields": torch.float32, "type_code": torch.long,
    "penetration": torch.float32, "clearance": torch.float32, "elastic": torch.float32, "loss_weight": torch.float32,
}


class LevelGraph(Data):
    """One frame on one mesh (or a batch of them), with its levels; fields per level l are
    suffixed ``_{l}``.

    x-like fields on level-0 nodes: ``pos``, ``rest_pos``, ``velocity`` (N, d),
    ``node_type`` (N,), ``loss_mask`` (N,), optional ``constants`` (N, k), ``target`` (N, d),
    ``frame_dt`` (N,), ``scenario_nodes`` (N,), and for source datasets (:mod:`bsms.fields`)
    ``fields`` (N, k) Eulerian node inputs and ``type_code`` (N,) node type codes. Per level:
    ``nodes_{l}``, ``edge_index_{l}``, ``contact_index_{l}``, ``down_*_{l}`` and ``up_*_{l}``
    (rows, cols, weights) of the transitions between l and l+1 (:meth:`transition`),
    ``n_nodes_{l}`` (an int; for a batch, one count per graph).
    """

    def __inc__(self, key: str, value, *args, **kwargs):
        prefix, _, level = key.rpartition("_")
        if prefix in _OFFSETS:
            return getattr(self, f"n_nodes_{int(level) + _OFFSETS[prefix]}")
        if prefix == "nodes":
            return self.num_nodes
        if prefix in ("down_weights", "up_weights") or key == "scenario_nodes":
            return 0
        return super().__inc__(key, value, *args, **kwargs)

    def __cat_dim__(self, key: str, value, *args, **kwargs):
        if key.rpartition("_")[0] in ("edge_index", "contact_index"):
            return -1
        return super().__cat_dim__(key, value, *args, **kwargs)

    @property
    def n_levels(self) -> int:
        return sum(1 for key in self.keys() if key.startswith("nodes_"))

    def transition(self, kind: str, level: int) -> Transition:
        """The ``"down"`` (l -> l+1) or ``"up"`` (l+1 -> l) transition of ``level`` l, in torch
        (of the whole batch for a batch)."""
        shape = (self.level_size(level + 1), self.level_size(level))
        return Transition(self[f"{kind}_rows_{level}"], self[f"{kind}_cols_{level}"], self[f"{kind}_weights_{level}"],
                          shape if kind == "down" else shape[::-1])

    def level_size(self, level: int) -> int:
        """Total node count of ``level`` (summed over the graphs of a batch)."""
        count = getattr(self, f"n_nodes_{level}")
        return int(count.sum()) if torch.is_tensor(count) else int(count)


@dataclass(frozen=True, eq=False)
class FrameArrays:
    """One frame's graph in numpy. nodes: per-node arrays by field name (:class:`LevelGraph`);
    levels: its levels, level 0 first; contacts: one (2, C_l) edge index per level, or None."""

    nodes: dict[str, np.ndarray]
    levels: tuple[FrameLevel, ...]
    contacts: tuple[np.ndarray, ...] | None

    @property
    def n_nodes(self) -> int:
        return len(self.levels[0].nodes)


def _joined(arrays: list[np.ndarray], shifts: np.ndarray) -> torch.Tensor:
    """Concatenation along the last axis of int arrays, each shifted by its entry of ``shifts``."""
    if len(arrays) == 1:  # one frame: nothing to shift
        return torch.from_numpy(np.array(arrays[0], np.int64))
    lengths = [a.shape[-1] for a in arrays]
    joined = np.concatenate(arrays, axis=-1) + np.repeat(shifts, lengths)
    return torch.from_numpy(joined)


def _level_fields(frames: list[FrameArrays], l: int, starts: np.ndarray, last: bool) -> dict:
    """The fields of level l of the joined graph; starts: (B, L) first node of each frame per level."""
    levels = [f.levels[l] for f in frames]
    fields = {f"nodes_{l}": _joined([level.nodes for level in levels], starts[:, 0]),
              f"edge_index_{l}": _joined([level.edge_index for level in levels], starts[:, l])}
    if frames[0].contacts is not None:
        fields[f"contact_index_{l}"] = _joined([np.asarray(f.contacts[l]).reshape(2, -1) for f in frames], starts[:, l])
    if not last:
        for kind, (rows, cols) in (("down", (l + 1, l)), ("up", (l, l + 1))):
            transitions = [getattr(level, kind) for level in levels]
            fields[f"{kind}_rows_{l}"] = _joined([t.rows for t in transitions], starts[:, rows])
            fields[f"{kind}_cols_{l}"] = _joined([t.cols for t in transitions], starts[:, cols])
            fields[f"{kind}_weights_{l}"] = torch.from_numpy(
                np.concatenate([t.weights for t in transitions]).astype(np.float32))
    return fields


def level_graph(frames: list[FrameArrays]) -> LevelGraph:
    """The :class:`LevelGraph` of one frame, or of several joined into one batch (graph k's
    nodes follow those of graphs 0..k-1 on every level; ``n_nodes_{l}`` then holds one count
    per graph, as in a PyG ``Batch``)."""
    n_levels, names = len(frames[0].levels), set(frames[0].nodes)
    if any(len(f.levels) != n_levels or set(f.nodes) != names for f in frames):
        raise ValueError("frames joined into one graph must have the same levels and node fields")
    if any(f.contacts is not None and len(f.contacts) < n_levels for f in frames):
        raise ValueError(f"contacts must give one edge index per level ({n_levels})")
    if len({f.contacts is None for f in frames}) > 1:
        raise ValueError("frames joined into one graph must all have contacts or none")
    sizes = np.array([[len(level.nodes) for level in f.levels] for f in frames], np.int64)  # (B, L)
    starts = np.cumsum(sizes, axis=0) - sizes
    fields = {name: torch.from_numpy(np.ascontiguousarray(np.concatenate([f.nodes[name] for f in frames])))
              .to(_NODE_FIELDS[name]) for name in names}
    for l in range(n_levels):
        fields[f"n_nodes_{l}"] = int(sizes[0, l]) if len(frames) == 1 else torch.from_numpy(sizes[:, l].copy())
        fields.update(_level_fields(frames, l, starts, l + 1 == n_levels))
    return LevelGraph(num_nodes=int(sizes[:, 0].sum()), **fields)


def frame_graph(levels: tuple[FrameLevel, ...], *, rest_pos, pos, velocity, node_type, target=None,
                loss_mask=None, constants=None, contacts: tuple | None = None) -> LevelGraph:
    """Build the graph of one frame from numpy arrays.

    levels: its levels (:func:`hierarchy_levels`, or a frame's :meth:`~bsms.graph.frames.SubHierarchy.levels`);
    rest_pos, pos, velocity: (N, d); node_type: (N,) NodeType codes; target: (N, d) or None;
    loss_mask: (N,) bool (default: free nodes); constants: (N, k) per-node scene constants;
    contacts: one (2, C_l) contact edge index per level (``coarsen_contacts``), or None.
    """
    n = len(levels[0].nodes)
    nodes = {"rest_pos": np.asarray(rest_pos), "pos": np.asarray(pos), "velocity": np.asarray(velocity),
             "node_type": np.asarray(node_type)}
    if nodes["pos"].shape != (n, nodes["rest_pos"].shape[-1]) or nodes["velocity"].shape != nodes["pos"].shape:
        raise ValueError(f"rest_pos, pos and velocity must all be (N, d) with N = {n} mesh nodes")
    nodes["loss_mask"] = nodes["node_type"] == NodeType.FREE if loss_mask is None else np.asarray(loss_mask)
    for name, value in (("target", target), ("constants", constants)):
        if value is not None:
            nodes[name] = np.asarray(value)
    return level_graph([FrameArrays(nodes, tuple(levels), contacts)])


def hierarchy_levels(hierarchy, n_levels: int | None = None) -> tuple[FrameLevel, ...]:
    """The first ``n_levels`` (default all) levels of a bi-stride hierarchy as a frame's levels."""
    levels = hierarchy.levels[: n_levels or hierarchy.n_levels]
    return tuple(FrameLevel(hierarchy.finest_indices(l), level.edge_index,
                            levels[l + 1].down if l + 1 < len(levels) else None,
                            levels[l + 1].up if l + 1 < len(levels) else None)
                 for l, level in enumerate(levels))
