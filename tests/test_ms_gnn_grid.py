"""bsms.models.ms_gnn_grid: grid membership from world positions, invariances, batching,
learning, and training through the trainer with exact resume."""

import math

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from torch_geometric.data import Batch

from bsms.data import NodeType
from bsms.graph import bistride_levels, contact_edges
from bsms.level_graph import frame_graph, hierarchy_levels
from bsms.models.inputs import Context
from bsms.models.ms_gnn_grid import MSGNNGrid, build_grids, cell_size
from bsms.models.simulator import LearnedSimulator
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer
from datagen import shapes

# ----------------------------------------------------------------------------- grid membership
# A U-shaped chain of six nodes: the tips 0 and 5 are five hops apart along the chain but close in space.
U_CHAIN = torch.tensor([[0.2, 2.2], [0.2, 1.2], [0.2, 0.2], [1.5, 0.2], [1.5, 1.5], [0.5, 2.4]], dtype=torch.float64)
CHAIN_EDGES = torch.tensor([[0, 1, 2, 3, 4], [1, 2, 3, 4, 5]])


def context(world: torch.Tensor, graph: torch.Tensor | None = None, rest: torch.Tensor | None = None) -> Context:
    graph = torch.zeros(len(world), dtype=torch.long) if graph is None else graph
    rest = world if rest is None else rest
    return Context(torch.cat([rest, world], dim=1).float(), graph, int(graph.max()) + 1, world.shape[1])


def pairs(index: torch.Tensor) -> set:
    return {tuple(p) for p in index.T.tolist()}


def test_cells_join_nodes_close_in_space_but_far_apart_in_the_mesh():
    """dx = 1: the origin is the minimum corner (0.2, 0.2) less 0.3 cells, so cell = floor(x + 0.1)."""
    (fine, middle, coarse) = build_grids(context(U_CHAIN), CHAIN_EDGES, [1.0, 1.0], 2.0, 3)
    assert fine.coords.tolist() == [[0, 0], [0, 1], [0, 2], [1, 0], [1, 1]]  # sorted by (graph, coordinates)
    assert fine.parent.tolist() == [2, 1, 0, 3, 4, 2]  # the tips 0 and 5 share cell (0, 2)
    assert fine.n == 5 and fine.count.flatten().tolist() == [1, 1, 2, 1, 1]
    neighbours = {(0, 1), (0, 3), (0, 4), (1, 2), (1, 3), (1, 4), (2, 4), (3, 4)}  # diagonals included
    assert pairs(fine.edges.index) == neighbours | {(b, a) for a, b in neighbours}
    # the tips' cell sits at their mean (0.35, 2.3); features are offsets over the cell size and their norm
    torch.testing.assert_close(fine.relative[0], torch.tensor([-0.15, -0.1, 0.0, math.hypot(0.15, 0.1)]))
    edge = fine.edges.index.T.tolist().index([2, 4])  # (0, 2) at (0.35, 2.3) -> (1, 1) at (1.5, 1.5)
    torch.testing.assert_close(fine.edges.features[edge], torch.tensor([1.15, -0.8, 0.0, math.hypot(1.15, 0.8)]))
    # twice the cell size: fine cell c belongs to floor((c + 1/2) / 2); only the tips' cell moves up
    assert middle.coords.tolist() == [[0, 0], [0, 1]] and middle.parent.tolist() == [0, 0, 1, 0, 0]
    assert middle.count.flatten().tolist() == [4, 1] and pairs(middle.edges.index) == {(0, 1), (1, 0)}
    # its positions are means over mesh nodes: (0.85, 0.775) and (0.35, 2.3); offsets over its size 2
    torch.testing.assert_close(middle.relative[2], torch.tensor([0.0, 0.0, 0.0, 0.0]))
    torch.testing.assert_close(middle.relative[0], torch.tensor([-0.325, -0.2875, 0.0, math.hypot(0.65, 0.575) / 2]))
    assert coarse.n == 1 and coarse.parent.tolist() == [0, 0] and coarse.edges.index.shape == (2, 0)


