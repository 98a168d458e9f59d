"""bsms.models and bsms.models.normalize: the physics-free core networks and the feature normaliser."""

import numpy as np
import pytest
import torch
from torch import nn

from bsms.graph import Transition
from bsms.models import (
    BSMSGNN,
    EdgeLatentBlock,
    EdgeSet,
    Level,
    MeshGraphNets,
    MessagePassingBlock,
    apply_transition,
    mlp,
)
from bsms.models.normalize import Normalizer

EDGE_DIMS = [3, 2]  # a mesh edge set and a contact edge set


def random_levels(sizes: list[int], generator: torch.Generator) -> list[Level]:
    """A synthetic multi-level graph: random edges per level, random averaging maps between levels."""
    levels = []
    for l, n in enumerate(sizes):
        edge_sets = []
        for dim, count in zip(EDGE_DIMS, (3 * n, n // 2), strict=True):
            index = torch.randint(0, n, (2, count), generator=generator)
            edge_sets.append(EdgeSet(index, torch.randn(count, dim, generator=generator)))
        down = up = None
        if l + 1 < len(sizes):
            n_coarse = sizes[l + 1]
            fine = torch.cat([torch.arange(n), torch.randint(0, n, (3 * n_coarse,), generator=generator)])
            coarse = torch.cat([torch.randint(0, n_coarse, (n,), generator=generator), torch.arange(n_coarse).repeat(3)])
            weight = torch.rand(fine.shape[0], generator=generator) + 0.1
            down = Transition(coarse, fine, weight / segment_sum(weight, coarse, n_coarse)[coarse], (n_coarse, n))
            up = Transition(fine, coarse, weight / segment_sum(weight, fine, n)[fine], (n, n_coarse))
        levels.append(Level(edge_sets, down, up))
    return levels


def segment_sum(values: torch.Tensor, segments: torch.Tensor, n: int) -> torch.Tensor:
    return torch.zeros(n).index_add_(0, segments, values)


def offset_map(a: Transition, b: Transition, rows: int, cols: int) -> Transition:
    return Transition(torch.cat([a.rows, b.rows + rows]), torch.cat([a.cols, b.cols + cols]),
                      torch.cat([a.weights, b.weights]), (a.shape[0] + b.shape[0], a.shape[1] + b.shape[1]))


def batch_levels(a: list[Level], b: list[Level], sizes_a: list[int]) -> list[Level]:
    """Disjoint union of two multi-level graphs, every index offset by the first graph's sizes."""
    joined = []
    for l, (la, lb) in enumerate(zip(a, b, strict=True)):
        edge_sets = [
            EdgeSet(torch.cat([ea.index, eb.index + sizes_a[l]], 1), torch.cat([ea.features, eb.features]))
            for ea, eb in zip(la.edge_sets, lb.edge_sets, strict=True)
        ]
        down = up = None
        if la.down is not None:
            down = offset_map(la.down, lb.down, sizes_a[l + 1], sizes_a[l])
            up = offset_map(la.up, lb.up, sizes_a[l], sizes_a[l + 1])
        joined.append(Level(edge_sets, down, up))
    return joined


def make_models():
    torch.manual_seed(0)
    return [
        BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, latent=32, hidden=32),
        MeshGraphNets(5, 2, EDGE_DIMS, n_passes=3, latent=32, hidden=32),
    ]


def test_mlp_follows_the_thesis():
    encoder = mlp(7, 128)
    linears = [m for m in encoder if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(7, 128), (128, 128), (128, 128)]
    assert isinstance(encoder[-1], nn.LayerNorm)
    decoder = mlp(128, 2, layer_norm=False)
    assert not any(isinstance(m, nn.LayerNorm) for m in decoder)
    assert sum(isinstance(m, nn.ReLU) for m in decoder) == 2


def test_maps_average_and_keep_constants():
    g = torch.Generator().manual_seed(1)
    (level, _) = random_levels([20, 7], g)
    # float32 sums of weights that add up to 1: a few ulps
    torch.testing.assert_close(apply_transition(torch.full((20, 3), 2.5), level.down), torch.full((7, 3), 2.5),
                               rtol=5e-7, atol=0)
    torch.testing.assert_close(apply_transition(torch.full((7, 3), -1.0), level.up), torch.full((20, 3), -1.0),
                               rtol=5e-7, atol=0)
    # Each output is a convex combination: bounded by the inputs it draws from.
    values = torch.randn(20, 1, generator=g)
    pooled = apply_transition(values, level.down)
    assert pooled.max() <= values.max() and pooled.min() >= values.min()


@pytest.mark.parametrize("index", [0, 1])
def test_batch_of_two_graphs_equals_each_alone(index):
    model = make_models()[index].eval()
    g = torch.Generator().manual_seed(2)
    sizes_a, sizes_b = [30, 14, 6], [45, 21, 9]
    a, b = random_levels(sizes_a, g), random_levels(sizes_b, g)
    xa, xb = torch.randn(30, 5, generator=g), torch.randn(45, 5, generator=g)
    with torch.no_grad():
        alone = torch.cat([model(xa, a), model(xb, b)])
        together = model(torch.cat([xa, xb]), batch_levels(a, b, sizes_a))
    torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)  # float32 matmuls of other shapes


