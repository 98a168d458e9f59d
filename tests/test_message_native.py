"""The compiled message sums and edge inputs (bsms/models/native.py) against the torch code they replace."""

from __future__ import annotations

import pytest
import torch
from test_precision import floor_scenario, state
from torch import nn

from bsms.models import BSMSGNN, EdgeSet, Level, MessagePassingBlock, blocks, native
from bsms.models.blocks import edge_first_layer, sum_per_receiver
from bsms.models.normalize import Normalizer
from bsms.models.simulator import LearnedSimulator, _offsets


@pytest.fixture(autouse=True)
def compiled():
    """Every test here needs the compiled loop; CI machines have a C compiler."""
    native.library.cache_clear()
    assert native.library() is not None, "no C compiler: the compiled message sums cannot be built"
    yield
    native.library.cache_clear()


def torch_sums(linear: nn.Linear, features, v, index):
    """What the compiled loop replaces: relu(first layer) per edge, summed per receiver."""
    return sum_per_receiver(torch.relu(edge_first_layer(linear, features, v, index)), index[1], v.shape[0])


def random_edges(n_nodes: int, n_edges: int, generator) -> torch.Tensor:
    """(2, E) with repeated edges, self-loops and (for the last quarter of the nodes) no edges at all."""
    return torch.randint(0, 3 * n_nodes // 4, (2, n_edges), generator=generator)


@pytest.mark.parametrize("hidden", [32, 64, 128, 48])  # the three unrolled widths and the generic loop
@pytest.mark.parametrize("n_features", [3, 4, 6, 8, 5])  # the four unrolled feature counts and the generic loop
def test_compiled_sums_equal_the_torch_pass(hidden, n_features):
    g = torch.Generator().manual_seed(hidden + n_features)
    n_nodes = 200
    linear = nn.Linear(n_features + 2 * hidden, hidden)
    v = torch.randn(n_nodes, hidden, generator=g)
    features = torch.randn(900, n_features, generator=g)
    index = random_edges(n_nodes, 900, g)
    f, h = n_features, hidden
    with torch.no_grad():
        products = torch.addmm(torch.cat([linear.bias, torch.zeros(h)]), v,
                               torch.cat([linear.weight[:, f: f + h], linear.weight[:, f + h:]]).T)
        ours = native.edge_sums(products, features, linear.weight[:, :f], index)
        reference = torch_sums(linear, features, v, index)
    assert torch.equal(ours[3 * n_nodes // 4:], torch.zeros(n_nodes // 4, hidden))
    # the same sums in the same edge order; each term a float32 sum of 2 + F products in another order
    torch.testing.assert_close(ours, reference, rtol=0, atol=2e-6 * float(reference.abs().max()))


def test_sums_read_products_in_place_and_count_each_receivers_edges():
    """Products given as columns of a wider product (a strided view) give the sums of the same
    products made contiguous, bit for bit; ``counts`` appends each receiver's edge count."""
    g = torch.Generator().manual_seed(3)
    wide = torch.randn(60, 5 * 32, generator=g)
    features, weight = torch.randn(300, 6, generator=g), torch.randn(32, 6, generator=g)
    index = random_edges(60, 300, g)
    view = wide[:, 64:128]
    assert view.stride() == (160, 1)
    plain = native.edge_sums(view.contiguous(), features, weight, index)
    counted = native.edge_sums(view, features, weight, index, counts=True)
    assert counted.shape == (60, 33)
    assert torch.equal(counted[:, :32], plain)
    assert torch.equal(counted[:, 32], torch.bincount(index[1], minlength=60).float())


def test_a_lean_block_at_inference_is_fused_and_equals_its_general_path(monkeypatch):
    """fused_pass (one product for every node part, edge counts from the compiled loop, each edge
    MLP's last layer folded into the node MLP's first) gives the block's general output to float32
    round-off: with an edge set that has no edges, and one with fewer edges than nodes."""
    g = torch.Generator().manual_seed(11)
    torch.manual_seed(11)
    block = MessagePassingBlock(32, [6, 3, 2], 32, 1, layer_norm=False)
    v = torch.randn(90, 32, generator=g)
    edge_sets = [EdgeSet(random_edges(90, 500, g), torch.randn(500, 6, generator=g)),
                 EdgeSet(torch.zeros(2, 0, dtype=torch.long), torch.zeros(0, 3)),
                 EdgeSet(random_edges(90, 20, g), torch.randn(20, 2, generator=g))]
    with torch.no_grad():
        fused = blocks.fused_pass(block, v, edge_sets)
        assert fused is not None
        monkeypatch.setattr(blocks, "fused_pass", lambda *args: None)
        general = block(v, edge_sets)
    training = block(v, edge_sets)  # with gradients: the torch path throughout
    for reference in (general, training.detach()):
        torch.testing.assert_close(fused, reference, rtol=0, atol=2e-6 * float(reference.abs().max()))
    assert float((fused - v).abs().max()) > 0.1  # the block changes its input
    with torch.no_grad():
        assert blocks.fused_pass(block, v.double(), edge_sets) is None
        assert blocks.fused_pass(MessagePassingBlock(32, [6], 32, 1, layer_norm=True), v, edge_sets[:1]) is None


def test_an_index_out_of_range_raises_and_other_dtypes_take_the_torch_path():
    products, features, weight = torch.zeros(5, 64), torch.zeros(3, 2), torch.zeros(32, 2)
    with pytest.raises(IndexError, match=r"^edge_sums: node index 5 out of range for 5 nodes$"):
        native.edge_sums(products, features, weight, torch.tensor([[0, 1, 2], [4, 5, 0]]))
    with pytest.raises(IndexError, match=r"^edge_sums: node index -1 out of range for 5 nodes$"):
        native.edge_sums(products, features, weight, torch.tensor([[0, -1, 2], [4, 1, 0]]))
    index = torch.tensor([[0, 1, 2], [4, 3, 0]])
    assert native.edge_sums(products.double(), features.double(), weight.double(), index) is None
    assert native.edge_sums(products.bfloat16(), features, weight, index) is None
    assert native.edge_sums(products, features, weight, index.int()) is None
    assert torch.equal(native.edge_sums(products, features, weight, index), torch.zeros(5, 32))


def lean_levels(generator) -> tuple[BSMSGNN, list[Level], torch.Tensor]:
    torch.manual_seed(4)
    model = BSMSGNN(5, 2, [3, 2], n_levels=1, latent=32, hidden=32, hidden_layers=1, layer_norm=False)
    edge_sets = [EdgeSet(random_edges(80, 400, generator), torch.randn(400, 3, generator=generator)),
                 EdgeSet(random_edges(80, 30, generator), torch.randn(30, 2, generator=generator))]
    return model, [Level(edge_sets, None, None)], torch.randn(80, 5, generator=generator)


def test_inference_sums_messages_in_the_compiled_loop_and_training_in_torch(monkeypatch):
    """A lean block (one hidden layer, no LayerNorm) at inference: every edge set through the
    compiled loop, the output that of the torch path to float32 round-off; with gradients, or
    with LayerNorm, or two hidden layers, the compiled loop is never called."""
    model, levels, x = lean_levels(torch.Generator().manual_seed(7))
    calls = []
    edge_sums = native.edge_sums
    monkeypatch.setattr(native, "edge_sums",
                        lambda *args, **kwargs: calls.append(args[3].shape[1]) or edge_sums(*args, **kwargs))
    with torch.no_grad():
        compiled_out = model(x, levels)
    assert calls == [400, 30], calls
    with monkeypatch.context() as patch:
        patch.setattr(blocks, "_compiled_sums", lambda *args: None)
        patch.setattr(blocks, "fused_pass", lambda *args: None)
        with torch.no_grad():
            torch_out = model(x, levels)
    torch.testing.assert_close(compiled_out, torch_out, rtol=0, atol=2e-6 * float(torch_out.abs().max()))
    calls.clear()
    model(x, levels).sum().backward()  # training: gradients through the torch path
    with torch.no_grad():
        for block in (MessagePassingBlock(32, [3, 2], 32, 1, layer_norm=True),
                      MessagePassingBlock(32, [3, 2], 32, 2, layer_norm=False)):
            block(torch.randn(80, 32), levels[0].edge_sets)
    assert calls == [], calls


def test_without_a_compiler_the_torch_path_gives_the_same_output(monkeypatch, tmp_path):
    model, levels, x = lean_levels(torch.Generator().manual_seed(8))
    with torch.no_grad():
        expected = model(x, levels)
    native.library.cache_clear()
    monkeypatch.setenv("BSMS_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "false")
    with pytest.warns(RuntimeWarning, match=r"could not build the compiled message sums \(false failed"):
        assert native.library() is None
    with torch.no_grad():
        fallback = model(x, levels)
    torch.testing.assert_close(fallback, expected, rtol=0, atol=2e-6 * float(expected.abs().max()))
    assert not list(tmp_path.rglob("*.so"))


@pytest.mark.parametrize("dim, groups", [(2, 2), (3, 2), (2, 1), (1, 3)])
def test_compiled_edge_offsets_equal_the_torch_inputs(dim, groups):
    """Offsets and lengths per group of points, normalised: the torch path's values to float32 round-off."""
    g = torch.Generator().manual_seed(10 * dim + groups)
    points = torch.randn(120, groups * dim, generator=g)
    index = random_edges(120, 700, g)
    normalizer = Normalizer(groups * (dim + 1))
    normalizer.accumulate(3.0 * torch.randn(50, groups * (dim + 1), generator=g) + 1.0)
    ours = native.edge_offsets(points, index, dim, normalizer.mean, normalizer.std)
    reference = normalizer(_offsets(points, index, dim))
    assert ours.shape == reference.shape == (700, groups * (dim + 1))
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-6 * float(reference.abs().max()))
    with pytest.raises(IndexError, match=r"^edge_offsets: node index 120 out of range for 120 nodes$"):
        native.edge_offsets(points, torch.tensor([[0], [120]]), dim, normalizer.mean, normalizer.std)
    assert native.edge_offsets(points.double(), index, dim, normalizer.mean, normalizer.std) is None


@pytest.mark.parametrize("dim, groups", [(2, 2), (3, 2), (2, 1), (2, 3)])
def test_reflected_edge_offsets_are_those_of_the_reflected_points(dim, groups):
    """``reflect``: each edge's inputs, then the inputs the mirror image (x -> -x) gives, bit for
    bit; the torch path of LearnedSimulator._edge_inputs gives the same to round-off."""
    g = torch.Generator().manual_seed(20 * dim + groups)
    points = torch.randn(90, groups * dim, generator=g)
    index = random_edges(90, 400, g)
    normalizer = Normalizer(groups * (dim + 1))
    normalizer.accumulate(2.0 * torch.randn(40, groups * (dim + 1), generator=g) + 0.5)
    flip = torch.ones(groups * dim)
    flip[::dim] = -1.0
    both = native.edge_offsets(points, index, dim, normalizer.mean, normalizer.std, reflect=True)
    columns = groups * (dim + 1)
    assert both.shape == (400, 2 * columns)
    assert torch.equal(both[:, :columns], native.edge_offsets(points, index, dim, normalizer.mean, normalizer.std))
    assert torch.equal(both[:, columns:],
                       native.edge_offsets(points * flip, index, dim, normalizer.mean, normalizer.std))
    assert not torch.equal(both[:, :columns], both[:, columns:])
    model = LearnedSimulator("bsms_gnn", dim, n_levels=1)
    torch_path = model._edge_inputs(normalizer, points, index, accumulate=False, reflect=True)  # with gradients: torch
    torch.testing.assert_close(torch_path, both, rtol=0, atol=1e-6 * float(both.abs().max()))


def test_a_models_inputs_come_from_the_compiled_pass_at_inference_only(monkeypatch):
    """LearnedSimulator._level at inference: mesh and contact inputs through edge_offsets, the
    outputs those of the torch path; while the normalisers accumulate (training), never."""
    scenario = floor_scenario()
    torch.manual_seed(0)
    model = LearnedSimulator("bsms_gnn", 2, n_levels=3, contact=True, latent=32, hidden_layers=1,
                             core_options={"layer_norm": False})
    graphs = [scenario.graph(*state(scenario, seed), target=0.01 * state(scenario, seed)[1]) for seed in range(3)]
    calls = []
    edge_offsets = native.edge_offsets
    monkeypatch.setattr(native, "edge_offsets", lambda *args: calls.append(args[1].shape[1]) or edge_offsets(*args))
    for graph in graphs:
        model.loss(graph, accumulate=True)
    assert calls == []
    model.eval()
    with torch.no_grad():
        compiled = model(graphs[2])
        assert len(calls) == 2 * 3 and 0 not in calls[::2], calls  # mesh and contact edges on every level
        with monkeypatch.context() as patch:
            patch.setattr(native, "edge_offsets", lambda *args: None)
            reference = model(graphs[2])
    torch.testing.assert_close(compiled, reference, rtol=0, atol=1e-5 * float(reference.abs().max()))
