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


class SparseMap(NamedTuple):
    """A linear map between levels as COO triplets: ``out[rows] += weights * x[cols]``.

    rows: (T,) output nodes; cols: (T,) input nodes; weights: (T,); n_out: output size.
    The down map of the bi-stride hierarchy takes level l to l+1 (weighted averages onto the
    kept nodes, thesis §4.3.2); the up map returns level l+1 to level l.
    """

    rows: Tensor
    cols: Tensor
    weights: Tensor
    n_out: int


class Level(NamedTuple):
    """One level of a multi-level graph: its edge sets and the maps to and from the next level.

    ``down`` (level l -> l+1) and ``up`` (l+1 -> l) are None on the coarsest level.
    """

    edge_sets: list[EdgeSet]
    down: SparseMap | None
    up: SparseMap | None


def apply_map(v: Tensor, sparse_map: SparseMap) -> Tensor:
    """(N_in, H) -> (n_out, H): out_r = sum over triplets (r, c, w) of w * v_c."""
    out = v.new_zeros(sparse_map.n_out, v.shape[1])
    return out.index_add_(0, sparse_map.rows, sparse_map.weights[:, None] * v[sparse_map.cols])


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
            v = apply_map(v, levels[l].down)
        v = self.bottom_block(v, levels[depth - 1].edge_sets)
        for l in reversed(range(depth - 1)):
            v = apply_map(v, levels[l].up)
            v = self.up_blocks[l](v, levels[l].edge_sets) + skips[l]
        return self.decoder(v)