def test_graphs_overlapping_in_space_never_share_cells():
    """A batch of the U and a copy moved by (0.05, -0.05) over it: each graph keeps its own grid."""
    world = torch.cat([U_CHAIN, U_CHAIN + torch.tensor([0.05, -0.05], dtype=torch.float64)])
    graph = torch.repeat_interleave(torch.arange(2), 6)
    edges = torch.cat([CHAIN_EDGES, CHAIN_EDGES + 6], dim=1)
    alone = build_grids(context(U_CHAIN), CHAIN_EDGES, [1.0, 1.0], 2.0, 2)
    together = build_grids(context(world, graph), edges, [1.0, 1.0], 2.0, 2)
    for one, both in zip(alone, together, strict=True):
        assert both.n == 2 * one.n
        assert both.parent.tolist() == one.parent.tolist() + (one.parent + one.n).tolist()
        assert both.graph.tolist() == [0] * one.n + [1] * one.n
        assert pairs(both.edges.index) == pairs(one.edges.index) | pairs(one.edges.index + one.n)
        torch.testing.assert_close(both.relative, one.relative.repeat(2, 1), rtol=0, atol=1e-6)


def test_3d_cells_have_26_neighbours_and_automatic_dx_is_twice_the_mean_rest_length():
    lattice = torch.stack(torch.meshgrid(*[torch.arange(3.0)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)
    (grid,) = build_grids(context(lattice.double() * 0.1), CHAIN_EDGES, [0.1] * 3, 2.0, 1)
    assert grid.n == 27 and grid.parent.tolist() == list(range(27))
    assert grid.edges.index.shape == (2, 8 * 7 + 12 * 11 + 6 * 17 + 26)  # corners, edges, faces, centre
    assert int((grid.edges.index[1] == 13).sum()) == 26
    # rest lengths 1, 1, 2 (graph 0) and 3 (graph 1): dx = 8/3 and 6, in every dimension
    rest = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [1.0, 3.0], [0.0, 0.0], [0.0, 3.0]], dtype=torch.float64)
    ctx = context(rest * 7.0, torch.tensor([0, 0, 0, 0, 1, 1]), rest=rest)  # world positions play no part
    size = cell_size(ctx, torch.tensor([[0, 1, 2, 4], [1, 2, 3, 5]]), [])
    torch.testing.assert_close(size, torch.tensor([[8 / 3, 8 / 3], [6.0, 6.0]], dtype=torch.float64))


# ----------------------------------------------------------------------------- the model in the simulator
def frame(mesh, seed: int, shift=(0.0, 0.0), contact_radius: float | None = None):
    """A frame of ``mesh`` moved by ``shift`` and jittered, with random velocities and targets."""
    rng = np.random.default_rng(seed)
    hierarchy = bistride_levels(mesh, mesh.nodes, levels=1)
    pos = mesh.nodes + np.asarray(shift) + 0.01 * rng.normal(size=mesh.nodes.shape)
    node_type = np.where(mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 0.05, NodeType.CLAMPED, NodeType.FREE)
    contacts = None
    if contact_radius is not None:
        half = np.where(mesh.nodes[:, 0] < np.median(mesh.nodes[:, 0]), 0, 1)
        contacts = (contact_edges(pos, half, contact_radius, exclude=mesh.edges, self_contact=False),)
    return frame_graph(hierarchy_levels(hierarchy), rest_pos=mesh.nodes, pos=pos,
                       velocity=rng.normal(size=mesh.nodes.shape), node_type=node_type,
                       target=rng.normal(size=mesh.nodes.shape), contacts=contacts)


def simulator(contact: bool = False, latent: int = 32) -> LearnedSimulator:
    torch.manual_seed(0)
    return LearnedSimulator("ms_gnn_grid", 2, contact=contact, latent=latent,
                            core_options={"passes": [4, 2, 2, 4], "dx": [], "inflation": 2.0})


def warm_up(model, graph):
    """Feed the normalisers once so that they are not the identity."""
    model.loss(graph, accumulate=True)
    return model.eval()


@pytest.fixture(scope="module")
def meshes():
    return shapes.disk(0.5, 0.12), shapes.glyph("B", 0.06)


