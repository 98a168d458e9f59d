"""Transitions between the levels of BSMS-GNN (thesis §4.4.4.1, Table 4.7).

A transition moves node latents from level l to level l+1 (``down``) and back (``up``). Every
variant here reads the sparsity patterns of the bi-stride operators stored in a
:class:`~bsms.models.inputs.Level` -- down: the closed neighbourhood (A + I) of each kept node;
up: the transpose, each fine node's kept neighbours (and itself if kept) -- and differs only in
the weights put on those pairs:

``bistride``   the stored weights of §4.3.2 (nodal-weight aggregation and contribution-share
               return, :mod:`bsms.graph.transitions`).
``none``       pool = the kept nodes' latents picked by index; unpool = coarse latents put back
               at their fine nodes, zeros on the dropped ones (Graph U-Nets without interpolation).
``graph_conv`` one unweighted graph convolution without activation: the mean over the pattern
               row, uniform weights 1 / (row count). Non-parametric.
``pos_kernel`` inverse-distance weights between the two nodes' world positions in the current
               frame, normalised per row (Liu et al. 2021). Non-parametric;
               :func:`inverse_distance_weights` explains the self pair.
``learnable``  one message pass per transition (Fortunato et al. 2022):
               :class:`MessagePassTransition`, own parameters per level and direction.

Each transition object has ``down(v, levels, l, context)`` and ``up(v, levels, l, context)``
and a ``needs_context`` flag: only ``pos_kernel`` and ``learnable`` read positions, so only
they make :class:`~bsms.models.simulator.LearnedSimulator` build a Context.

Level-0 indices: ``Level.nodes`` gives the level-0 index of every node of a level (for a
batch, of the batch's level 0), so a pair's two nodes and their positions are found without
any per-graph bookkeeping, and a batch of graphs gives each graph its own result.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from bsms.graph import Transition
from bsms.models.blocks import after_first_layer, node_update, sum_per_receiver
from bsms.models.inputs import Context, Level
from bsms.models.mlp import mlp
from bsms.models.normalize import Normalizer

__all__ = [
    "TRANSITIONS", "BiStrideTransition", "GraphConvTransition", "IndexTransition", "LearnableTransition",
    "MAX_DIM", "MessagePassTransition", "PosKernelTransition", "apply_transition", "inverse_distance_weights",
    "kept_local_indices", "make_transitions", "mean_over_rows", "pair_offsets", "uniform_weights",
]

TRANSITIONS = ("bistride", "none", "graph_conv", "pos_kernel", "learnable")

# Offsets are padded to this many components, so that the learnable transition's parameters
# do not depend on the spatial dimension (which the core is not told).
MAX_DIM = 3
# Distances below this (coincident nodes of a collapsed mesh) count as this: finite weights
# whose row-normalisation still gives the coincident pair nearly all of the row.
_MIN_DISTANCE = 1e-18


def apply_transition(v: Tensor, transition: Transition) -> Tensor:
    """(n_in, H) -> (n_out, H): out_r = sum over triplets (r, c, w) of w * v_c (thesis §4.3.2).

    Triplets sorted by row (every pattern a hierarchy or a frame builds) are summed as one
    weighted bag per row (``embedding_bag``: gather, weigh and sum in one pass); others are
    gathered, weighed and added per triplet. Both give the same sums up to float round-off."""
    rows, weights = transition.rows, transition.weights.to(v.dtype)
    if rows.numel() and bool((rows[1:] >= rows[:-1]).all()):
        counts = torch.bincount(rows, minlength=transition.shape[0])
        starts = counts.cumsum(0) - counts  # each row's first triplet
        return nn.functional.embedding_bag(transition.cols, v, starts, mode="sum", per_sample_weights=weights)
    out = v.new_zeros(transition.shape[0], v.shape[1])
    return out.index_add_(0, rows, v.index_select(0, transition.cols) * weights[:, None])


# ----------------------------------------------------------------------------- pattern helpers
def _nodes(levels: list[Level], l: int) -> Tensor:
    nodes = levels[l].nodes
    if nodes is None:
        raise ValueError(f"this transition needs the level-0 index of every node (Level.nodes); level {l} has none")
    return nodes


def kept_local_indices(levels: list[Level], l: int) -> Tensor:
    """(n_{l+1},) int64: the level-l index of each node of level l+1 (an inverse map of
    level l's level-0 indices, read at level l+1's; ``levels[0].nodes`` spans level 0)."""
    fine, coarse = _nodes(levels, l), _nodes(levels, l + 1)
    inverse = torch.full((_nodes(levels, 0).shape[0],), -1, dtype=torch.long, device=fine.device)
    inverse.index_copy_(0, fine, torch.arange(fine.shape[0], device=fine.device))
    return inverse.index_select(0, coarse)


def pair_ids(levels: list[Level], l: int, kind: str) -> tuple[Transition, Tensor, Tensor]:
    """(pattern, receiver ids, sender ids) of the ``down`` or ``up`` pattern between levels l and
    l+1; the ids are level-0 indices (nnz,) of each pair's receiver (row) and sender (col)."""
    pattern = levels[l].down if kind == "down" else levels[l].up
    if pattern is None:
        raise ValueError(f"level {l} has no {kind} transition")
    rows_level, cols_level = (l + 1, l) if kind == "down" else (l, l + 1)
    receivers = _nodes(levels, rows_level).index_select(0, pattern.rows)
    senders = _nodes(levels, cols_level).index_select(0, pattern.cols)
    return pattern, receivers, senders


