"""Message-passing blocks shared by all graph models (thesis eq. 4.2; MeshGraphNets processor).

A graph is given to a block as its node latents ``v (N, H)`` and a list of edge sets (mesh
edges, contact edges, ...), each with its own edge MLP. Edges run from ``senders`` j to
``receivers`` i; messages are summed per receiver.

The first layer of an edge MLP reads the concatenation [e_ij, v_i, v_j]; with its weight
split by columns as [W_e | W_r | W_s] it equals W_e e_ij + (W_r v)_i + (W_s v)_j + b. The
node products W_r v and W_s v are computed once per node and gathered per edge (an edge set
with fewer edges than nodes gathers v first instead), so the same parameters do the same
computation with fewer multiplications; the node MLP's first layer on [v, sum e^1, ...] is
split the same way. An edge MLP that ends in a Linear (no LayerNorm after it) has its messages
summed per receiver before that layer: sum_j (W h_ij + b) = W (sum_j h_ij) + deg_i b, one
product per node instead of one per edge. The parameters and state_dict keys are those of the
concatenated form.

At inference a lean block (every MLP Linear, ReLU, Linear, as the press recipe's) runs
:func:`fused_pass`: all node products of its edge MLPs and the node MLP's own part in one matrix
product, each edge set's messages summed with their edge counts by the compiled loop, and each
edge MLP's last Linear folded into the node MLP's first: W_k (W sum_j h_ij + deg_i b) =
[W_k W | W_k b] [sum_j h_ij; deg_i], one product per edge set instead of two.
"""

from __future__ import annotations

from itertools import islice
from typing import NamedTuple

import torch
from torch import Tensor, nn

from bsms.models import native
from bsms.models.mlp import mlp


class EdgeSet(NamedTuple):
    """One set of directed edges: ``index (2, E)`` = (senders, receivers), ``features (E, F)``."""

    index: Tensor
    features: Tensor


def sum_per_receiver(messages: Tensor, receivers: Tensor, n_nodes: int) -> Tensor:
    """(E, H) messages summed onto their receivers -> (N, H)."""
    out = messages.new_zeros(n_nodes, messages.shape[1])
    return out.index_add_(0, receivers, messages)


def node_products(linear: nn.Linear, v: Tensor, f: int) -> Tensor:
    """(N, 2 hidden): per node [W_r v + b | W_s v], the receiver and sender parts of an edge MLP's
    first layer (its weight split by columns as [W_e | W_r | W_s], W_e of width ``f``)."""
    h, weight = v.shape[1], linear.weight
    return torch.addmm(torch.cat([linear.bias, torch.zeros_like(linear.bias)]), v,
                       torch.cat([weight[:, f: f + h], weight[:, f + h:]]).T)


def edge_first_layer(linear: nn.Linear, features: Tensor, v: Tensor, index: Tensor) -> Tensor:
    """``linear(cat([features, v[receivers], v[senders]], -1))`` without the concatenation.

    features: (E, F), v: (N, H), index: (2, E) = (senders, receivers) -> (E, hidden).
    """
    f = features.shape[1]
    weight = linear.weight
    senders, receivers = index
    if index.shape[1] >= v.shape[0]:  # one product per node, gathered per edge
        # rows 2i and 2i + 1 of ``products`` are W_r v_i + b and W_s v_i; each edge sums one of each
        products = node_products(linear, v, f)
        pairs = torch.stack([2 * receivers, 2 * senders + 1], dim=1)
        out = nn.functional.embedding_bag(pairs, products.view(2 * v.shape[0], -1), mode="sum")
    else:  # fewer edges than nodes: gather first, multiply per edge
        gathered = torch.cat([v.index_select(0, receivers), v.index_select(0, senders)], dim=-1)
        out = torch.addmm(linear.bias, gathered, weight[:, f:].T)
    # addmm_ works in place, where autocast casts nothing: the edge term joins in the node terms' dtype
    return out.addmm_(features.to(out.dtype), weight[:, :f].T.to(out.dtype))


def _compilable(edge_mlp: nn.Sequential) -> bool:
    """Whether an MLP is Linear, ReLU, Linear (one hidden layer, no LayerNorm): an edge MLP whose
    messages the compiled loop sums, and what every MLP of a fused block is."""
    return len(edge_mlp) == 3 and isinstance(edge_mlp[1], nn.ReLU) and isinstance(edge_mlp[0], nn.Linear) \
        and isinstance(edge_mlp[2], nn.Linear)


