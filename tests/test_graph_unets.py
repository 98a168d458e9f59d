"""bsms.models.graph_unets: top-k pooling per graph, sparse A + A^2 coarse graphs, invariances,
batching, learning, and exact resume through the trainer."""

import math

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from conftest import tiny_run_config
from graph_meshes import side_by_side
from torch_geometric.data import Batch

from bsms.data import LevelGraph, NodeType
from bsms.graph import bistride_levels, coarsen_contacts, contact_edges
from bsms.level_graph import frame_graph, hierarchy_levels
from bsms.models.graph_unets import GraphUNets, coarse_edges, top_k_per_graph
from bsms.models.simulator import LearnedSimulator
from bsms.run import load_config
from bsms.training.trainer import Trainer
from datagen import shapes

N_LEVELS = 3
RATIO = 0.5


def sample(parts, gap: float, seed: int, contact_radius: float) -> LevelGraph:
    """A frame of the meshes ``parts`` side by side (one body each), slightly moved, with random
    velocities and targets, clamped nodes on the left and contact edges between the bodies."""
    mesh = side_by_side(parts, gap)
    body_id = np.repeat(np.arange(len(parts)), [part.n_nodes for part in parts])
    rng = np.random.default_rng(seed)
    hierarchy = bistride_levels(mesh, mesh.nodes, levels=1)
    pos = mesh.nodes + 0.01 * rng.normal(size=mesh.nodes.shape)
    node_type = np.where(mesh.boundary_node_mask & (mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 0.05),
                         NodeType.CLAMPED, NodeType.FREE)
    contacts = coarsen_contacts(hierarchy, contact_edges(pos, body_id, contact_radius, exclude=mesh.edges,
                                                         self_contact=False))
    return frame_graph(hierarchy_levels(hierarchy), rest_pos=mesh.nodes, pos=pos,
                       velocity=rng.normal(size=mesh.nodes.shape), node_type=node_type,
                       target=rng.normal(size=mesh.nodes.shape), contacts=contacts)


@pytest.fixture(scope="module")
def graphs():
    """Two frames of different meshes, each of two bodies in contact."""
    disks = sample([shapes.disk(0.5, 0.12), shapes.disk(0.4, 0.12)], 0.05, 0, contact_radius=0.15)
    letter = sample([shapes.glyph("B", 0.06), shapes.rectangle(0.4, 0.8, 0.1)], 0.03, 1, contact_radius=0.12)
    return [disks, letter]


def simulator(contact: bool = True, latent: int = 32) -> LearnedSimulator:
    torch.manual_seed(0)
    return LearnedSimulator("graph_unets", 2, n_levels=N_LEVELS, contact=contact, latent=latent,
                            core_options={"ratio": RATIO})


def warm_up(model: LearnedSimulator, graph) -> LearnedSimulator:
    """Feed every normaliser (the core's coarse-edge ones too) once, so none is the identity."""
    model.loss(graph, accumulate=True)
    return model.eval()


def core_levels(model: LearnedSimulator, graph):
    """The levels the core pools from ``graph`` (a single graph or a batch)."""
    inputs = model.node_normalizer(model.node_features(graph))
    return model.core.pooled_levels(inputs, [model._level(graph, 0, False)], model._context(graph, False))


def test_pools_the_configured_fraction_of_every_graph(graphs):
    model = warm_up(simulator(), graphs[0])
    batch = Batch.from_data_list(graphs)
    levels = core_levels(model, batch)
    assert len(levels) == N_LEVELS
    sizes = np.array([g.num_nodes for g in graphs])
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    for l, level in enumerate(levels):
        per_graph = np.histogram(level.nodes.numpy(), bounds)[0]
        np.testing.assert_array_equal(per_graph, sizes, err_msg=f"level {l}")
        assert torch.equal(level.nodes, torch.sort(level.nodes).values)
        sizes = np.array([math.ceil(RATIO * n) for n in sizes])
    assert len(levels[-1].nodes) < len(levels[0].nodes) / 3


