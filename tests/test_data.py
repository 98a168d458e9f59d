"""bsms.data and the LearnedSimulator: batching of different meshes, invariances."""

import numpy as np
import pytest
import torch
from graph_meshes import side_by_side
from torch_geometric.data import Batch

from bsms.data import LevelGraph, NodeType
from bsms.graph import bistride_levels, coarsen_contacts, contact_edges
from bsms.level_graph import frame_graph, hierarchy_levels
from bsms.models.simulator import LearnedSimulator
from datagen import shapes

N_LEVELS = 3


def two_bodies(first, second, gap: float):
    """(mesh, body_id) of two meshes side by side, ``gap`` apart along x."""
    mesh = side_by_side([first, second], gap)
    return mesh, np.repeat([0, 1], [first.n_nodes, second.n_nodes])


def sample(mesh, body_id, seed: int, contact_radius: float) -> LevelGraph:
    """A frame of ``mesh`` slightly moved, with clamped nodes on its left and contact edges
    between its bodies on every level."""
    rng = np.random.default_rng(seed)
    hierarchy = bistride_levels(mesh, mesh.nodes, levels=N_LEVELS, seeding="close_center")
    pos = mesh.nodes + 0.01 * rng.normal(size=mesh.nodes.shape)
    node_type = np.where(mesh.boundary_node_mask & (mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 0.05),
                         NodeType.CLAMPED, NodeType.FREE)
    contacts = coarsen_contacts(hierarchy, contact_edges(pos, body_id, contact_radius, exclude=mesh.edges,
                                                         self_contact=False))
    return frame_graph(
        hierarchy_levels(hierarchy), rest_pos=mesh.nodes, pos=pos,
        velocity=rng.normal(size=mesh.nodes.shape), node_type=node_type,
        target=rng.normal(size=mesh.nodes.shape), contacts=contacts,
    )


@pytest.fixture(scope="module")
def graphs():
    """Two frames of different meshes, each of two bodies in contact."""
    disks = two_bodies(shapes.disk(0.5, 0.15), shapes.disk(0.4, 0.15), gap=0.05)
    letter = two_bodies(shapes.glyph("B", 0.06), shapes.rectangle(0.4, 0.8, 0.1), gap=0.03)
    return [sample(*disks, 0, contact_radius=0.2), sample(*letter, 1, contact_radius=0.12)]


def test_both_graphs_carry_contacts_on_every_level(graphs):
    a, b = graphs
    assert a.num_nodes != b.num_nodes
    for graph in graphs:
        for l in range(N_LEVELS):
            assert graph[f"contact_index_{l}"].shape[1] >= 4, f"level {l} must have contacts to batch"


def models(contact: bool = False):
    torch.manual_seed(0)
    return [
        LearnedSimulator("bsms_gnn", 2, n_levels=N_LEVELS, contact=contact, latent=32),
        LearnedSimulator("meshgraphnets", 2, contact=contact, latent=32, n_passes=3),
    ]


def warm_up(model, graph):
    """Feed the normalisers once so that they are not the identity."""
    model.loss(graph, accumulate=True)
    return model.eval()


def test_batch_offsets_every_level(graphs):
    batch = Batch.from_data_list(graphs)
    a, b = graphs
    for l in range(N_LEVELS):
        n_a = a[f"n_nodes_{l}"]
        assert batch.level_size(l) == n_a + b[f"n_nodes_{l}"]
        for key in (f"edge_index_{l}", f"contact_index_{l}"):
            split = a[key].shape[1]
            torch.testing.assert_close(batch[key], torch.cat([a[key], b[key] + n_a], dim=1), rtol=0, atol=0)
            assert split > 0 and b[key].shape[1] > 0
        torch.testing.assert_close(batch[f"nodes_{l}"][n_a:], b[f"nodes_{l}"] + a.num_nodes)
    for l in range(N_LEVELS - 1):
        for kind in ("down", "up"):
            ta, tb, together = a.transition(kind, l), b.transition(kind, l), batch.transition(kind, l)
            assert together.shape == (ta.shape[0] + tb.shape[0], ta.shape[1] + tb.shape[1])
            torch.testing.assert_close(together.rows, torch.cat([ta.rows, tb.rows + ta.shape[0]]))
            torch.testing.assert_close(together.cols, torch.cat([ta.cols, tb.cols + ta.shape[1]]))
            torch.testing.assert_close(together.weights, torch.cat([ta.weights, tb.weights]), rtol=0, atol=0)