def compiled_message_passing(model: nn.Module, dtype: torch.dtype) -> bool:
    """Whether every message pass of ``model`` sums its messages in the compiled loop at
    inference on a CPU in ``dtype`` (float32 only, and the library built): such a model keeps
    no (E, H) per-edge activations, whatever the size of the graph."""
    blocks = [m for m in model.modules() if isinstance(m, MessagePassingBlock)]
    return dtype == torch.float32 and bool(blocks) and native.library() is not None \
        and all(_compilable(edge_mlp) for block in blocks for edge_mlp in block.edge_mlps)


def fusable(block: MessagePassingBlock) -> bool:
    """Whether ``block`` is lean (every MLP Linear, ReLU, Linear) and the compiled library is
    built: at inference in float32 on a CPU it then runs :func:`fused_pass`."""
    return _compilable(block.node_mlp) and all(_compilable(edge_mlp) for edge_mlp in block.edge_mlps) \
        and native.library() is not None


def fused_pass(block: MessagePassingBlock, v: Tensor, edge_sets: list[EdgeSet], groups: int = 1) -> Tensor | None:
    """``block(v, edge_sets)`` for a lean block at inference in float32 on a CPU, fused (module
    docstring); None where it does not apply (gradients, autocast, other MLPs or dtypes, no
    compiled library): the block then runs its general path. ``groups`` G: v holds G copies of
    the graph's latents, node i's copy g in row i G + g, and each edge set's features the G
    copies' side by side (E, G F): :func:`bsms.models.native.edge_sums`."""
    if torch.is_grad_enabled() or v.device.type != "cpu" or v.dtype != torch.float32 \
            or torch.is_autocast_enabled("cpu") or not fusable(block):
        return None
    h, node_first, node_last = v.shape[1], block.node_mlp[0], block.node_mlp[2]
    pairs = enumerate(zip(block.edge_mlps, edge_sets, strict=True))
    active = [(k, edge_mlp, edge_set) for k, (edge_mlp, edge_set) in pairs if edge_set.index.shape[1]]
    weights, biases = [], []
    for _, edge_mlp, (_, features) in active:
        first, f = edge_mlp[0], features.shape[1] // groups
        weights += [first.weight[:, f: f + h], first.weight[:, f + h:]]
        biases += [first.bias, torch.zeros_like(first.bias)]
    products = torch.addmm(torch.cat([*biases, node_first.bias]), v,
                           torch.cat([*weights, node_first.weight[:, :h]]).T)
    hidden, start = products[:, products.shape[1] - node_first.out_features:], 0
    for k, edge_mlp, (index, features) in active:
        first, last, f = edge_mlp[0], edge_mlp[2], features.shape[1] // groups
        width = 2 * first.out_features
        sums = native.edge_sums(products[:, start: start + width], features, first.weight[:, :f], index, counts=True,
                                groups=groups)
        if sums is None:
            return None
        start += width
        folded = node_first.weight[:, (k + 1) * h: (k + 2) * h] @ torch.cat([last.weight, last.bias[:, None]], 1)
        hidden = torch.addmm(hidden, sums, folded.T)
    return torch.addmm(node_last.bias, hidden.relu_(), node_last.weight.T).add_(v)


def _compiled_sums(edge_mlp: nn.Sequential, features: Tensor, v: Tensor, index: Tensor) -> Tensor | None:
    """The sums over each receiver's edges of relu(first layer) by the compiled loop
    (:func:`bsms.models.native.edge_sums`), for an MLP [Linear, ReLU, Linear] at inference in
    float32 on a CPU; None elsewhere (the torch path runs)."""
    if torch.is_grad_enabled() or not _compilable(edge_mlp) or v.device.type != "cpu" or v.dtype != torch.float32 \
            or torch.is_autocast_enabled("cpu"):
        return None
    first, f = edge_mlp[0], features.shape[1]
    return native.edge_sums(node_products(first, v, f), features, first.weight[:, :f], index)


def summed_messages(edge_mlp: nn.Sequential, features: Tensor, v: Tensor, index: Tensor) -> Tensor:
    """``sum_per_receiver(edge_mlp_messages(edge_mlp, features, v, index), receivers, N)``, (N, out);
    an MLP whose last layer is a Linear after others gets it applied once per node, to the sums
    of its inputs (exact up to float round-off, and so are its gradients). At inference a
    [Linear, ReLU, Linear] MLP's sums come from one compiled pass over the edges where it runs."""
    receivers, n_nodes = index[1], v.shape[0]
    last = edge_mlp[-1]
    if len(edge_mlp) == 1 or not isinstance(last, nn.Linear):
        return sum_per_receiver(edge_mlp_messages(edge_mlp, features, v, index), receivers, n_nodes)
    summed = _compiled_sums(edge_mlp, features, v, index)
    if summed is None:
        hidden = edge_first_layer(edge_mlp[0], features, v, index)
        for layer in islice(edge_mlp, 1, len(edge_mlp) - 1):
            hidden = layer(hidden)
        summed = sum_per_receiver(hidden, receivers, n_nodes)
    degree = torch.bincount(receivers, minlength=n_nodes).to(summed.dtype)[:, None]
    return torch.addmm(degree * last.bias.to(summed.dtype), summed, last.weight.T.to(summed.dtype))


