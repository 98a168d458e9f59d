"""BSMS-GNN (thesis §4.3, Fig. 4.2): one message pass per level, non-parametric transitions.

encoder -> [block, pool] per level going down -> bottom block -> [unpool, block, + skip]
per level going up -> decoder. The levels and transition weights come from the bi-stride
hierarchy of the mesh; the network never sees positions except through edge features.
The transitions of the ablation (thesis §4.4.4.1, Table 4.7) are in
:mod:`bsms.models.transition_variants`; the default ``bistride`` reads no positions.
"""

from __future__ import annotations

from torch import Tensor, nn

from bsms.models.blocks import MessagePassingBlock, fusable
from bsms.models.inputs import Context, Level
from bsms.models.mlp import mlp
from bsms.models.transition_variants import TRANSITIONS, apply_transition, make_transitions

__all__ = ["BSMSGNN", "apply_transition"]


def add_unet_modules(module: nn.Module, node_in: int, node_out: int, edge_feature_dims: list[int], n_levels: int,
                     latent: int, hidden: int, hidden_layers: int, layer_norm: bool = True,
                     first_level: int = 0) -> None:
    """The modules of a U-shaped core with one message pass per level (BSMS-GNN, GraphUNets):
    ``encoder``, ``down_blocks`` and ``up_blocks`` (one per level from ``first_level`` to the one
    above the bottom), ``bottom_block`` and ``decoder``, registered on ``module`` in this order
    (their state_dict keys); ``layer_norm`` on the encoder's and the blocks' MLPs."""

    def block() -> MessagePassingBlock:
        return MessagePassingBlock(latent, list(edge_feature_dims), hidden, hidden_layers, layer_norm)

    passing = n_levels - 1 - first_level  # levels that pass messages on the way down (and up)
    module.encoder = mlp(node_in, latent, hidden, hidden_layers, layer_norm)
    module.down_blocks = nn.ModuleList(block() for _ in range(passing))
    module.bottom_block = block()
    module.up_blocks = nn.ModuleList(block() for _ in range(passing))
    module.decoder = mlp(latent, node_out, hidden, hidden_layers, layer_norm=False)


class BSMSGNN(nn.Module):
    """Bi-stride multi-scale graph network.

    Args:
        node_in: width of the (normalised) node inputs.
        node_out: width of the outputs.
        edge_feature_dims: width of the edge features of each edge set (mesh, contact, ...),
            the same at every level.
        n_levels: levels used; a hierarchy with fewer levels uses its own depth (the bottom
            block runs on its coarsest level), one with more uses only the first ``n_levels``.
        transition: how latents move between levels, one of ``bistride`` (default), ``none``,
            ``graph_conv``, ``pos_kernel``, ``learnable`` (:mod:`bsms.models.transition_variants`).
        layer_norm: LayerNorm on the encoder's and the message passes' MLPs (default, the thesis');
            False drops it (a ``learnable`` transition keeps its own).
        first_level: the finest level that passes messages (default 0, every level). The levels
            below it only carry latents: encoded at level 0, pooled down, unpooled up with their
            skip connection, decoded; their edges are never read (``model.first_level``).

    ``needs_context`` is True only for the transitions that read positions (``pos_kernel``,
    ``learnable``); the others get no Context and cost nothing beyond the transition itself.
    """

    def __init__(self, node_in: int, node_out: int, edge_feature_dims: list[int], n_levels: int,
                 latent: int = 128, hidden: int = 128, hidden_layers: int = 2, transition: str = "bistride",
                 layer_norm: bool = True, first_level: int = 0):
        super().__init__()
        if n_levels < 1:
            raise ValueError(f"n_levels must be at least 1, got {n_levels}")
        if not 0 <= first_level < n_levels:
            raise ValueError(f"first_level must lie in [0, n_levels) = [0, {n_levels}), got {first_level}")
        if transition not in TRANSITIONS:
            raise ValueError(f"unknown transition {transition!r}; choose one of {', '.join(TRANSITIONS)}")
        self.n_levels, self.first_level = n_levels, first_level
        add_unet_modules(self, node_in, node_out, edge_feature_dims, n_levels, latent, hidden, hidden_layers,
                         layer_norm, first_level)
        self.transitions = make_transitions(transition, n_levels, latent, hidden, hidden_layers)
        self.needs_context = self.transitions.needs_context

    def runs_groups(self) -> bool:
        """Whether :meth:`forward` takes several copies of a graph at once (``groups``): every block
        fused (:func:`bsms.models.blocks.fusable`) and a transition that reads no positions. The
        copies then cost one pass of the network over wider arrays, not one pass each."""
        blocks = [*self.down_blocks, self.bottom_block, *self.up_blocks]
        return not self.needs_context and all(fusable(block) for block in blocks)

    def forward(self, node_features: Tensor, levels: list[Level], context: Context | None = None,
                groups: int = 1) -> Tensor:
        """node_features: (N, node_in); levels[0] is the mesh itself -> (N, node_out).

        groups G > 1 (inference, :meth:`runs_groups`): G copies of the graph at once (a frame and
        its mirror image), node i's copy g in row i G + g of node_features and of the output, and
        each edge set's features the copies' side by side, (E, G F)."""
        if groups > 1 and not self.runs_groups():
            raise ValueError(f"this network runs {groups} copies of a graph at once only with every block lean "
                             "(model.layer_norm: false, model.hidden_layers: 1), the compiled library built and a "
                             "transition that reads no positions")
        depth = min(self.n_levels, len(levels))
        v = self.encoder(node_features).to(node_features.dtype)  # the residual stream: float32 under autocast
        latent = v.shape[1]
        width = latent * groups  # a node's row over all copies: transitions move whole rows
        skips = []
        first = self.first_level
        for l in range(depth - 1):
            if l >= first:
                v = self.down_blocks[l - first](v, levels[l].edge_sets, groups)
            skips.append(v)
            v = self.transitions.down(v.reshape(-1, width), levels, l, context).reshape(-1, latent)
        v = self.bottom_block(v, levels[depth - 1].edge_sets, groups)
        for l in reversed(range(depth - 1)):
            v = self.transitions.up(v.reshape(-1, width), levels, l, context).reshape(-1, latent)
            if l >= first:
                v = self.up_blocks[l - first](v, levels[l].edge_sets, groups)
            v = v + skips[l]
        return self.decoder(v)