def test_the_model_uses_four_levels_of_grids_and_translations_change_nothing(meshes, one_thread):
    graph = frame(meshes[1], 0)
    model = warm_up(simulator(), graph)
    assert isinstance(model.core, MSGNNGrid) and model.core.needs_context
    assert [len(b) for b in model.core.down] == [4, 2, 2] and len(model.core.bottom) == 4
    shifted = graph.clone()
    shifted.pos = graph.pos + torch.tensor([0.5, -0.25])
    shifted.rest_pos = graph.rest_pos + torch.tensor([-0.25, 0.5])
    grids = [build_grids(model._context(g, False), g.edge_index_0, [], 2.0, 3) for g in (graph, shifted)]
    assert [g.n for g in grids[0]] == [g.n for g in grids[1]] and grids[0][0].n > 20 and grids[0][2].n > 1
    for a, b in zip(*grids, strict=True):
        assert torch.equal(a.parent, b.parent) and torch.equal(a.edges.index, b.edges.index)
    with torch.no_grad():
        difference = (model(shifted) - model(graph)).abs().max()
    assert difference < 4e-6, f"{difference:.2g}"  # float32 positions moved by O(1) lose ulps; measured 4.5e-7


@pytest.mark.parametrize("overlap", [False, True])
@pytest.mark.parametrize("contact", [False, True])
def test_batch_of_two_meshes_equals_each_alone(meshes, overlap, contact, one_thread):
    """Side by side or on top of each other in space: each graph of a batch gets its own result."""
    radius = 0.1 if contact else None
    graphs = [frame(meshes[0], 1, (0.4, 0.5), radius), frame(meshes[1], 2, (0.0, 0.0) if overlap else (3.0, 0.0), radius)]
    model = warm_up(simulator(contact), graphs[0])
    with torch.no_grad():
        alone = torch.cat([model(g) for g in graphs])
        together = model(Batch.from_data_list(graphs))
    difference = (together - alone).abs().max()
    assert difference < 1e-6, f"{difference:.2g}"  # measured 0 (bit-equal) here; matmuls of other shapes may round


def test_overfits_one_batch(one_thread):
    """28 nodes with random targets, two passes per level: memorised within 100 Adam steps."""
    graph = frame(shapes.disk(0.5, 0.25), 3)
    torch.manual_seed(0)
    model = LearnedSimulator("ms_gnn_grid", 2, latent=32, core_options={"passes": [2, 1, 1, 2]})
    model.loss(graph, accumulate=True)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    with torch.no_grad():
        first = float(model.loss(graph))
    for _ in range(100):
        optimizer.zero_grad()
        model.loss(graph).backward()
        optimizer.step()
    with torch.no_grad():
        final = float(model.loss(graph))
    assert final < first / 1000, f"loss fell from {first:.3g} to {final:.3g} only"  # measured 2.1 -> 5.8e-5


# ----------------------------------------------------------------------------- the trainer
def grid_config(tiny_dataset, runs) -> dict:
    return tiny_run_config(tiny_dataset, runs, model={"name": "ms_gnn_grid", "latent": 16})


def test_trains_through_the_trainer_and_resumes_exactly(tiny_dataset, tmp_path, one_thread):
    folder = prepare_dataset(load_config(grid_config(tiny_dataset, tmp_path / "a")), progress=False)
    whole = Trainer(load_config(grid_config(tiny_dataset, tmp_path / "a")), dataset_folder=folder)
    assert isinstance(whole.model.core, MSGNNGrid)
    whole.fit()
    interrupted = Trainer(load_config(grid_config(tiny_dataset, tmp_path / "b")), dataset_folder=folder)
    interrupted.fit(stop_at=5)  # saves latest.pt at step 5, as a killed run would have
    del interrupted
    resumed = Trainer(load_config(grid_config(tiny_dataset, tmp_path / "b")), dataset_folder=folder, resume=True)
    assert resumed.step == 5
    resumed.fit()
    for (name, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values(), strict=True):
        assert torch.equal(a, b), f"{name} differs after resume"
    rows_a = [r.split(",")[:3] for r in (tmp_path / "a/tiny/metrics.csv").read_text().splitlines()]
    rows_b = [r.split(",")[:3] for r in (tmp_path / "b/tiny/metrics.csv").read_text().splitlines()]
    assert [r[0] for r in rows_a] == [r[0] for r in rows_b] == ["step", "4", "6", "8", "12"]
    assert rows_a[-1][1:] == rows_b[-1][1:], "loss and lr logged after resume equal the uninterrupted run's"
    initial = Trainer(load_config(grid_config(tiny_dataset, tmp_path / "c")), dataset_folder=folder).model
    moved = max(float((whole.model.state_dict()[k] - v).abs().max()) for k, v in initial.state_dict().items()
                if "normalizer" not in k)
    assert moved > 1e-4, "training must have changed the weights for the comparison to mean anything"