def test_bsms_gnn_uses_every_level_and_adapts_depth():
    model = make_models()[0]
    g = torch.Generator().manual_seed(3)
    levels = random_levels([30, 14, 6], g)
    x = torch.randn(30, 5, generator=g)
    model(x, levels).square().sum().backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name
    # Fewer levels than the model has: the bottom block runs on the coarsest one given, and the
    # blocks of the missing level get no gradient.
    model.zero_grad(set_to_none=True)
    model(x, levels[:2]).square().sum().backward()
    unused = {name for name, p in model.named_parameters() if p.grad is None}
    assert unused == {name for name, _ in model.named_parameters() if name.startswith(("down_blocks.1.", "up_blocks.1."))}
    # More levels than the model has: the extra ones are never read.
    deeper = random_levels([30, 14, 6, 3], g)
    with torch.no_grad():
        assert torch.equal(model(x, deeper), model(x, deeper[:3]))


def test_meshgraphnets_sees_only_the_mesh_level():
    model = make_models()[1].eval()
    g = torch.Generator().manual_seed(4)
    levels = random_levels([30, 14, 6], g)
    x = torch.randn(30, 5, generator=g)
    with torch.no_grad():
        assert torch.equal(model(x, levels), model(x, levels[:1]))
    assert len(model.blocks) == 3 and len(MeshGraphNets(5, 2, EDGE_DIMS).blocks) == 15


def test_block_rejects_wrong_number_of_edge_sets():
    model = make_models()[0]
    g = torch.Generator().manual_seed(5)
    levels = random_levels([10, 4, 2], g)
    broken = [Level(level.edge_sets[:1], level.down, level.up) for level in levels]
    with pytest.raises(ValueError, match="block expects 2 edge sets, got 1"):
        model(torch.randn(10, 5), broken)


def test_normalizer_statistics_and_freezing():
    rng = np.random.default_rng(0)
    batches = [rng.normal([1.0, -3.0, 0.0], [2.0, 0.5, 0.0], size=(50, 3)) for _ in range(4)]
    norm = Normalizer(3, max_accumulations=3)
    for batch in batches:
        norm.accumulate(torch.tensor(batch, dtype=torch.float32))
    seen = np.concatenate(batches[:3])  # the fourth came after freezing
    assert norm.frozen and int(norm.accumulations) == 3
    # the statistics are float64 sums of the float32 inputs: float32 rounding of the data only
    np.testing.assert_allclose(norm.mean.numpy(), seen.mean(axis=0), rtol=5e-8, atol=0)
    np.testing.assert_allclose(norm.std.numpy()[:2], seen.std(axis=0)[:2], rtol=2e-7)
    assert float(norm.std[2]) == 1e-8  # constant feature: floor, not division by zero
    x = torch.tensor(batches[3], dtype=torch.float32)
    torch.testing.assert_close(norm.inverse(norm(x)), x, rtol=0, atol=1e-6)
    z = norm(torch.tensor(seen, dtype=torch.float32))
    np.testing.assert_allclose(z[:, :2].mean(0).numpy(), 0.0, atol=5e-7)
    np.testing.assert_allclose(z[:, :2].std(0, unbiased=False).numpy(), 1.0, rtol=1e-6)