@pytest.mark.parametrize("contact", [False, True])
@pytest.mark.parametrize("index", [0, 1])
def test_batch_of_two_meshes_equals_each_alone(graphs, index, contact):
    model = warm_up(models(contact)[index], graphs[0])
    with torch.no_grad():
        alone = torch.cat([model(g) for g in graphs])
        together = model(Batch.from_data_list(graphs))
    torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)  # float32 matmuls of other shapes


@pytest.mark.parametrize("index", [0, 1])
def test_translation_invariance(graphs, index):
    graph = graphs[1]
    model = warm_up(models()[index], graph)
    shifted = graph.clone()
    shifted.pos = graph.pos + torch.tensor([3.0, -2.0])
    shifted.rest_pos = graph.rest_pos + torch.tensor([-1.0, 5.0])
    with torch.no_grad():
        # float32 positions shifted by O(1) lose a few ulps in the offsets
        torch.testing.assert_close(model(shifted), model(graph), rtol=0, atol=2e-6)


def test_loss_only_counts_free_nodes(graphs):
    graph = graphs[0].clone()
    model = warm_up(models()[0], graph)
    clamped = graph.node_type != NodeType.FREE
    assert clamped.any()
    changed = graph.clone()
    changed.target = graph.target.clone()
    changed.target[clamped] += 100.0
    with torch.no_grad():
        assert model.loss(changed) == model.loss(graph)
        assert (model.velocity_change(graph)[clamped] == 0).all()


def test_bad_inputs():
    with pytest.raises(ValueError, match="unknown model 'gcn'; choose one of bsms_gnn, meshgraphnets, ms_gnn_grid, graph_unets"):
        LearnedSimulator("gcn", 2)
    mesh = shapes.disk(1.0, 0.3)
    levels = hierarchy_levels(bistride_levels(mesh, mesh.nodes, levels=2))
    with pytest.raises(ValueError, match="must all be \\(N, d\\) with N = "):
        frame_graph(levels, rest_pos=mesh.nodes, pos=mesh.nodes[:-1], velocity=mesh.nodes,
                    node_type=np.zeros(mesh.n_nodes, dtype=int))
    graph = frame_graph(levels, rest_pos=mesh.nodes, pos=mesh.nodes, velocity=mesh.nodes,
                        node_type=np.zeros(mesh.n_nodes, dtype=int))
    with pytest.raises(ValueError, match="the graph has 2 levels but the model needs 3"):
        LearnedSimulator("bsms_gnn", 2, n_levels=3)(graph)


@pytest.mark.parametrize("dim", [2, 3])
def test_obstacle_facets_are_subdivided_without_changing_the_geometry(dim):
    from bsms.graph.obstacles import subdivide_facets
    from datagen.scenes.base import outline

    domain = shapes.rectangle(1.0, 0.6, 0.3) if dim == 2 else shapes.box((1.0, 0.6, 0.8), 0.5)
    nodes, facets = outline(domain)
    fine_nodes, fine_facets = subdivide_facets(nodes, facets, 0.1)

    def measure(n, f):
        if dim == 2:
            return np.linalg.norm(n[f[:, 1]] - n[f[:, 0]], axis=1)
        return 0.5 * np.linalg.norm(np.cross(n[f[:, 1]] - n[f[:, 0]], n[f[:, 2]] - n[f[:, 0]]), axis=1)

    assert measure(fine_nodes, fine_facets).sum() == pytest.approx(measure(nodes, facets).sum(), rel=2e-15)
    edges = [fine_facets[:, [a, (a + 1) % dim]] for a in range(dim)] if dim == 3 else [fine_facets]
    lengths = np.concatenate([np.linalg.norm(fine_nodes[e[:, 0]] - fine_nodes[e[:, 1]], axis=1) for e in edges])
    assert lengths.max() <= 0.1 + 1e-12 and lengths.min() > 0
    assert len(np.unique(np.round(fine_nodes, 9), axis=0)) == len(fine_nodes), "shared points are merged"
    for corner in nodes:  # the original corners are kept
        assert np.isclose(np.linalg.norm(fine_nodes - corner, axis=1).min(), 0.0)
