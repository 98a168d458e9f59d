"""What a core network reads: the levels of a multi-level graph, and (for cores that build
structure of their own from positions) a :class:`Context`.

Every core's forward is ``core(node_features (N, node_in), levels, context) -> (N, node_out)``.
``context`` is None unless the core sets ``needs_context = True``
(:class:`~bsms.models.simulator.LearnedSimulator` builds it only then).
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from bsms.graph import Transition
from bsms.models.blocks import EdgeSet


class Level(NamedTuple):
    """One level of the multi-level graph a core network reads: its edge sets and the
    transitions to and from the next level (:class:`~bsms.graph.Transition` with torch tensors).

    ``down`` (level l -> l+1) and ``up`` (l+1 -> l) are None on the coarsest level; ``edge_sets``
    is empty on a level the core passes no messages on (BSMS-GNN below its ``first_level``).
    ``nodes`` (n_l,): the level-0 index of each node of this level (sorted within each graph;
    None where a caller has no use for it). The nodes of level l+1 are a subset of those of
    level l (bi-stride pooling keeps nodes), so their level-l indices follow from ``nodes``.
    """

    edge_sets: list[EdgeSet]
    down: Transition | None
    up: Transition | None
    nodes: Tensor | None = None


class Context(NamedTuple):
    """Per-frame inputs beyond the edge sets, for cores that build their own structure.

    points: (N, 2 d) rest (material-space) then world positions of the level-0 nodes, float32;
    graph: (N,) int64, the graph of each level-0 node within a batch (0 for a single graph);
    n_graphs: graphs in the batch; dim: d;
    accumulate: whether normalisers owned by the core should learn from this call (training).
    """

    points: Tensor
    graph: Tensor
    n_graphs: int
    dim: int
    accumulate: bool = False

    @property
    def rest_pos(self) -> Tensor:
        return self.points[:, : self.dim]

    @property
    def pos(self) -> Tensor:
        return self.points[:, self.dim:]