def test_normalizer_state_travels_with_the_state_dict():
    norm = Normalizer(2)
    norm.accumulate(torch.tensor([[1.0, 2.0], [3.0, 6.0]]))
    fresh = Normalizer(2)
    fresh.load_state_dict(norm.state_dict())
    x = torch.tensor([[0.5, -1.0]])
    assert torch.equal(fresh(x), norm(x))
    assert set(norm.state_dict()) == {"count", "accumulations", "total", "total_squares"}


# ----------------------------------------------------------------------------- split message passing
def concatenated_block(block, v, edge_sets, groups=1):
    """A block in its textbook form (thesis eq. 4.2): each edge MLP on the concatenation
    [e_ij, v_i, v_j], the node MLP on [v_i, sum_j e^1_ij, ...] (one copy of the graph)."""
    assert groups == 1
    aggregated, updated = [], []
    for edge_mlp, (index, features) in zip(block.edge_mlps, edge_sets, strict=True):
        senders, receivers = index
        messages = edge_mlp(torch.cat([features, v[receivers], v[senders]], dim=-1))
        if isinstance(block, EdgeLatentBlock):
            messages = features + messages
            updated.append(EdgeSet(index, messages))
        aggregated.append(torch.zeros(v.shape[0], messages.shape[1]).index_add_(0, receivers, messages))
    v = v + block.node_mlp(torch.cat([v, *aggregated], dim=-1))
    return (v, updated) if isinstance(block, EdgeLatentBlock) else v


def with_empty_contacts(levels: list[Level], level: int) -> list[Level]:
    """``levels`` with no contact edges on ``level`` (an edge set without edges)."""
    empty = EdgeSet(torch.zeros(2, 0, dtype=torch.long), torch.zeros(0, EDGE_DIMS[1]))
    changed = Level([levels[level].edge_sets[0], empty], levels[level].down, levels[level].up)
    return [changed if l == level else lv for l, lv in enumerate(levels)]


def lean_model(hidden_layers: int) -> BSMSGNN:
    """BSMS-GNN without LayerNorm: its edge MLPs end in a Linear, applied to each receiver's sum."""
    torch.manual_seed(1)
    return BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, latent=32, hidden=32, hidden_layers=hidden_layers, layer_norm=False)


@pytest.mark.parametrize("index", [0, 1, "lean1", "lean2"])
def test_split_message_passing_equals_the_concatenated_form(index, monkeypatch):
    """Node products gathered per edge (mesh edges: E > N), gathered inputs (contacts: E < N) and
    an empty edge set give the concatenated form's outputs and gradients to float32 round-off; so
    does an edge MLP's last Linear applied to each receiver's sum of its inputs (no LayerNorm)."""
    model = lean_model(int(index[-1])) if isinstance(index, str) else make_models()[index]
    g = torch.Generator().manual_seed(6)
    levels = with_empty_contacts(random_levels([30, 14, 6], g), 1)
    x = torch.randn(30, 5, generator=g)

    def run():
        model.zero_grad(set_to_none=True)
        out = model(x, levels)
        out.square().sum().backward()
        return out.detach(), {name: p.grad.clone() for name, p in model.named_parameters()}

    split, split_grads = run()
    with torch.no_grad():  # skips the empty edge set
        split_inference = model(x, levels)
    monkeypatch.setattr(MessagePassingBlock, "forward", concatenated_block)
    monkeypatch.setattr(EdgeLatentBlock, "forward", concatenated_block)
    reference, reference_grads = run()
    # float32 sums in another order: over 30 seeds <= 4.3e-7 of the output's scale, 9.1e-7 of each gradient's
    scale = float(reference.abs().max())
    torch.testing.assert_close(split, reference, rtol=0, atol=4e-6 * scale)
    torch.testing.assert_close(split_inference, reference, rtol=0, atol=4e-6 * scale)
    for name, grad in reference_grads.items():
        torch.testing.assert_close(split_grads[name], grad, rtol=0, atol=9e-6 * float(grad.abs().max()) + 1e-12,
                                   msg=lambda m, name=name: f"gradient of {name}: {m}")