def row_counts(pattern: Transition, dtype: torch.dtype) -> Tensor:
    """(n_out,) number of pairs in each row of the pattern."""
    return torch.bincount(pattern.rows, minlength=pattern.shape[0]).to(dtype)


def uniform_weights(pattern: Transition) -> Tensor:
    """(nnz,) float32 weights 1 / (row count) of the unweighted graph convolution."""
    return row_counts(pattern, torch.float32).reciprocal().index_select(0, pattern.rows)


def mean_over_rows(v: Tensor, pattern: Transition) -> Tensor:
    """:func:`apply_transition` with :func:`uniform_weights`, computed as a sum over the row
    divided by its count (so a constant whose row sums are exact comes back exactly)."""
    total = sum_per_receiver(v.index_select(0, pattern.cols), pattern.rows, pattern.shape[0])
    return total / row_counts(pattern, v.dtype).clamp_min(1)[:, None]


def inverse_distance_weights(pattern: Transition, receivers: Tensor, senders: Tensor, pos: Tensor) -> Tensor:
    """(nnz,) float32 weights of ``pos_kernel``: w ∝ 1 / |x_receiver - x_sender|, rows summing to 1.

    pattern: its rows (the output node of each pair) and shape; receivers, senders: (nnz,)
    level-0 ids of each pair's nodes; pos: (N0, d) world positions of level 0.

    Self pair (a kept node and its own coarse copy, distance 0): it gets the weight of the
    nearest other node of its row, as if its own value sat one nearest-neighbour distance
    away -- never less than any neighbour's weight, never all of the row (1 / 0 would make
    pooling a mere pick, the ``none`` transition). No length scale enters, so the weights are
    invariant to translation, rotation and uniform scaling of the positions. A row holding
    only its self pair gets weight 1.
    """
    delta = pos.index_select(0, receivers).float() - pos.index_select(0, senders).float()
    distance = (delta * delta).sum(dim=-1).sqrt()
    is_self = receivers == senders
    inverse = torch.where(is_self, torch.zeros_like(distance), distance.clamp_min(_MIN_DISTANCE).reciprocal())
    n_rows = pattern.shape[0]
    nearest = inverse.new_zeros(n_rows).scatter_reduce_(0, pattern.rows, inverse, "amax")
    nearest = torch.where(nearest > 0, nearest, torch.ones_like(nearest))
    inverse = torch.where(is_self, nearest.index_select(0, pattern.rows), inverse)
    total = inverse.new_zeros(n_rows).index_add_(0, pattern.rows, inverse)
    return inverse / total.index_select(0, pattern.rows)


