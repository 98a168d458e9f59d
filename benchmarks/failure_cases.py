"""Pieces of the failure suite (benchmarks/failures.py) that its test also uses: steady heat
conduction (its own FE solver), the stick and U-channel layouts, and the two model cores
trained on them with node fields of their own (thesis §4.4.3, Fig. 4.6).

The problems are physics-free for the cores: node inputs are [is_fixed, fixed temperature,
is_flux, flux]; edges carry the world offset receiver - sender and its norm, divided by the
level's typical edge length (the mesh spacing h times 2^level); nothing else tells a node
where it is. The output is the temperature. BSMS-GNN reads the bi-stride levels of the mesh;
MS-GNN-Grid the mesh and regular grids built from the world positions, so a grid cell that
straddles a gap joins two bodies (or the two arms of a U) that share no mesh edge.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import spsolve

from bsms.graph import bistride_levels
from bsms.level_graph import frame_graph, hierarchy_levels
from bsms.models import BSMSGNN, Context, EdgeSet, Level, MSGNNGrid

N_INPUTS = 4  # is_fixed, fixed temperature, is_flux, flux


# ----------------------------------------------------------------------------- the heat solver
def conduction(nodes: np.ndarray, cells: np.ndarray, fixed: dict[int, float],
               flux: dict[int, float] | None = None) -> np.ndarray:
    """Steady conduction (unit conductivity, linear finite elements): div grad T = 0.

    nodes: (N, d) positions; cells: (C, 2) segments (any d) or (C, 3) triangles (d = 2);
    fixed: node -> temperature (Dirichlet); flux: node -> heat leaving the body there (a
    nodal Neumann load; on a 1D stick, -dT/dn at that end). Returns T (N,) float64.
    """
    nodes, cells = np.asarray(nodes, np.float64), np.asarray(cells, np.int64)
    n = len(nodes)
    corners = nodes[cells]  # (C, k, d)
    if cells.shape[1] == 2:
        length = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
        local = np.array([[1.0, -1.0], [-1.0, 1.0]])[None] / length[:, None, None]
    elif cells.shape[1] == 3 and nodes.shape[1] == 2:
        edges = corners[:, 1:] - corners[:, :1]  # (C, 2, 2) rows: x1 - x0, x2 - x0
        area = 0.5 * np.abs(np.linalg.det(edges))
        grad = np.linalg.inv(edges)  # columns: gradients of barycentrics 1 and 2
        grads = np.concatenate([-grad.sum(axis=2, keepdims=True), grad], axis=2).transpose(0, 2, 1)  # (C, 3, 2)
        local = area[:, None, None] * grads @ grads.transpose(0, 2, 1)
    else:
        raise ValueError(f"conduction needs segments or 2D triangles, got cells {cells.shape} in {nodes.shape[1]}D")
    k = cells.shape[1]
    rows, cols = np.repeat(cells, k, axis=1).ravel(), np.tile(cells, (1, k)).ravel()
    stiffness = sp.csr_matrix((local.ravel(), (rows, cols)), shape=(n, n))
    load = np.zeros(n)
    for node, value in (flux or {}).items():
        load[node] -= value
    known = np.array(sorted(fixed), dtype=np.int64)
    if known.size == 0:
        raise ValueError("conduction needs at least one fixed temperature")
    temperature = np.zeros(n)
    temperature[known] = [fixed[int(i)] for i in known]
    free = np.setdiff1d(np.arange(n), known)
    rhs = load[free] - stiffness[free][:, known] @ temperature[known]
    temperature[free] = spsolve(stiffness[free][:, free].tocsc(), rhs)
    return temperature


# ----------------------------------------------------------------------------- layouts
@dataclass
class Case:
    """One conduction instance: nodes (N, 2), cells, mesh edges (2, E) both directions,
    inputs (N, N_INPUTS), target temperature (N,), graph id per node (N,): a core sees nodes
    with different ids as separate graphs (own grids), nodes with one id as one scene."""

    nodes: np.ndarray
    cells: np.ndarray
    edges: np.ndarray
    inputs: np.ndarray
    target: np.ndarray
    graph: np.ndarray


def _both_ways(cells: np.ndarray) -> np.ndarray:
    k = cells.shape[1]
    pairs = np.concatenate([cells[:, [a, b]] for a in range(k) for b in range(a + 1, k)])
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    return np.concatenate([pairs.T, pairs.T[::-1]], axis=1)


def _case(nodes, cells, fixed: dict, flux: dict, graph: int = 0) -> Case:
    inputs = np.zeros((len(nodes), N_INPUTS))
    for node, value in fixed.items():
        inputs[node, :2] = (1.0, value)
    for node, value in flux.items():
        inputs[node, 2:] = (1.0, value)
    return Case(np.asarray(nodes, np.float64), np.asarray(cells, np.int64), _both_ways(np.asarray(cells)),
                inputs, conduction(nodes, cells, fixed, flux), np.full(len(nodes), graph, np.int64))


def stick(n: int, mirrored: bool = False, start: float = 0.0, graph: int = 0) -> Case:
    """A chain of n nodes along x from ``start`` (length 1, spacing 1/(n - 1)); one end at
    temperature 1, the other losing a unit flux (T falls linearly to 0 there). ``mirrored``:
    the fixed end on the right (x = start + 1) instead of the left."""
    nodes = np.stack([start + np.linspace(0.0, 1.0, n), np.zeros(n)], axis=1)
    cells = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    fixed_end, flux_end = (n - 1, 0) if mirrored else (0, n - 1)
    return _case(nodes, cells, {fixed_end: 1.0}, {flux_end: 1.0}, graph)


def joined(cases: list[Case], graphs: list[int] | None = None) -> Case:
    """Cases side by side in one Case (node indices shifted), with the given graph ids."""
    shifts = np.cumsum([0] + [len(c.nodes) for c in cases[:-1]])
    graphs = list(range(len(cases))) if graphs is None else graphs
    return Case(np.concatenate([c.nodes for c in cases]),
                np.concatenate([c.cells + s for c, s in zip(cases, shifts, strict=True)]),
                np.concatenate([c.edges + s for c, s in zip(cases, shifts, strict=True)], axis=1),
                np.concatenate([c.inputs for c in cases]), np.concatenate([c.target for c in cases]),
                np.concatenate([np.full(len(c.nodes), g, np.int64) for c, g in zip(cases, graphs, strict=True)]))


def head_to_tail(n: int, gap: float, mirrored: bool = False) -> Case:
    """Two sticks of one kind in a row along x, the second starting ``gap`` after the first
    ends: no mesh edge joins them, so their temperatures are those of two single sticks."""
    return joined([stick(n, mirrored), stick(n, mirrored, start=1.0 + gap)], graphs=[0, 0])


def stick_grid_dx(n: int, gap: float, grids: int, per_cell: float = 2.0) -> float:
    """A cell size for MS-GNN-Grid on head-to-tail sticks: about ``per_cell`` node spacings,
    such that the second stick's start is a whole number of coarsest cells from the first's
    (each stick alone sits in its cells as in training) and the finest cell holding the first
    stick's last node also holds the second's first node (gap < 0.3 cells, the grid's inset)."""
    h = 1.0 / (n - 1)
    unit = 2 ** (grids - 1)
    count = max(1, round((1.0 + gap) / (per_cell * h * unit)))
    dx = (1.0 + gap) / (count * unit)
    if gap >= 0.3 * dx:
        raise ValueError(f"gap {gap} is not below 0.3 grid cells ({dx:.4g}); choose a smaller gap or more nodes")
    return dx


def u_channel(gap: float, arm: float = 6.0, width: float = 1.0, size: float = 0.25,
              temperatures: tuple[float, float] = (1.0, 0.0), graph: int = 0) -> Case:
    """A U of two arms (``width`` wide, ``arm`` long) ``gap`` apart, joined at the bottom by a
    ``width``-thick bar; the top of the left arm held at temperatures[0], of the right at [1]."""
    from datagen.shapes import polygon

    right = 2 * width + gap
    ring = [(0, 0), (right, 0), (right, arm), (width + gap, arm), (width + gap, width), (width, width),
            (width, arm), (0, arm)]
    mesh = polygon(ring, size=size)
    nodes, top = mesh.nodes, np.isclose(mesh.nodes[:, 1], arm)
    fixed = {int(i): temperatures[0] if nodes[i, 0] < width + gap / 2 else temperatures[1] for i in np.flatnonzero(top)}
    return _case(nodes, mesh.cells, fixed, {}, graph)


# ----------------------------------------------------------------------------- the cores
def _edge_set(pos: torch.Tensor, index: torch.Tensor, scale: float) -> EdgeSet:
    delta = (pos.index_select(0, index[1]) - pos.index_select(0, index[0])) / scale
    return EdgeSet(index, torch.cat([delta, delta.norm(dim=1, keepdim=True)], dim=1).float())


@dataclass
class Prepared:
    """What a core reads for one Case: inputs (N, 4), target (N, 1), levels, context."""

    inputs: torch.Tensor
    target: torch.Tensor
    levels: list[Level]
    context: Context


def prepare(case: Case, kind: str, h: float, n_levels: int) -> Prepared:
    """The inputs of core ``kind`` (``bsms`` or ``grid``) for ``case``; h: the mesh spacing
    (edge features are offsets / (h 2^level))."""
    pos = torch.from_numpy(case.nodes)
    n_graphs = int(case.graph.max()) + 1
    context = Context(torch.cat([pos, pos], dim=1).float(), torch.from_numpy(case.graph), n_graphs, 2)
    inputs = torch.from_numpy(case.inputs).float()
    target = torch.from_numpy(case.target).float()[:, None]
    if kind == "grid":
        return Prepared(inputs, target, [Level([_edge_set(pos, torch.from_numpy(case.edges), h)], None, None)], context)
    hierarchy = bistride_levels(case.edges.T, case.nodes, levels=n_levels)
    frame_levels = hierarchy_levels(hierarchy)
    zeros = np.zeros_like(case.nodes)
    graph = frame_graph(frame_levels, rest_pos=case.nodes, pos=case.nodes, velocity=zeros,
                        node_type=np.zeros(len(case.nodes), np.int64))
    levels = []
    for l, level in enumerate(frame_levels):
        edge_set = _edge_set(pos[torch.from_numpy(level.nodes)], torch.from_numpy(level.edge_index), h * 2**l)
        last = l + 1 == len(frame_levels)
        levels.append(Level([edge_set], None if last else graph.transition("down", l),
                            None if last else graph.transition("up", l), torch.from_numpy(level.nodes)))
    return Prepared(inputs, target, levels, context)


def make_core(kind: str, n_levels: int, dx: float = 0.0, latent: int = 64, seed: int = 0) -> torch.nn.Module:
    """BSMS-GNN with ``n_levels`` bi-stride levels, or MS-GNN-Grid with the mesh and
    n_levels - 1 grids of finest cell ``dx`` (two passes per level), both ``latent`` wide."""
    torch.manual_seed(seed)
    if kind == "bsms":
        return BSMSGNN(N_INPUTS, 1, [3], n_levels, latent=latent, hidden=latent)
    return MSGNNGrid(N_INPUTS, 1, [3], passes=[2] * n_levels, dx=(dx, dx), latent=latent, hidden=latent)


def predict(core: torch.nn.Module, data: Prepared) -> np.ndarray:
    with torch.no_grad():
        return core(data.inputs, data.levels, data.context)[:, 0].double().numpy()


def train(core: torch.nn.Module, batches: list[Prepared], target_loss: float, max_steps: int,
          lr: float = 1e-3) -> dict:
    """Adam on the mean squared temperature error, cycling through ``batches``, until the loss
    over all of them falls to ``target_loss`` (checked every 25 steps) or ``max_steps``;
    the learning rate halves when the loss stalls. Returns {steps, loss, seconds}."""
    optimiser = torch.optim.Adam(core.parameters(), lr=lr)
    best, stall, start, loss = math.inf, 0, time.perf_counter(), math.inf
    for step in range(1, max_steps + 1):
        data = batches[step % len(batches)]
        optimiser.zero_grad()
        context = data.context._replace(accumulate=step <= 50)  # normalisers a core owns (GraphUNets) learn
        error = (core(data.inputs, data.levels, context) - data.target).square().mean()
        error.backward()
        optimiser.step()
        if step % 25 == 0 or step == max_steps:
            loss = float(np.mean([np.mean((predict(core, b) - b.target[:, 0].numpy()) ** 2) for b in batches]))
            if loss <= target_loss:
                break
            stall = 0 if loss < 0.7 * best else stall + 1
            best = min(best, loss)
            if stall >= 8:
                for group in optimiser.param_groups:
                    group["lr"] *= 0.5
                stall = 0
    return {"steps": step, "loss": loss, "seconds": time.perf_counter() - start}


# ----------------------------------------------------------------------------- item 2: pooling
def plate(mesh, graph: int = 0) -> Case:
    """Conduction on a 2D shape: boundary nodes in the leftmost tenth at temperature 1, in the
    rightmost tenth at 0 (the task GraphUNets is briefly trained on)."""
    x = mesh.nodes[:, 0]
    low, high = x.min(), x.max()
    boundary = np.flatnonzero(mesh.boundary_node_mask)
    fixed = {int(i): 1.0 for i in boundary if x[i] <= low + 0.1 * (high - low)}
    fixed.update({int(i): 0.0 for i in boundary if x[i] >= high - 0.1 * (high - low)})
    return _case(mesh.nodes, mesh.cells, fixed, {}, graph)


def make_gunets(n_levels: int, latent: int = 32, seed: int = 0) -> torch.nn.Module:
    from bsms.models import GraphUNets

    torch.manual_seed(seed)
    return GraphUNets(N_INPUTS, 1, [3], n_levels, latent=latent, hidden=latent, max_accumulations=50)


def gunets_levels(core, case: Case, h: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(level-0 node indices, (2, E) edges in each level's numbering) of every level the trained
    GraphUNets ``core`` pools for ``case``, the mesh first."""
    data = prepare(case, "grid", h, 1)
    levels = core.pooled_levels(data.inputs, data.levels, data.context)
    return [level.nodes.numpy() for level in levels], [level.edge_sets[0].index.numpy() for level in levels]


def bistride_of(case: Case, n_levels: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The same for bi-stride pooling (MinAve seeding)."""
    hierarchy = bistride_levels(case.edges.T, case.nodes, levels=n_levels)
    return [hierarchy.finest_indices(l) for l in range(hierarchy.n_levels)], list(hierarchy.edge_indices)