def test_top_k_per_graph_breaks_ties_by_index():
    score = torch.tensor([0.0, 3.0, 1.0, 1.0, 5.0, 2.0, 2.0, -1.0])
    graph = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1])
    # graph 0 keeps ceil(0.6 * 4) = 3: 1 (3.0) then 2, 3 (1.0); graph 1 keeps 4 (5.0), 5 and 6 (2.0)
    assert top_k_per_graph(score, graph, 2, 0.6).tolist() == [1, 2, 3, 4, 5, 6]
    # ceil(0.3 * 4) = 2 per graph; an empty third graph keeps nothing
    assert top_k_per_graph(score, graph, 3, 0.3).tolist() == [1, 2, 4, 5]
    assert top_k_per_graph(torch.arange(10.0), torch.zeros(10, dtype=torch.long), 1, 0.3).tolist() == [7, 8, 9]


def edge_set(index: torch.Tensor) -> set:
    return set(map(tuple, index.T.tolist()))


def matrix(index: torch.Tensor, n: int) -> sp.csr_matrix:
    return sp.csr_matrix((np.ones(index.shape[1]), index.numpy()), shape=(n, n))


def pattern(m: sp.spmatrix) -> set:
    m = sp.coo_matrix(m)
    return {(int(a), int(b)) for a, b, value in zip(m.row, m.col, m.data, strict=True) if a != b and value != 0}


def test_coarse_edges_are_the_squared_graph_on_the_kept_nodes(graphs):
    """Every level's mesh edges equal the pattern of A + A^2 of the level above restricted to the
    kept nodes (scipy, off the diagonal), its contacts R^T C R with R = (A + I)[:, kept]; the
    coarse mesh features are the offsets and norms of the kept nodes' own positions."""
    model = warm_up(simulator(), graphs[1])
    graph = graphs[1]
    levels = core_levels(model, graph)
    squared_only = 0
    for l, (fine, coarse) in enumerate(zip(levels[:-1], levels[1:], strict=True)):
        n = len(fine.nodes)
        kept = np.searchsorted(fine.nodes.numpy(), coarse.nodes.numpy())
        assert np.array_equal(fine.nodes.numpy()[kept], coarse.nodes.numpy())
        a = matrix(fine.edge_sets[0].index, n)
        assert edge_set(coarse.edge_sets[0].index) == pattern((a + a @ a)[kept][:, kept])
        reach = (a + sp.identity(n)).tocsr()[:, kept]
        contacts = reach.T @ matrix(fine.edge_sets[1].index, n) @ reach
        assert edge_set(coarse.edge_sets[1].index) == pattern(contacts) != set()
        squared_only += len(pattern((a + a @ a)[kept][:, kept]) - pattern(a[kept][:, kept]))
        senders, receivers = coarse.nodes[coarse.edge_sets[0].index]
        expected = torch.cat([torch.cat([x, x.norm(dim=-1, keepdim=True)], dim=-1) for x in (
            graph.rest_pos[receivers] - graph.rest_pos[senders], graph.pos[receivers] - graph.pos[senders])], dim=-1)
        raw = model.core.edge_normalizers[l][0].inverse(coarse.edge_sets[0].features)
        torch.testing.assert_close(raw, expected, rtol=0, atol=2e-6)
    assert squared_only > 0, "some coarse edges come only from A^2"


def test_coarse_edges_on_a_path():
    """0-1-2-3-4-5-6 keeping 0, 2, 3, 6: 0-2 and 2-3 (one apart or adjacent); 3 and 6 are three
    apart and stay unjoined; a contact 1-5 joins 0 and 2 (both reach 1) with 6 (reaches 5)."""
    path = torch.tensor([[0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6], [1, 0, 2, 1, 3, 2, 4, 3, 5, 4, 6, 5]])
    mesh, contact = coarse_edges(path, torch.tensor([0, 2, 3, 6]), 7, [torch.tensor([[1, 5], [5, 1]])])
    assert edge_set(mesh) == {(0, 1), (1, 0), (1, 2), (2, 1)}
    assert edge_set(contact) == {(0, 3), (3, 0), (1, 3), (3, 1)}
    keys = mesh[0] * 4 + mesh[1]
    assert (keys[1:] > keys[:-1]).all(), "sorted by (sender, receiver)"


