"""The one MLP factory every model in bsms uses, so that comparisons between models are fair."""

from __future__ import annotations

from torch import nn


def mlp(
    in_dim: int, out_dim: int, hidden: int = 128, hidden_layers: int = 2, layer_norm: bool = True
) -> nn.Sequential:
    """ReLU MLP with ``hidden_layers`` hidden layers of width ``hidden``; LayerNorm on the output.

    Thesis §4.4.2.1: two hidden layers of 128, LayerNorm on every MLP but the decoder
    (build the decoder with ``layer_norm=False``).
    """
    layers: list[nn.Module] = []
    width = in_dim
    for _ in range(hidden_layers):
        layers += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    layers.append(nn.Linear(width, out_dim))
    if layer_norm:
        layers.append(nn.LayerNorm(out_dim))
    return nn.Sequential(*layers)