def pair_offsets(points: Tensor, receivers: Tensor, senders: Tensor, dim: int) -> Tensor:
    """points: (N0, k d), k points of dimension d per node (rest then world) -> (nnz, k (MAX_DIM + 1)):
    for each, x_receiver - x_sender padded with zeros to MAX_DIM components, and its norm (the
    layout of the mesh-edge features, of the same width in 1D, 2D and 3D)."""
    if not 1 <= dim <= MAX_DIM:
        raise ValueError(f"positions must have 1 to {MAX_DIM} dimensions, got {dim}")
    delta = points.index_select(0, receivers) - points.index_select(0, senders)
    delta = delta.view(delta.shape[0], points.shape[1] // dim, dim)
    norms = delta.norm(dim=-1, keepdim=True)
    return torch.cat([nn.functional.pad(delta, (0, MAX_DIM - dim)), norms], dim=-1).flatten(1)


def _require(context: Context | None, name: str) -> Context:
    if context is None:
        raise ValueError(f"the {name} transition reads positions: pass a Context (LearnedSimulator does "
                         f"when the core's needs_context is True)")
    return context


# ----------------------------------------------------------------------------- non-parametric
class BiStrideTransition(nn.Module):
    """The stored bi-stride weights (thesis §4.3.2); no parameters, no positions."""

    needs_context = False

    def down(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        return apply_transition(v, levels[l].down)

    def up(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        return apply_transition(v, levels[l].up)


class IndexTransition(nn.Module):
    """``none``: pick the kept nodes' latents; put them back, zeros on the dropped nodes."""

    needs_context = False

    def down(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        return v.index_select(0, kept_local_indices(levels, l))

    def up(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        kept = kept_local_indices(levels, l)
        return v.new_zeros(_nodes(levels, l).shape[0], v.shape[1]).index_copy_(0, kept, v)


class GraphConvTransition(nn.Module):
    """``graph_conv``: the mean over each row of the bi-stride patterns."""

    needs_context = False

    def down(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        return mean_over_rows(v, levels[l].down)

    def up(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        return mean_over_rows(v, levels[l].up)


class PosKernelTransition(nn.Module):
    """``pos_kernel``: inverse world-distance weights of the current frame on the bi-stride patterns."""

    needs_context = True

    def _weighted(self, v: Tensor, levels: list[Level], l: int, kind: str, context: Context | None) -> Tensor:
        pattern, receivers, senders = pair_ids(levels, l, kind)
        weights = inverse_distance_weights(pattern, receivers, senders, _require(context, "pos_kernel").pos)
        return apply_transition(v, Transition(pattern.rows, pattern.cols, weights, pattern.shape))

    def down(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        return self._weighted(v, levels, l, "down", context)

    def up(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        return self._weighted(v, levels, l, "up", context)


# ----------------------------------------------------------------------------- learnable
class MessagePassTransition(nn.Module):
    """One message pass over the pairs of a transition pattern (one level, one direction).

    For each pair (sender s -> receiver r): m_sr = f^E([o_sr, v_s]) with o_sr the normalised
    offset features x_r - x_s and |x_r - x_s| of rest and world positions (the mesh-edge
    layout, padded to 3D: :func:`pair_offsets`); then v_r <- u_r + f^V([u_r, sum_s m_sr]),
    where u is the ``none`` transition of v (down: the kept node's own fine latent; up: its
    coarse latent on a kept node, zeros on a dropped one) -- the residual every receiver has a
    shape for.

    Args:
        latent: H; hidden, hidden_layers: of both MLPs.
    """

    def __init__(self, latent: int, hidden: int, hidden_layers: int):
        super().__init__()
        features = 2 * (MAX_DIM + 1)
        self.edge_mlp = mlp(features + latent, latent, hidden, hidden_layers)
        self.node_mlp = mlp(2 * latent, latent, hidden, hidden_layers)
        self.normalizer = Normalizer(features)

    def messages(self, features: Tensor, v: Tensor, senders: Tensor) -> Tensor:
        """``edge_mlp(cat([features, v[senders]], -1))``, its first layer split: the sender
        product W_s v once per node (patterns have more pairs than nodes), gathered per pair."""
        linear, f = self.edge_mlp[0], features.shape[1]
        products = torch.mm(v, linear.weight[:, f:].T)
        hidden = torch.addmm(linear.bias, features, linear.weight[:, :f].T)
        hidden = hidden + products.index_select(0, senders).to(hidden.dtype)
        return after_first_layer(self.edge_mlp, hidden)

    def forward(self, v: Tensor, own: Tensor, pattern: Transition, receivers: Tensor, senders: Tensor,
                context: Context) -> Tensor:
        """v: (n_in, H) sender latents; own: (n_out, H) receivers' residual base;
        receivers, senders: level-0 ids of each pair -> (n_out, H)."""
        raw = pair_offsets(context.points, receivers, senders, context.dim)
        if context.accumulate:
            self.normalizer.accumulate(raw)
        messages = self.messages(self.normalizer(raw), v, pattern.cols)
        aggregated = sum_per_receiver(messages, pattern.rows, pattern.shape[0])
        return own + node_update(self.node_mlp, own, [aggregated])


class LearnableTransition(nn.Module):
    """``learnable``: a :class:`MessagePassTransition` per level and direction.

    State_dict keys: ``passes.{l}.{0 = down, 1 = up}.{edge_mlp, node_mlp, normalizer}.*``.
    """

    needs_context = True

    def __init__(self, n_levels: int, latent: int, hidden: int, hidden_layers: int):
        super().__init__()
        self.passes = nn.ModuleList(
            nn.ModuleList(MessagePassTransition(latent, hidden, hidden_layers) for _ in range(2))
            for _ in range(n_levels - 1)
        )
        self.index = IndexTransition()

    def down(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        pattern, receivers, senders = pair_ids(levels, l, "down")
        own = self.index.down(v, levels, l)
        return self.passes[l][0](v, own, pattern, receivers, senders, _require(context, "learnable"))

    def up(self, v: Tensor, levels: list[Level], l: int, context: Context | None = None) -> Tensor:
        pattern, receivers, senders = pair_ids(levels, l, "up")
        own = self.index.up(v, levels, l)
        return self.passes[l][1](v, own, pattern, receivers, senders, _require(context, "learnable"))


def make_transitions(kind: str, n_levels: int, latent: int, hidden: int, hidden_layers: int) -> nn.Module:
    """The transition object of ``kind`` (one of :data:`TRANSITIONS`) for a core of ``n_levels``."""
    if kind == "learnable":
        return LearnableTransition(n_levels, latent, hidden, hidden_layers)
    simple = {"bistride": BiStrideTransition, "none": IndexTransition, "graph_conv": GraphConvTransition,
              "pos_kernel": PosKernelTransition}
    if kind not in simple:
        raise ValueError(f"unknown transition {kind!r}; choose one of {', '.join(TRANSITIONS)}")
    return simple[kind]()
