"""Message-passing blocks shared by all graph models (thesis eq. 4.2; MeshGraphNets processor).

A graph is given to a block as its node latents ``v (N, H)`` and a list of edge sets (mesh
edges, contact edges, ...), each with its own edge MLP. Edges run from ``senders`` j to
``receivers`` i; messages are summed per receiver.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from bsms.models.mlp import mlp


class EdgeSet(NamedTuple):
    """One set of directed edges: ``index (2, E)`` = (senders, receivers), ``features (E, F)``."""

    index: Tensor
    features: Tensor


def sum_per_receiver(messages: Tensor, receivers: Tensor, n_nodes: int) -> Tensor:
    """(E, H) messages summed onto their receivers -> (N, H)."""
    out = messages.new_zeros(n_nodes, messages.shape[1])
    return out.index_add_(0, receivers, messages)


class MessagePassingBlock(nn.Module):
    """One BSMS-GNN message pass (thesis eq. 4.2).

    e^s_ij = f^s([features^s_ij, v_i, v_j]) per edge set s;  v_i <- v_i + f^V([v_i, sum_j e^1_ij, ...]).
    The edge inputs (offsets and norms) are appended to the node latents rather than encoded.

    Args:
        latent: H, the node latent width.
        edge_feature_dims: F^s of each edge set, in the order edge sets are passed to forward.
    """

    def __init__(self, latent: int, edge_feature_dims: list[int], hidden: int = 128, hidden_layers: int = 2):
        super().__init__()
        self.edge_mlps = nn.ModuleList(
            mlp(dim + 2 * latent, latent, hidden, hidden_layers) for dim in edge_feature_dims
        )
        self.node_mlp = mlp(latent * (1 + len(edge_feature_dims)), latent, hidden, hidden_layers)

    def forward(self, v: Tensor, edge_sets: list[EdgeSet]) -> Tensor:
        """v: (N, H), one EdgeSet per edge MLP -> (N, H)."""
        if len(edge_sets) != len(self.edge_mlps):
            raise ValueError(f"block expects {len(self.edge_mlps)} edge sets, got {len(edge_sets)}")
        aggregated = []
        for edge_mlp, (index, features) in zip(self.edge_mlps, edge_sets, strict=True):
            senders, receivers = index
            messages = edge_mlp(torch.cat([features, v[receivers], v[senders]], dim=-1))
            aggregated.append(sum_per_receiver(messages, receivers, v.shape[0]))
        return v + self.node_mlp(torch.cat([v, *aggregated], dim=-1))


class EdgeLatentBlock(nn.Module):
    """One MeshGraphNets processor step: edge latents are carried and updated with residuals.

    e^s_ij <- e^s_ij + f^s([e^s_ij, v_i, v_j]);  v_i <- v_i + f^V([v_i, sum_j e^1_ij, ...]).
    """

    def __init__(self, latent: int, n_edge_sets: int, hidden: int = 128, hidden_layers: int = 2):
        super().__init__()
        self.edge_mlps = nn.ModuleList(
            mlp(3 * latent, latent, hidden, hidden_layers) for _ in range(n_edge_sets)
        )
        self.node_mlp = mlp(latent * (1 + n_edge_sets), latent, hidden, hidden_layers)

    def forward(self, v: Tensor, edge_sets: list[EdgeSet]) -> tuple[Tensor, list[EdgeSet]]:
        """v: (N, H), edge sets with (E, H) latents -> updated v and edge sets."""
        updated, aggregated = [], []
        for edge_mlp, (index, latents) in zip(self.edge_mlps, edge_sets, strict=True):
            senders, receivers = index
            latents = latents + edge_mlp(torch.cat([latents, v[receivers], v[senders]], dim=-1))
            updated.append(EdgeSet(index, latents))
            aggregated.append(sum_per_receiver(latents, receivers, v.shape[0]))
        return v + self.node_mlp(torch.cat([v, *aggregated], dim=-1)), updated