def test_translation_invariance(graphs):
    graph = graphs[1]
    model = warm_up(simulator(), graph)
    shifted = graph.clone()
    shifted.pos = graph.pos + torch.tensor([3.0, -2.0])
    shifted.rest_pos = graph.rest_pos + torch.tensor([-1.0, 5.0])
    with torch.no_grad():
        kept = [[level.nodes for level in core_levels(model, g)] for g in (graph, shifted)]
        assert all(torch.equal(a, b) for a, b in zip(*kept, strict=True)), "the same nodes are kept"
        # measured max difference 5.7e-7 (outputs of order 0.5): shifted float32 positions lose ulps in the offsets
        torch.testing.assert_close(model(shifted), model(graph), rtol=0, atol=5e-6)


def test_batch_of_two_meshes_equals_each_alone(graphs):
    model = warm_up(simulator(), graphs[0])
    with torch.no_grad():
        alone = torch.cat([model(g) for g in graphs])
        together = model(Batch.from_data_list(graphs))
    # measured max difference 1.8e-7: float32 matmuls of other shapes
    torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)


def test_gate_trains_the_projections(graphs):
    model = simulator()
    model.loss(graphs[0], accumulate=True).backward()
    grad = model.core.projections.grad
    assert grad is not None and grad.shape == (N_LEVELS - 1, 32) and (grad.norm(dim=1) > 0).all()


def test_overfits_one_graph(graphs, one_thread):
    graph = graphs[0]
    model = simulator(latent=32)
    model.loss(graph, accumulate=True)
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    losses = []
    for _ in range(150):
        optimizer.zero_grad()
        loss = model.loss(graph)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    with torch.no_grad():
        final = float(model.loss(graph))
    # measured final/first: 0.022 (random targets, so the network memorises them per node)
    assert final < 0.1 * losses[0], f"one-step loss fell from {losses[0]:.3g} to {final:.3g} only"


def test_cores_reject_bad_options():
    with pytest.raises(ValueError, match="ratio"):
        GraphUNets(4, 2, [6], 3, ratio=1.0)
    with pytest.raises(ValueError, match="n_levels"):
        GraphUNets(4, 2, [6], 0)
    core = GraphUNets(4, 2, [6], 2, latent=8, hidden=8)
    with pytest.raises(ValueError, match="Context"):
        core(torch.zeros(3, 4), [], None)


@pytest.fixture(scope="module")
def folder(tiny_folder):
    return tiny_folder


def test_trainer_resumes_exactly(tiny_dataset, folder, tmp_path, one_thread):
    def trainer(runs, resume=False):
        config = tiny_run_config(tiny_dataset, runs, model={"name": "graph_unets", "latent": 16},
                                 train={"steps": 8, "log_every": 2, "valid_every": 8, "checkpoint_every": 4,
                                        "normalizer_steps": 3, "valid_samples": 2})
        return Trainer(load_config(config), dataset_folder=folder, resume=resume)

    whole = trainer(tmp_path / "a")
    assert isinstance(whole.model.core, GraphUNets) and whole.model.contact
    whole.fit()
    interrupted = trainer(tmp_path / "b")
    interrupted.fit(stop_at=4)  # at a log boundary: every logged mean covers the same steps
    del interrupted
    resumed = trainer(tmp_path / "b", resume=True)
    assert resumed.step == 4
    resumed.fit()
    assert any("core.edge_normalizers" in name for name in whole.model.state_dict())
    for (name, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values(), strict=True):
        assert torch.equal(a, b), f"{name} differs after resume"
    rows_a = (tmp_path / "a/tiny/metrics.csv").read_text().splitlines()
    rows_b = (tmp_path / "b/tiny/metrics.csv").read_text().splitlines()
    assert [r.split(",")[:3] for r in rows_a] == [r.split(",")[:3] for r in rows_b]
