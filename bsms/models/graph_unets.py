"""Graph U-Nets (Gao & Ji 2019), the learnable-pooling baseline of thesis §4.4.2.4.

BSMS-GNN's U (encoder -> [block, pool] per level -> bottom block -> [unpool, block, + skip] per
level -> decoder, one message pass per level) with gPool and gUnpool in place of bi-stride
pooling, and the thesis's two modifications: the project's message-passing block instead of
GCN (1), and sparse coarse graphs instead of dense adjacency powers (2).

- gPool: score y = v . p / |p| with a learnable p per level; each graph of a batch keeps its
  ceil(ratio n) best-scored nodes (ties: the lower index); the kept latents are multiplied by
  sigmoid(y), Gao & Ji's gate (tanh is the variant of Cangea et al.). p learns through the gate.
- gUnpool: coarse latents go back to the rows they came from, zeros elsewhere.
- coarse edges: the second graph power A + A^2 of the mesh edges restricted to the kept nodes,
  by an index join of edge lists (never an N x N matrix). With the reach R = (I + A)[:, kept]
  (a kept node is reached from itself and from its mesh neighbours) the coarse mesh is R^T R
  and the coarse contacts are R^T C R, both without self-pairs: the construction of thesis
  eq. 4.1 for bi-stride contacts. A contact whose ends reach no kept node is dropped.
- coarse edge features: level 0's layout (material and world offsets and norms on mesh edges,
  only material ones for an Eulerian mesh; world offset and norm on contacts) between the kept
  nodes' own positions, normalised by normalisers this module owns, one per coarse level and
  edge set.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from bsms.models.blocks import EdgeSet
from bsms.models.bsms_gnn import add_unet_modules
from bsms.models.inputs import Context, Level
from bsms.models.normalize import Normalizer

__all__ = ["GraphUNets", "top_k_per_graph", "reach", "coarse_pairs", "coarse_edges"]


def top_k_per_graph(score: Tensor, graph: Tensor, n_graphs: int, ratio: float) -> Tensor:
    """Sorted indices of the ceil(ratio n_g) best-scored nodes of every graph g (at least one).

    score: (n,) float; graph: (n,) int64 graph of each node. Ties go to the lower index. The
    count forgives float round-off of ratio n (ratio 0.3 of 10 nodes keeps 3).
    """
    counts = torch.bincount(graph, minlength=n_graphs)
    keep = torch.ceil(counts.double() * ratio - 1e-9).long().clamp(min=1)
    order = torch.argsort(score, descending=True, stable=True)
    order = order[torch.argsort(graph[order], stable=True)]  # by graph, then by falling score
    starts = torch.cumsum(counts, 0) - counts
    owner = graph[order]
    rank = torch.arange(order.shape[0], device=score.device) - starts[owner]
    return torch.sort(order[rank < keep[owner]]).values


def reach(edge_index: Tensor, kept: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """CSR (indptr (n + 1,), columns) of R = (I + A)[:, kept], the n x n' 0/1 matrix of which kept
    nodes each node reaches in at most one edge of ``edge_index`` (2, E), both directions given."""
    device = kept.device
    position = torch.full((n,), -1, dtype=torch.long, device=device)
    position[kept] = torch.arange(kept.shape[0], device=device)
    senders, receivers = edge_index
    target = position[receivers]
    hit = target >= 0
    rows = torch.cat([kept, senders[hit]])
    cols = torch.cat([torch.arange(kept.shape[0], device=device), target[hit]])
    order = torch.argsort(rows * kept.shape[0] + cols)
    indptr = torch.zeros(n + 1, dtype=torch.long, device=device)
    indptr[1:] = torch.cumsum(torch.bincount(rows, minlength=n), 0)
    return indptr, cols[order]


def coarse_pairs(pairs: Tensor, indptr: Tensor, cols: Tensor, n_coarse: int) -> Tensor:
    """The pattern of R^T P R without its diagonal, for P the 0/1 matrix of ``pairs``.

    pairs: (2, P) int64 (i, j) node pairs; (indptr, cols): R as :func:`reach` gives it
    -> (2, P') unique (a, b), a in R(i), b in R(j), a != b, sorted by (a, b). Each pair yields
    |R(i)| |R(j)| candidates, enumerated without a loop.
    """
    i, j = pairs
    start_i, start_j = indptr[i], indptr[j]
    count_j = indptr[j + 1] - start_j
    count = (indptr[i + 1] - start_i) * count_j
    device = pairs.device
    owner = torch.repeat_interleave(torch.arange(count.shape[0], device=device), count)
    first = torch.repeat_interleave(torch.cumsum(count, 0) - count, count)  # of each pair's candidates
    offset = torch.arange(owner.shape[0], device=device) - first
    a = cols[start_i[owner] + torch.div(offset, count_j[owner], rounding_mode="floor")]
    b = cols[start_j[owner] + offset % count_j[owner]]
    apart = a != b
    keys = torch.unique(a[apart] * n_coarse + b[apart])
    return torch.stack([torch.div(keys, n_coarse, rounding_mode="floor"), keys % n_coarse])


def coarse_edges(edge_index: Tensor, kept: Tensor, n: int, contacts: list[Tensor] = ()) -> list[Tensor]:
    """Edge indices among the kept nodes (numbered in the order of ``kept``): first the mesh,
    A + A^2 restricted to them (R^T R), then each contact set C as R^T C R; see the module doc."""
    indptr, cols = reach(edge_index, kept, n)
    every = torch.arange(n, device=kept.device)
    return [coarse_pairs(torch.stack([every, every]), indptr, cols, kept.shape[0])] + [
        coarse_pairs(index, indptr, cols, kept.shape[0]) for index in contacts
    ]


def offsets(points: Tensor, index: Tensor, dim: int) -> Tensor:
    """points (n, k d), k points of dimension d per node -> (E, k (d + 1)): for each of the k,
    x_receiver - x_sender and its norm."""
    delta = points.index_select(0, index[1]) - points.index_select(0, index[0])
    delta = delta.view(delta.shape[0], points.shape[1] // dim, dim)
    return torch.cat([delta, delta.norm(dim=-1, keepdim=True)], dim=-1).flatten(1)


class _Pooled(NamedTuple):
    """What one gPool leaves for the way up: the fine level's latents (the skip), edge sets,
    level-0 node indices, and the fine indices of the nodes it kept."""

    skip: Tensor
    edge_sets: list[EdgeSet]
    nodes: Tensor
    kept: Tensor


class GraphUNets(nn.Module):
    """Graph U-Nets with message-passing blocks and sparse coarse graphs (see the module doc).

    Args:
        node_in: width of the (normalised) node inputs.
        node_out: width of the outputs.
        edge_feature_dims: widths of the level-0 edge sets: the mesh (2 (d + 1): material and
            world offsets and norms; d + 1: material only) first, then contacts (d + 1: world).
        n_levels: levels, the mesh included (n_levels - 1 gPools).
        ratio: fraction of each graph's nodes every gPool keeps.
        max_accumulations: batches after which the coarse edge normalisers freeze.
    """

    needs_context = True

    def __init__(self, node_in: int, node_out: int, edge_feature_dims: list[int], n_levels: int,
                 latent: int = 128, hidden: int = 128, hidden_layers: int = 2, ratio: float = 0.5,
                 max_accumulations: int = 1_000_000):
        super().__init__()
        if n_levels < 1:
            raise ValueError(f"n_levels must be at least 1, got {n_levels}")
        if not 0 < ratio < 1:
            raise ValueError(f"ratio must lie strictly between 0 and 1, got {ratio}")
        self.n_levels, self.ratio, self.edge_feature_dims = n_levels, ratio, list(edge_feature_dims)
        add_unet_modules(self, node_in, node_out, edge_feature_dims, n_levels, latent, hidden, hidden_layers)
        # one projection p per gPool, rows of unit expected norm
        self.projections = nn.Parameter(torch.randn(n_levels - 1, latent) / math.sqrt(latent))
        self.edge_normalizers = nn.ModuleList(
            nn.ModuleList(Normalizer(size, max_accumulations) for size in edge_feature_dims)
            for _ in range(n_levels - 1)
        )

    def forward(self, node_features: Tensor, levels: list[Level], context: Context) -> Tensor:
        """node_features: (N, node_in); only ``levels[0]`` (the mesh) is used -> (N, node_out)."""
        v = self.encoder(node_features).to(node_features.dtype)  # the residual stream: float32 under autocast
        v, edge_sets, _, pools = self._down(v, levels, context)
        v = self.bottom_block(v, edge_sets)
        for l in reversed(range(len(pools))):
            pool = pools[l]
            v = v.new_zeros(pool.skip.shape).index_copy(0, pool.kept, v)  # gUnpool
            v = self.up_blocks[l](v, pool.edge_sets) + pool.skip
        return self.decoder(v)

    def _down(self, v: Tensor, levels: list[Level],
              context: Context | None) -> tuple[Tensor, list[EdgeSet], Tensor, list[_Pooled]]:
        """The way down from the mesh, ``levels[0]``: (coarsest latents, its edge sets, its
        level-0 node indices, one :class:`_Pooled` per gPool)."""
        if context is None:
            raise ValueError("GraphUNets needs a Context (positions and graph ids) as its third argument")
        mesh = levels[0]
        nodes = mesh.nodes if mesh.nodes is not None else torch.arange(v.shape[0], device=v.device)
        graph, edge_sets, pools = context.graph[nodes], list(mesh.edge_sets), []
        for l in range(self.n_levels - 1):
            v = self.down_blocks[l](v, edge_sets)
            p = self.projections[l]
            score = (v * p).sum(dim=-1) / p.norm()  # elementwise: float32 under autocast too
            kept = top_k_per_graph(score.detach(), graph, context.n_graphs, self.ratio)
            pools.append(_Pooled(v, edge_sets, nodes, kept))
            v = v[kept] * torch.sigmoid(score[kept])[:, None]
            n, nodes, graph = nodes.shape[0], nodes[kept], graph[kept]
            edge_sets = self._coarse_edge_sets(l, edge_sets, kept, n, nodes, context)
        return v, edge_sets, nodes, pools

    def _coarse_edge_sets(self, l: int, edge_sets: list[EdgeSet], kept: Tensor, n: int, nodes: Tensor,
                          context: Context) -> list[EdgeSet]:
        """Edge sets of level l + 1 from those of level l and the kept nodes (level-l indices);
        ``nodes``: level-0 indices of the kept nodes."""
        with torch.no_grad():
            indices = coarse_edges(edge_sets[0].index, kept, n, [s.index for s in edge_sets[1:]])
        points, d = context.points.index_select(0, nodes), context.dim
        out = []
        for s, (normalizer, index) in enumerate(zip(self.edge_normalizers[l], indices, strict=True)):
            # mesh edges: material (+ world) offsets, 2 (d + 1) or d + 1 wide; contacts: world offsets
            width = self.edge_feature_dims[s] // (d + 1) * d
            start = 0 if s == 0 else points.shape[1] - width
            raw = offsets(points[:, start: start + width], index, d)
            if context.accumulate:
                normalizer.accumulate(raw)
            out.append(EdgeSet(index, normalizer(raw)))
        return out

    @torch.no_grad()
    def pooled_levels(self, node_features: Tensor, levels: list[Level], context: Context) -> list[Level]:
        """The levels gPool builds from these inputs (as :meth:`forward` does, normalisers left
        alone): one :class:`~bsms.models.inputs.Level` per level, the mesh first, with its edge
        sets and ``nodes``, the level-0 indices of its nodes (``down``/``up`` None)."""
        v = self.encoder(node_features).to(node_features.dtype)
        context = None if context is None else context._replace(accumulate=False)
        _, edge_sets, nodes, pools = self._down(v, levels, context)
        return [Level(p.edge_sets, None, None, p.nodes) for p in pools] + [Level(edge_sets, None, None, nodes)]

    def pooled_nodes(self, node_features: Tensor, levels: list[Level], context: Context) -> list[Tensor]:
        """Level-0 indices of the nodes of every level gPool builds, the mesh first (sorted)."""
        return [level.nodes for level in self.pooled_levels(node_features, levels, context)]