def node_first_layer(linear: nn.Linear, v: Tensor, aggregated: list[Tensor | None]) -> Tensor:
    """``linear(cat([v, *aggregated], -1))``, all parts (N, H); a None part (an edge set without
    edges) stands for zeros and costs nothing."""
    h = v.shape[1]
    out = torch.addmm(linear.bias, v, linear.weight[:, :h].T)
    for k, part in enumerate(aggregated, start=1):
        if part is not None:
            out.addmm_(part.to(out.dtype), linear.weight[:, k * h: (k + 1) * h].T.to(out.dtype))
    return out


def after_first_layer(layers: nn.Sequential, hidden: Tensor) -> Tensor:
    """The rest of an :func:`~bsms.models.mlp.mlp` after its first Linear."""
    for layer in islice(layers, 1, None):
        hidden = layer(hidden)
    return hidden


def edge_mlp_messages(edge_mlp: nn.Sequential, features: Tensor, v: Tensor, index: Tensor) -> Tensor:
    """``edge_mlp(cat([features, v_receivers, v_senders], -1))``, (E, out), computed split."""
    return after_first_layer(edge_mlp, edge_first_layer(edge_mlp[0], features, v, index))


def node_update(node_mlp: nn.Sequential, v: Tensor, aggregated: list[Tensor | None]) -> Tensor:
    """``node_mlp(cat([v, *aggregated], -1))`` computed split (None: an all-zero aggregate)."""
    return after_first_layer(node_mlp, node_first_layer(node_mlp[0], v, aggregated))


def _skippable(index: Tensor) -> bool:
    """An edge set without edges sends zero messages; without gradients it is skipped. (Training
    runs it, so that its MLP gets zero gradients as every other parameter does.)"""
    return index.shape[1] == 0 and not torch.is_grad_enabled()


class MessagePassingBlock(nn.Module):
    """One BSMS-GNN message pass (thesis eq. 4.2).

    e^s_ij = f^s([features^s_ij, v_i, v_j]) per edge set s;  v_i <- v_i + f^V([v_i, sum_j e^1_ij, ...]).
    The edge inputs (offsets and norms) are appended to the node latents rather than encoded.

    Args:
        latent: H, the node latent width.
        edge_feature_dims: F^s of each edge set, in the order edge sets are passed to forward.
        layer_norm: LayerNorm on the output of every MLP (the thesis' choice).
    """

    def __init__(self, latent: int, edge_feature_dims: list[int], hidden: int = 128, hidden_layers: int = 2,
                 layer_norm: bool = True):
        super().__init__()
        self.edge_mlps = nn.ModuleList(
            mlp(dim + 2 * latent, latent, hidden, hidden_layers, layer_norm) for dim in edge_feature_dims
        )
        self.node_mlp = mlp(latent * (1 + len(edge_feature_dims)), latent, hidden, hidden_layers, layer_norm)

    def forward(self, v: Tensor, edge_sets: list[EdgeSet], groups: int = 1) -> Tensor:
        """v: (N, H), one EdgeSet per edge MLP -> (N, H). ``groups`` > 1: v holds that many copies
        of the graph's latents, as :func:`fused_pass` takes them (the only path that runs them)."""
        if len(edge_sets) != len(self.edge_mlps):
            raise ValueError(f"block expects {len(self.edge_mlps)} edge sets, got {len(edge_sets)}")
        fused = fused_pass(self, v, edge_sets, groups)
        if fused is not None:
            return fused
        if groups != 1:
            raise ValueError(f"a block passes messages for {groups} copies of a graph at once only on its fused path: "
                             "a lean block (model.layer_norm: false, model.hidden_layers: 1) at inference in float32 "
                             "on a CPU, with the compiled library built")
        aggregated = []
        for edge_mlp, (index, features) in zip(self.edge_mlps, edge_sets, strict=True):
            if _skippable(index):
                aggregated.append(None)
                continue
            aggregated.append(summed_messages(edge_mlp, features, v, index))
        return v + node_update(self.node_mlp, v, aggregated)


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
            if _skippable(index):
                updated.append(EdgeSet(index, latents))
                aggregated.append(None)
                continue
            latents = latents + edge_mlp_messages(edge_mlp, latents, v, index)
            updated.append(EdgeSet(index, latents))
            aggregated.append(sum_per_receiver(latents, index[1], v.shape[0]))
        return v + node_update(self.node_mlp, v, aggregated), updated