def test_a_final_edge_linear_runs_once_per_receiver_not_per_edge():
    """Without LayerNorm the edge MLPs' last Linear never sees the (E, H) per-edge rows: its
    module is not called, its weights act on the (N, H) sums (with LayerNorm it is called per edge)."""
    g = torch.Generator().manual_seed(2)
    levels, x = random_levels([30, 14, 6], g), torch.randn(30, 5, generator=g)
    for model, calls_expected in ((lean_model(1), 0), (make_models()[0], None)):
        calls = []
        for name, module in model.named_modules():
            if ".edge_mlps." in name and isinstance(module, nn.Linear) and not name.endswith(".0"):
                module.register_forward_hook(lambda m, args, out, calls=calls: calls.append(args[0].shape[0]))
        model(x, levels)
        if calls_expected is None:
            assert calls and all(rows in (3 * 30, 3 * 14, 3 * 6, 15, 7, 3) for rows in calls), calls
        else:
            assert len(calls) == calls_expected, calls


def test_sorted_transitions_equal_the_unsorted_sum():
    """Triplets sorted by row are summed as weighted bags; the same triplets shuffled take the
    per-triplet path: equal sums (to float32 round-off) and gradients, rows without triplets 0."""
    g = torch.Generator().manual_seed(3)
    rows = torch.sort(torch.randint(0, 40, (300,), generator=g)).values
    rows = rows[rows != 7]  # an empty row, and the last rows likely empty too
    cols = torch.randint(0, 90, rows.shape, generator=g)
    weights = torch.rand(rows.shape, generator=g)
    shuffle = torch.randperm(rows.numel(), generator=g)
    v = torch.randn(90, 16, generator=g, requires_grad=True)
    outs, grads = [], []
    for order in (torch.arange(rows.numel()), shuffle):
        out = apply_transition(v, Transition(rows[order], cols[order], weights[order], (45, 90)))
        (grad,) = torch.autograd.grad(out.square().sum(), v)
        outs.append(out.detach()), grads.append(grad)
    reference = torch.zeros(45, 16).index_add_(0, rows, v.detach()[cols] * weights[:, None])
    assert torch.equal(outs[0][7], torch.zeros(16)) and torch.equal(outs[0][40:], torch.zeros(5, 16))
    torch.testing.assert_close(outs[0], reference, rtol=0, atol=2e-6)
    torch.testing.assert_close(outs[1], reference, rtol=0, atol=2e-6)
    torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=4e-6)


def test_split_blocks_keep_the_concatenated_parameters():
    """The same parameters under the same names and shapes as the concatenated form: checkpoints
    written before the split load unchanged."""
    bsms_gnn, mgn = make_models()
    state = bsms_gnn.state_dict()
    assert state["bottom_block.edge_mlps.0.0.weight"].shape == (32, EDGE_DIMS[0] + 2 * 32)
    assert state["bottom_block.edge_mlps.1.0.weight"].shape == (32, EDGE_DIMS[1] + 2 * 32)
    assert state["down_blocks.0.node_mlp.0.weight"].shape == (32, 3 * 32)
    assert mgn.state_dict()["blocks.2.edge_mlps.1.0.weight"].shape == (32, 3 * 32)
    assert sum(1 for name in state if name.startswith("bottom_block.")) == 3 * (2 * 3 + 2)  # 3 MLPs
