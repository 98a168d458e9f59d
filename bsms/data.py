"""Frames of trajectories as multi-level graphs that batch correctly.

A mesh's bi-stride :class:`~bsms.graph.hierarchy.Hierarchy` is converted once into
:class:`MeshLevels` (torch tensors); each frame then becomes a :class:`LevelGraph` (a PyG
``Data``) holding the node state, the per-level edges and transition maps, and optional
contact edges per level. Batching graphs of different meshes with PyG's ``Batch`` offsets
every index field by the node count of the level it points into.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Data

from datagen.dataset import NodeType

__all__ = ["NodeType", "N_NODE_TYPES", "MeshLevels", "LevelGraph", "frame_graph"]


N_NODE_TYPES = len(NodeType)


def _tensor(array, dtype) -> Tensor:
    return torch.tensor(np.asarray(array), dtype=dtype)


@dataclass(frozen=True)
class MeshLevels:
    """The levels of one mesh in torch form, level 0 first (built once per mesh).

    nodes[l]: (n_l,) level-0 index of each level-l node. edge_index[l]: (2, E_l).
    down[l]: (rows, cols, weights) of the map level l -> l+1 (rows index level l+1).
    up[l]: (rows, cols, weights) of the map level l+1 -> l (rows index level l).
    """

    nodes: tuple[Tensor, ...]
    edge_index: tuple[Tensor, ...]
    down: tuple[tuple[Tensor, Tensor, Tensor], ...]
    up: tuple[tuple[Tensor, Tensor, Tensor], ...]

    @property
    def n_levels(self) -> int:
        return len(self.nodes)

    @classmethod
    def from_hierarchy(cls, hierarchy, n_levels: int | None = None) -> MeshLevels:
        """Torch form of the first ``n_levels`` (default all) levels of a bi-stride hierarchy."""
        levels = hierarchy.levels[: n_levels or hierarchy.n_levels]
        nodes = tuple(_tensor(hierarchy.finest_indices(l), torch.long) for l in range(len(levels)))
        edges = tuple(_tensor(level.edge_index, torch.long) for level in levels)

        def triplets(transition):
            return (_tensor(transition.rows, torch.long), _tensor(transition.cols, torch.long),
                    _tensor(transition.weights, torch.float32))

        down = tuple(triplets(level.down) for level in levels[1:])
        up = tuple(triplets(level.up) for level in levels[1:])
        return cls(nodes, edges, down, up)


# Which node count each index field is offset by when graphs are batched:
# (prefix, level offset of the counted level relative to the field's level).
_OFFSETS = {
    "edge_index": 0, "contact_index": 0, "down_rows": 1, "down_cols": 0, "up_rows": 0, "up_cols": 1,
}


class LevelGraph(Data):
    """One frame on one mesh, with its levels; fields per level l are suffixed ``_{l}``.

    x-like fields on level-0 nodes: ``pos``, ``rest_pos``, ``velocity`` (N, d),
    ``node_type`` (N,), optional ``constants`` (N, k), ``target`` (N, d), ``loss_mask`` (N,).
    Per level: ``nodes_{l}``, ``edge_index_{l}``, ``contact_index_{l}``, ``down_*_{l}`` and
    ``up_*_{l}`` (rows, cols, weights) for the maps between l and l+1, ``n_nodes_{l}``.
    """

    def __inc__(self, key: str, value, *args, **kwargs):
        prefix, _, level = key.rpartition("_")
        if prefix in _OFFSETS:
            return getattr(self, f"n_nodes_{int(level) + _OFFSETS[prefix]}")
        if prefix == "nodes":
            return self.num_nodes
        if prefix in ("down_weights", "up_weights"):
            return 0
        return super().__inc__(key, value, *args, **kwargs)

    def __cat_dim__(self, key: str, value, *args, **kwargs):
        if key.rpartition("_")[0] in ("edge_index", "contact_index"):
            return -1
        return super().__cat_dim__(key, value, *args, **kwargs)

    @property
    def n_levels(self) -> int:
        return sum(1 for key in self.keys() if key.startswith("nodes_"))

    def level_size(self, level: int) -> int:
        """Total node count of ``level`` (summed over the graphs of a batch)."""
        count = getattr(self, f"n_nodes_{level}")
        return int(count.sum()) if torch.is_tensor(count) else int(count)


def frame_graph(levels: MeshLevels, *, rest_pos, pos, velocity, node_type, target=None, loss_mask=None,
                constants=None, contacts: tuple | None = None) -> LevelGraph:
    """Build the graph of one frame.

    rest_pos, pos, velocity: (N, d); node_type: (N,) NodeType codes; target: (N, d) or None;
    loss_mask: (N,) bool (default: free nodes); constants: (N, k) per-node scene constants;
    contacts: one (2, C_l) contact edge index per level (``coarsen_contacts``), or None.
    """
    n = levels.nodes[0].shape[0]
    node_type = _tensor(node_type, torch.long)
    data = LevelGraph(
        num_nodes=n, rest_pos=_tensor(rest_pos, torch.float32), pos=_tensor(pos, torch.float32),
        velocity=_tensor(velocity, torch.float32), node_type=node_type,
    )
    if data.pos.shape != (n, data.rest_pos.shape[1]) or data.velocity.shape != data.pos.shape:
        raise ValueError(f"rest_pos, pos and velocity must all be (N, d) with N = {n} mesh nodes")
    if target is not None:
        data.target = _tensor(target, torch.float32)
    data.loss_mask = node_type == NodeType.FREE if loss_mask is None else _tensor(loss_mask, torch.bool)
    if constants is not None:
        data.constants = _tensor(constants, torch.float32)
    if contacts is not None and len(contacts) < levels.n_levels:
        raise ValueError(f"contacts must give one edge index per level ({levels.n_levels}); got {len(contacts)}")
    for l in range(levels.n_levels):
        setattr(data, f"n_nodes_{l}", int(levels.nodes[l].shape[0]))
        setattr(data, f"nodes_{l}", levels.nodes[l])
        setattr(data, f"edge_index_{l}", levels.edge_index[l])
        if contacts is not None:
            setattr(data, f"contact_index_{l}", _tensor(contacts[l], torch.long).reshape(2, -1))
        if l + 1 < levels.n_levels:
            for kind, (rows, cols, weights) in (("down", levels.down[l]), ("up", levels.up[l])):
                setattr(data, f"{kind}_rows_{l}", rows)
                setattr(data, f"{kind}_cols_{l}", cols)
                setattr(data, f"{kind}_weights_{l}", weights)
    return data
