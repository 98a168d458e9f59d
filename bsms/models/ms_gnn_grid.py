"""MS-GNN-Grid (Lino et al. 2021, 2022a) with the same MLPs as BSMS-GNN: the baseline whose
hierarchy comes from spatial proximity on regular grids (thesis §4.4.2.3, Table 4.3).

Levels: level 0 is the mesh; levels 1 .. L-1 (L = ``len(passes)``) are regular grids of cell
size dx, dx * inflation, dx * inflation^2, ... Only occupied cells are nodes. Table 4.3's
"4 levels, [4, 2, 2, 4] passes" is read as: four passes on the mesh, two on each of the two
middle grids, four on the coarsest grid (the thesis: "four at the top and bottom levels and two
for the others"). The network is U-shaped (Lino et al. 2022a): level l < L-1 runs passes[l]
passes on the way down and passes[l] more on the way up, the coarsest level passes[-1] once.

Modules (thesis §4.4.2.3): the node encoder and, at the finest level only, the edge encoder
whose latents are carried through the mesh passes (MeshGraphNets); an aggregation per
transition down (edge MLP on [v_member, r], averaged per cell, node MLP); plain message
passes on the grids (:class:`MessagePassingBlock`, geometric edge features appended each
pass); a return module per transition up (v_i <- v_i + f([V_cell(i), v_i, r_i]) on the skip
saved on the way down); the decoder.

Grids are rebuilt from the WORLD positions of every frame, so a cell joins nodes close in space
however far apart they are in the material (the point of the baseline, and its weakness).
Each graph of a batch has its own grid, anchored at its own minimum corner (translation
invariant); cells are keyed by (graph, integer cell coordinates), so graphs never share cells.
Geometric features are offsets divided by the cell size of the coarser level (dimensionless,
no normaliser needed), zero-padded to 3 components, and their norm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from bsms.models.blocks import EdgeLatentBlock, EdgeSet, MessagePassingBlock, sum_per_receiver
from bsms.models.inputs import Context, Level
from bsms.models.mlp import mlp

GEOMETRY = 4  # geometric features: an offset padded to 3 components, and its norm
INSET = 0.3  # the grid origin sits this many cells below each graph's minimum corner (see cell_coords)


class Grid(NamedTuple):
    """One grid level, seen from the level above it (the finer one: the mesh or a finer grid).

    parent (n_fine,): the cell of each finer node; n: occupied cells; count (n, 1): finer nodes
    per cell, float32; relative (n_fine, GEOMETRY): (finer node position - its cell's position)
    / cell size, float32; edges: neighbouring cells (3^d - 1 offsets, both directions) with
    (position_receiver - position_sender) / cell size. A cell's position is the mean world
    position of the mesh nodes in it. graph (n,), coords (n, d): each cell's graph and integer
    cell coordinates (for tests and inspection).
    """

    parent: Tensor
    n: int
    count: Tensor
    relative: Tensor
    edges: EdgeSet
    graph: Tensor
    coords: Tensor


def geometry(scaled: Tensor) -> Tensor:
    """(n, d) dimensionless offsets, float64 -> (n, GEOMETRY) float32: offsets padded to 3, norm."""
    padded = nn.functional.pad(scaled, (0, GEOMETRY - 1 - scaled.shape[1]))
    return torch.cat([padded, scaled.norm(dim=1, keepdim=True)], dim=1).float()


def cell_size(context: Context, mesh_index: Tensor, dx: Sequence[float]) -> Tensor:
    """(n_graphs, d) float64 finest cell size per graph: ``dx`` when given, else twice the mean
    REST length of the mesh edges of each graph (constant over a trajectory)."""
    n_graphs, dim = context.n_graphs, context.dim
    if dx:
        if len(dx) != dim:
            raise ValueError(f"ms_gnn_grid dx must give one cell size per dimension ({dim}), got {list(dx)}")
        return torch.tensor(dx, dtype=torch.float64, device=context.points.device).expand(n_graphs, dim)
    rest = context.rest_pos.double()
    senders, receivers = mesh_index
    length = (rest.index_select(0, receivers) - rest.index_select(0, senders)).norm(dim=1)
    edge_graph = context.graph.index_select(0, senders)
    total = length.new_zeros(n_graphs).index_add_(0, edge_graph, length)
    count = length.new_zeros(n_graphs).index_add_(0, edge_graph, torch.ones_like(length))
    if not bool((total > 0).all()):
        raise ValueError("ms_gnn_grid with automatic dx needs mesh edges of non-zero length in every graph; "
                         "set model.grid_dx")
    return (2.0 * total / count)[:, None].expand(n_graphs, dim)


def cell_coords(context: Context, size: Tensor) -> Tensor:
    """(N, d) int64 finest-grid cell of each mesh node, from its world position.

    Each graph's grid is anchored at its own minimum corner, moved INSET cells further out,
    so that meshes on a lattice commensurate with the cells (spacing ratios with denominators
    up to 9) put no node on a cell face, where round-off would decide the cell.
    """
    pos, graph = context.pos.double(), context.graph
    index = graph[:, None].expand_as(pos)
    lowest = pos.new_full((context.n_graphs, context.dim), math.inf).scatter_reduce_(0, index, pos, "amin")
    origin = lowest - INSET * size
    return torch.floor((pos - origin.index_select(0, graph)) / size.index_select(0, graph)).long()


def occupied_cells(graph: Tensor, coords: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Occupied cells of points with graph ids (n,) and cell coordinates (n, d) >= 0.

    Returns parent (n,): the cell of each point; cell_graph (m,), cell_coords (m, d); and
    index (2, E): (sender, receiver) pairs of occupied cells of one graph whose coordinates
    differ by at most 1 in every dimension (diagonals included). Cells are sorted by
    (graph, coordinates); scalar keys with one padding coordinate on each side let neighbours
    be found by ``searchsorted`` without leaving their graph.
    """
    dim = coords.shape[1]
    base = [int(top) + 3 for top in coords.amax(dim=0).tolist()]  # padded coordinates c + 1 in [1, top + 1]
    strides = [math.prod(base[j + 1:]) for j in range(dim)]
    per_graph = math.prod(base)
    if (int(graph.max()) + 1) * per_graph >= 2**62:
        raise ValueError("ms_gnn_grid: too many cells to key with int64; choose a larger dx")
    stride = torch.tensor(strides, dtype=torch.long, device=coords.device)
    keys, parent = torch.unique(graph * per_graph + ((coords + 1) * stride).sum(dim=1), return_inverse=True)
    cell_graph, local = keys // per_graph, keys % per_graph
    base_t = torch.tensor(base, dtype=torch.long, device=coords.device)
    cell_coords = (local[:, None] // stride) % base_t - 1
    steps = torch.arange(-1, 2, device=coords.device)
    offsets = torch.stack(torch.meshgrid(*[steps] * dim, indexing="ij"), dim=-1).reshape(-1, dim)
    offsets = offsets[(offsets != 0).any(dim=1)]
    candidates = keys[:, None] + (offsets * stride).sum(dim=1)[None, :]  # (m, 3^d - 1)
    found_at = torch.searchsorted(keys, candidates).clamp(max=len(keys) - 1)
    found = keys[found_at] == candidates
    receivers = torch.arange(len(keys), device=coords.device)[:, None].expand_as(candidates)
    return parent, cell_graph, cell_coords, torch.stack([found_at[found], receivers[found]])


def grid_level(graph: Tensor, coords: Tensor, pos: Tensor, weight: Tensor,
               size: Tensor) -> tuple[Grid, Tensor, Tensor]:
    """One grid from its finer level: points with graph ids (n,), cell coordinates (n, d), mean
    positions (n, d) float64 of ``weight`` (n,) mesh nodes each; ``size`` (n_graphs, d) this
    grid's cell size. Returns the Grid, the cells' positions (m, d) and mesh-node counts (m,)."""
    parent, cell_graph, cell_coords_, index = occupied_cells(graph, coords)
    m = len(cell_graph)
    mass = weight.new_zeros(m).index_add_(0, parent, weight)
    cell_pos = pos.new_zeros(m, pos.shape[1]).index_add_(0, parent, pos * weight[:, None]) / mass[:, None]
    cell_h = size.index_select(0, cell_graph)
    relative = geometry((pos - cell_pos.index_select(0, parent)) / cell_h.index_select(0, parent))
    senders, receivers = index
    offsets = cell_pos.index_select(0, receivers) - cell_pos.index_select(0, senders)
    offsets = offsets / cell_h.index_select(0, receivers)
    count = torch.zeros(m, 1, device=pos.device).index_add_(0, parent, torch.ones(len(parent), 1, device=pos.device))
    grid = Grid(parent, m, count, relative, EdgeSet(index, geometry(offsets)), cell_graph, cell_coords_)
    return grid, cell_pos, mass


@torch.no_grad()
def build_grids(context: Context, mesh_index: Tensor, dx: Sequence[float], inflation: float,
                n_grids: int) -> list[Grid]:
    """The ``n_grids`` grid levels of one frame (finest first) from the world positions in
    ``context``; ``mesh_index`` (2, E): the mesh edges (for the automatic dx).

    Grid k + 1 groups the cells of grid k: a cell with coordinates c belongs to the coarser
    cell floor((c + 1/2) / inflation), the one holding its centre, so the grids nest exactly.
    """
    if n_grids == 0:
        return []
    size = cell_size(context, mesh_index, dx)
    graph, coords = context.graph, cell_coords(context, size)
    pos = context.pos.double()
    weight = torch.ones(len(pos), dtype=torch.float64, device=pos.device)
    grids = []
    for k in range(n_grids):
        if k > 0:
            size = size * inflation
            coords = torch.floor((grids[-1].coords.double() + 0.5) / inflation).long()
            graph = grids[-1].graph
        grid, pos, weight = grid_level(graph, coords, pos, weight, size)
        grids.append(grid)
    return grids


class Aggregation(nn.Module):
    """Finer level -> grid: m_i = f^E([v_i, r_i]) per finer node i (r_i: its offset to its cell),
    averaged per cell; V_c = f^V(mean_i m_i)."""

    def __init__(self, latent: int, hidden: int, hidden_layers: int):
        super().__init__()
        self.edge_mlp = mlp(latent + GEOMETRY, latent, hidden, hidden_layers)
        self.node_mlp = mlp(latent, latent, hidden, hidden_layers)

    def forward(self, v: Tensor, grid: Grid) -> Tensor:
        """v: (n_fine, H) -> (grid.n, H), in the dtype of ``v``."""
        messages = self.edge_mlp(torch.cat([v, grid.relative.to(v.dtype)], dim=-1)).to(v.dtype)
        mean = sum_per_receiver(messages, grid.parent, grid.n) / grid.count.to(v.dtype)
        return self.node_mlp(mean).to(v.dtype)


class Return(nn.Module):
    """Grid -> finer level: v_i <- v_i + f([V_cell(i), v_i, r_i]), v_i the latent the finer level
    had before the transition down (the U-net skip)."""

    def __init__(self, latent: int, hidden: int, hidden_layers: int):
        super().__init__()
        self.mlp = mlp(2 * latent + GEOMETRY, latent, hidden, hidden_layers)

    def forward(self, coarse: Tensor, skip: Tensor, grid: Grid) -> Tensor:
        """coarse: (grid.n, H), skip: (n_fine, H) -> (n_fine, H)."""
        inputs = torch.cat([coarse.index_select(0, grid.parent), skip, grid.relative.to(skip.dtype)], dim=-1)
        return skip + self.mlp(inputs).to(skip.dtype)


class MSGNNGrid(nn.Module):
    """Multi-scale GNN on the mesh and regular grids built from world positions.

    Args:
        node_in: width of the (normalised) node inputs.
        node_out: width of the outputs.
        edge_feature_dims: width of the features of each mesh-level edge set (mesh, contact, ...).
        passes: message passes per level, the mesh first (Table 4.3: [4, 2, 2, 4]); its length
            is the number of levels.
        dx: finest cell size per dimension, in world units; empty: twice the mean rest length
            of the mesh edges of each graph.
        inflation: cell size ratio between consecutive grids (> 1).
    """

    needs_context = True

    def __init__(self, node_in: int, node_out: int, edge_feature_dims: list[int],
                 passes: Sequence[int] = (4, 2, 2, 4), dx: Sequence[float] = (), inflation: float = 2.0,
                 latent: int = 128, hidden: int = 128, hidden_layers: int = 2):
        super().__init__()
        if len(passes) < 1 or min(passes) < 1:
            raise ValueError(f"passes must give one count >= 1 per level, got {list(passes)}")
        if inflation <= 1 or any(size <= 0 for size in dx):
            raise ValueError(f"need inflation > 1 and positive dx, got {inflation} and {list(dx)}")
        self.passes, self.dx, self.inflation = list(passes), tuple(float(s) for s in dx), float(inflation)
        n_sets = len(edge_feature_dims)

        def blocks(level: int, count: int) -> nn.ModuleList:
            if level == 0:
                return nn.ModuleList(EdgeLatentBlock(latent, n_sets, hidden, hidden_layers) for _ in range(count))
            return nn.ModuleList(MessagePassingBlock(latent, [GEOMETRY], hidden, hidden_layers) for _ in range(count))

        top = len(passes) - 1  # transitions (and grids)
        self.encoder = mlp(node_in, latent, hidden, hidden_layers)
        self.edge_encoders = nn.ModuleList(mlp(dim, latent, hidden, hidden_layers) for dim in edge_feature_dims)
        self.down = nn.ModuleList(blocks(l, passes[l]) for l in range(top))
        self.bottom = blocks(top, passes[top])
        self.up = nn.ModuleList(blocks(l, passes[l]) for l in range(top))
        self.aggregations = nn.ModuleList(Aggregation(latent, hidden, hidden_layers) for _ in range(top))
        self.returns = nn.ModuleList(Return(latent, hidden, hidden_layers) for _ in range(top))
        self.decoder = mlp(latent, node_out, hidden, hidden_layers, layer_norm=False)

    @staticmethod
    def _passes(blocks: nn.ModuleList, level: int, v: Tensor, mesh_edges: list[EdgeSet],
                grids: list[Grid]) -> tuple[Tensor, list[EdgeSet]]:
        """The passes of one level: edge-latent blocks on the mesh, plain blocks on a grid."""
        for block in blocks:
            if level == 0:
                v, mesh_edges = block(v, mesh_edges)
            else:
                v = block(v, [grids[level - 1].edges])
        return v, mesh_edges

    def forward(self, node_features: Tensor, levels: list[Level], context: Context | None = None) -> Tensor:
        """node_features: (N, node_in); ``levels[0]`` (the mesh) and ``context`` (positions,
        graph ids) are used -> (N, node_out)."""
        if context is None:
            raise ValueError("ms_gnn_grid builds its grids from positions: it needs a Context")
        mesh = levels[0].edge_sets
        grids = build_grids(context, mesh[0].index, self.dx, self.inflation, len(self.passes) - 1)
        v = self.encoder(node_features).to(node_features.dtype)  # latents: float32 under autocast
        edges = [EdgeSet(index, encode(features).to(features.dtype))
                 for encode, (index, features) in zip(self.edge_encoders, mesh, strict=True)]
        skips = []
        for l, blocks in enumerate(self.down):
            v, edges = self._passes(blocks, l, v, edges, grids)
            skips.append(v)
            v = self.aggregations[l](v, grids[l])
        v, edges = self._passes(self.bottom, len(self.down), v, edges, grids)
        for l in reversed(range(len(self.up))):
            v = self.returns[l](v, skips[l], grids[l])
            v, edges = self._passes(self.up[l], l, v, edges, grids)
        return self.decoder(v)
