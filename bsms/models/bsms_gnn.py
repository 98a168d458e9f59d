"""BSMS-GNN (thesis §4.3, Fig. 4.2): one message pass per level, non-parametric transitions.

encoder -> [block, pool] per level going down -> bottom block -> [unpool, block, + skip]
per level going up -> decoder. The levels and transition weights come from the bi-stride
hierarchy of the mesh; the network never sees positions except through edge features.
"""

from __future__ import annotations

from torch import Tensor, nn

from bsms.graph import Transition
from bsms.models.blocks import MessagePassingBlock
from bsms.models.inputs import Context, Level
from bsms.models.mlp import mlp


def apply_transition(v: Tensor, transition: Transition) -> Tensor:
    """(n_in, H) -> (n_out, H): out_r = sum over triplets (r, c, w) of w * v_c (thesis §4.3.2)."""
    out = v.new_zeros(transition.shape[0], v.shape[1])
    weights = transition.weights.to(v.dtype)[:, None]
    return out.index_add_(0, transition.rows, v.index_select(0, transition.cols) * weights)


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
                 latent: int = 128, hidden: int = 128, hidden_layers: int = 2, transition: str = "bistride"):
        super().__init__()
        if n_levels < 1:
            raise ValueError(f"n_levels must be at least 1, got {n_levels}")
        if transition != "bistride":
            raise ValueError(f"transition {transition!r} is not available yet")
        self.n_levels = n_levels

        def block() -> MessagePassingBlock:
            return MessagePassingBlock(latent, list(edge_feature_dims), hidden, hidden_layers)

        self.encoder = mlp(node_in, latent, hidden, hidden_layers)
        self.down_blocks = nn.ModuleList(block() for _ in range(n_levels - 1))
        self.bottom_block = block()
        self.up_blocks = nn.ModuleList(block() for _ in range(n_levels - 1))
        self.decoder = mlp(latent, node_out, hidden, hidden_layers, layer_norm=False)

    def forward(self, node_features: Tensor, levels: list[Level], context: Context | None = None) -> Tensor:
        """node_features: (N, node_in); levels[0] is the mesh itself -> (N, node_out)."""
        depth = min(self.n_levels, len(levels))
        v = self.encoder(node_features).to(node_features.dtype)  # the residual stream: float32 under autocast
        skips = []
        for l in range(depth - 1):
            v = self.down_blocks[l](v, levels[l].edge_sets)
            skips.append(v)
            v = apply_transition(v, levels[l].down)
        v = self.bottom_block(v, levels[depth - 1].edge_sets)
        for l in reversed(range(depth - 1)):
            v = apply_transition(v, levels[l].up)
            v = self.up_blocks[l](v, levels[l].edge_sets) + skips[l]
        return self.decoder(v)
