"""BSMS-GNN (thesis §4.3, Fig. 4.2): one message pass per level, non-parametric transitions.

encoder -> [block, pool] per level going down -> bottom block -> [unpool, block, + skip]
per level going up -> decoder. The levels and transition weights come from the bi-stride
hierarchy of the mesh; the network never sees positions except through edge features.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor, nn

from bsms.models.blocks import EdgeSet, MessagePassingBlock
from bsms.models.mlp import mlp


class Transition(NamedTuple):
    """Weights of the move between level l and level l+1 (thesis §4.3.2), as COO triplets.

    ``fine (T,)`` indexes level-l nodes, ``coarse (T,)`` level-(l+1) nodes, ``weight (T,)`` is
    the contribution C_ij of fine node i to coarse node j; ``n_coarse`` the level-(l+1) size.
    """

    fine: Tensor
    coarse: Tensor
    weight: Tensor
    n_coarse: int


class Level(NamedTuple):
    """One level of a multi-level graph: its edge sets and the transition to the next level."""

    edge_sets: list[EdgeSet]
    down: Transition | None


def pool(v: Tensor, transition: Transition) -> Tensor:
    """Down: v_j = sum_i C_ij v_i over fine i, for each coarse j. (N_l, H) -> (N_l+1, H)."""
    out = v.new_zeros(transition.n_coarse, v.shape[1])
    return out.index_add_(0, transition.coarse, transition.weight[:, None] * v[transition.fine])


def unpool(v: Tensor, transition: Transition, n_fine: int) -> Tensor:
    """Up: v_i = sum_j C_ij v_j over coarse j, for each fine i. (N_l+1, H) -> (N_l, H)."""
    out = v.new_zeros(n_fine, v.shape[1])
    return out.index_add_(0, transition.fine, transition.weight[:, None] * v[transition.coarse])


class BSMSGNN(nn.Module):
    """Bi-stride multi-scale graph network.

    Args:
        node_in, node_out: widths of the (normalised) node inputs and outputs.
        edge_feature_dims: width of the edge features of each edge set (mesh, contact, ...),
            the same at every level.
        n_levels: levels used; a hierarchy with fewer levels uses its own depth (the bottom
            block runs on its coarsest level), one with more uses only the first ``n_levels``.
    """

    def __init__(self, node_in: int, node_out: int, edge_feature_dims: list[int], n_levels: int,
                 latent: int = 128, hidden: int = 128, hidden_layers: int = 2):
        super().__init__()
        if n_levels < 1:
            raise ValueError(f"n_levels must be at least 1, got {n_levels}")
        self.n_levels = n_levels

        def block() -> MessagePassingBlock:
            return MessagePassingBlock(latent, list(edge_feature_dims), hidden, hidden_layers)

        self.encoder = mlp(node_in, latent, hidden, hidden_layers)
        self.down_blocks = nn.ModuleList(block() for _ in range(n_levels - 1))
        self.bottom_block = block()
        self.up_blocks = nn.ModuleList(block() for _ in range(n_levels - 1))
        self.decoder = mlp(latent, node_out, hidden, hidden_layers, layer_norm=False)

    def forward(self, node_features: Tensor, levels: list[Level]) -> Tensor:
        """node_features: (N, node_in); levels[0] is the mesh itself -> (N, node_out)."""
        depth = min(self.n_levels, len(levels))
        v = self.encoder(node_features)
        skips = []
        for l in range(depth - 1):
            v = self.down_blocks[l](v, levels[l].edge_sets)
            skips.append(v)
            v = pool(v, levels[l].down)
        v = self.bottom_block(v, levels[depth - 1].edge_sets)
        for l in reversed(range(depth - 1)):
            v = unpool(v, levels[l].down, skips[l].shape[0])
            v = self.up_blocks[l](v, levels[l].edge_sets) + skips[l]
        return self.decoder(v)
