"""MeshGraphNets (Pfaff et al. 2021) with the same MLPs as BSMS-GNN: the single-level baseline.

Differences from BSMS-GNN (thesis §4.4.2.2): edge features are encoded into edge latents that
are carried and updated through ``n_passes`` (15) message passes on the finest level only.
"""

from __future__ import annotations

from torch import Tensor, nn

from bsms.models.blocks import EdgeLatentBlock, EdgeSet
from bsms.models.inputs import Context, Level
from bsms.models.mlp import mlp


class MeshGraphNets(nn.Module):
    """Encode-process-decode on the mesh (level 0) with carried edge latents."""

    def __init__(self, node_in: int, node_out: int, edge_feature_dims: list[int], n_passes: int = 15,
                 latent: int = 128, hidden: int = 128, hidden_layers: int = 2):
        super().__init__()
        self.encoder = mlp(node_in, latent, hidden, hidden_layers)
        self.edge_encoders = nn.ModuleList(
            mlp(dim, latent, hidden, hidden_layers) for dim in edge_feature_dims
        )
        self.blocks = nn.ModuleList(
            EdgeLatentBlock(latent, len(edge_feature_dims), hidden, hidden_layers) for _ in range(n_passes)
        )
        self.decoder = mlp(latent, node_out, hidden, hidden_layers, layer_norm=False)

    def forward(self, node_features: Tensor, levels: list[Level], context: Context | None = None) -> Tensor:
        """node_features: (N, node_in); only ``levels[0]`` (the mesh) is used -> (N, node_out)."""
        v = self.encoder(node_features).to(node_features.dtype)  # latents: float32 under autocast
        edge_sets = [
            EdgeSet(index, encode(features).to(features.dtype))
            for encode, (index, features) in zip(self.edge_encoders, levels[0].edge_sets, strict=True)
        ]
        for block in self.blocks:
            v, edge_sets = block(v, edge_sets)
        return self.decoder(v)
