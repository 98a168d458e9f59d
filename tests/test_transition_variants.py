"""bsms.models.transition_variants: the transitions of the ablation (thesis §4.4.4.1, Table 4.7)."""

import math

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from torch_geometric.data import Batch

from bsms.data import NodeType
from bsms.graph import Transition, bistride_levels
from bsms.level_graph import frame_graph, hierarchy_levels
from bsms.models import BSMSGNN, Context, Level, apply_transition
from bsms.models.simulator import LearnedSimulator
from bsms.models.transition_variants import (
    TRANSITIONS,
    GraphConvTransition,
    IndexTransition,
    LearnableTransition,
    inverse_distance_weights,
    kept_local_indices,
    mean_over_rows,
    uniform_weights,
)
from bsms.run import load_config
from bsms.training.trainer import Trainer
from datagen import shapes

N_LEVELS = 3


def sample(mesh, seed: int):
    """(hierarchy, graph) of a frame of ``mesh`` slightly moved, clamped nodes on its left, a
    target the network can learn from its inputs (a rotated velocity plus a smooth field)."""
    rng = np.random.default_rng(seed)
    hierarchy = bistride_levels(mesh, mesh.nodes, levels=N_LEVELS, seeding="close_center")
    pos = mesh.nodes + 0.01 * rng.normal(size=mesh.nodes.shape)
    velocity = rng.normal(size=mesh.nodes.shape)
    target = 0.5 * velocity[:, ::-1] * [-1.0, 1.0] + 0.3 * np.cos(3.0 * mesh.nodes)
    node_type = np.where(mesh.boundary_node_mask & (mesh.nodes[:, 0] < mesh.nodes[:, 0].min() + 0.05),
                         NodeType.CLAMPED, NodeType.FREE)
    graph = frame_graph(hierarchy_levels(hierarchy), rest_pos=mesh.nodes, pos=pos, velocity=velocity,
                        node_type=node_type, target=target)
    return hierarchy, graph


@pytest.fixture(scope="module")
def meshes():
    """Two different meshes (58 and 178 nodes), each with its hierarchy and one frame."""
    return [sample(shapes.disk(0.5, 0.15), 0), sample(shapes.glyph("B", 0.06), 1)]


def bare_levels(graph) -> list[Level]:
    """The graph's levels without edge sets: what the transitions read."""
    return [Level([], graph.transition("down", l) if l + 1 < N_LEVELS else None,
                  graph.transition("up", l) if l + 1 < N_LEVELS else None, graph[f"nodes_{l}"])
            for l in range(N_LEVELS)]


def context_of(graph, accumulate: bool = False) -> Context:
    counts = graph["n_nodes_0"]
    ids = torch.arange(len(counts)).repeat_interleave(counts) if torch.is_tensor(counts) else torch.zeros(
        graph.num_nodes, dtype=torch.long)
    return Context(torch.cat([graph.rest_pos, graph.pos], -1), ids, int(ids.max()) + 1, 2, accumulate)


def model(transition: str, latent: int = 32) -> LearnedSimulator:
    torch.manual_seed(0)
    return LearnedSimulator("bsms_gnn", 2, n_levels=N_LEVELS, latent=latent, core_options={"transition": transition})


# ----------------------------------------------------------------------------- none, graph_conv
def test_none_picks_and_puts_back_exactly(meshes):
    for hierarchy, graph in meshes:
        levels, index = bare_levels(graph), IndexTransition()
        for l in range(N_LEVELS - 1):
            kept = kept_local_indices(levels, l)
            np.testing.assert_array_equal(kept.numpy(), hierarchy.levels[l + 1].kept)
            v = torch.randn(graph.level_size(l), 5)
            pooled = index.down(v, levels, l)
            assert torch.equal(pooled, v[kept])
            back = index.up(pooled, levels, l)
            dropped = torch.ones(len(v), dtype=torch.bool).index_fill_(0, kept, False)
            assert torch.equal(back[kept], v[kept]) and dropped.any() and not back[dropped].any()


def test_graph_conv_is_a_uniform_mean_over_the_bistride_patterns(meshes):
    for _, graph in meshes:
        levels, conv = bare_levels(graph), GraphConvTransition()
        for l in range(N_LEVELS - 1):
            for pattern in (levels[l].down, levels[l].up):
                counts = np.bincount(pattern.rows.numpy(), minlength=pattern.shape[0]).astype(np.float32)
                assert counts.min() >= 1
                expected = (np.float32(1) / counts)[pattern.rows.numpy()]  # float32 division, correctly rounded
                assert np.array_equal(uniform_weights(pattern).numpy(), expected)
                v = torch.randn(pattern.shape[1], 4)
                # the sum-then-divide form against the weighted sum: float32 round-off
                torch.testing.assert_close(mean_over_rows(v, pattern), apply_transition(
                    v, Transition(pattern.rows, pattern.cols, uniform_weights(pattern), pattern.shape)),
                    rtol=0, atol=1e-6)
            # a constant whose row sums are exact (dyadic, few bits) comes back exactly
            constant = torch.tensor([1.5, -3.25, 0.0, 1024.0]).expand(graph.level_size(l), 4)
            down = conv.down(constant, levels, l)
            assert torch.equal(down, constant[: len(down)])
            assert torch.equal(conv.up(down, levels, l), constant)


# ----------------------------------------------------------------------------- pos_kernel
def star_levels():
    """A kept node at the origin with neighbours at distances 1, 2 and 4; the neighbours are dropped."""
    pos = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, -2.0], [-4.0, 0.0]])
    down = Transition(torch.zeros(4, dtype=torch.long), torch.arange(4), torch.full((4,), 0.25), (1, 4))
    up = Transition(torch.arange(4), torch.zeros(4, dtype=torch.long), torch.ones(4), (4, 1))
    return pos, [Level([], down, up, torch.arange(4)), Level([], None, None, torch.tensor([0]))]


def reference_weights(transition, receiver_nodes, sender_nodes, pos) -> np.ndarray:
    """The pos_kernel weights by hand, row by row in float64: 1 / distance, the self pair at the
    nearest other node's distance (1 alone in its row), divided by the row's sum."""
    weights = np.zeros(len(transition.rows))
    for r in range(transition.shape[0]):
        entries = np.flatnonzero(transition.rows == r)
        receiver = receiver_nodes[r]
        senders = sender_nodes[transition.cols[entries]]
        distance = np.linalg.norm(pos[senders] - pos[receiver], axis=1)
        others = senders != receiver
        inverse = np.where(others, 1.0 / np.where(others, distance, 1.0), 0.0)
        inverse[~others] = inverse[others].max() if others.any() else 1.0
        weights[entries] = inverse / inverse.sum()
    return weights


def pos_kernel_weights(levels, l, kind, pos):
    pattern = levels[l].down if kind == "down" else levels[l].up
    rows_level, cols_level = (l + 1, l) if kind == "down" else (l, l + 1)
    receivers = levels[rows_level].nodes[pattern.rows]
    senders = levels[cols_level].nodes[pattern.cols]
    return inverse_distance_weights(pattern, receivers, senders, pos)


def test_pos_kernel_weights_of_a_star_by_hand():
    pos, levels = star_levels()
    # inverse distances 1 (self: as the nearest neighbour), 1, 1/2, 1/4 over their sum 11/4
    torch.testing.assert_close(pos_kernel_weights(levels, 0, "down", pos),
                               torch.tensor([4 / 11, 4 / 11, 2 / 11, 1 / 11]), rtol=2e-7, atol=0)  # measured 3.0e-8
    # each fine node has only the kept node: weight 1, the kept node's own copy included
    assert torch.equal(pos_kernel_weights(levels, 0, "up", pos), torch.ones(4))


def test_pos_kernel_weights_match_a_numpy_reference(meshes):
    worst_reference = worst_sum = 0.0
    for hierarchy, graph in meshes:
        levels, pos = bare_levels(graph), graph.pos
        pos64 = pos.double().numpy()  # the same float32 positions: only float32 arithmetic differs
        for l in range(N_LEVELS - 1):
            fine, coarse = hierarchy.finest_indices(l), hierarchy.finest_indices(l + 1)
            for kind, transition, receivers, senders in (("down", hierarchy.levels[l + 1].down, coarse, fine),
                                                         ("up", hierarchy.levels[l + 1].up, fine, coarse)):
                weights = pos_kernel_weights(levels, l, kind, pos)
                expected = reference_weights(transition, receivers, senders, pos64)
                worst_reference = max(worst_reference, float(np.abs(weights.double().numpy() / expected - 1).max()))
                sums = torch.zeros(transition.shape[0], dtype=torch.float64).index_add_(
                    0, torch.from_numpy(transition.rows), weights.double())
                worst_sum = max(worst_sum, float((sums - 1).abs().max()))
    assert worst_reference < 2e-6, worst_reference  # measured 2.3e-7 relative
    assert worst_sum < 1e-6, worst_sum  # rows sum to 1: measured 1.2e-7 (one float32 ulp)


def test_pos_kernel_weights_are_invariant_to_rigid_motions(meshes):
    _, graph = meshes[1]
    levels = bare_levels(graph)
    angle = 0.7
    rotation = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    moved = graph.pos @ rotation.T + torch.tensor([3.0, -2.0])
    for l in range(N_LEVELS - 1):
        for kind in ("down", "up"):
            before = pos_kernel_weights(levels, l, kind, graph.pos)
            after = pos_kernel_weights(levels, l, kind, moved)
            # float32 positions moved by O(3): distances of O(0.05) change by a few ulps of 3
            torch.testing.assert_close(after, before, rtol=0, atol=2e-5)  # measured 3.5e-6


# ----------------------------------------------------------------------------- learnable
def test_learnable_gives_each_graph_of_a_batch_its_own_result(meshes):
    torch.manual_seed(0)
    learnable = LearnableTransition(N_LEVELS, 16, 16, 2)
    graphs = [g for _, g in meshes]
    batch = Batch.from_data_list(graphs)
    levels, contexts = [bare_levels(g) for g in graphs], [context_of(g) for g in graphs]
    with torch.no_grad():
        for l in range(N_LEVELS - 1):  # normalisers that are not the identity
            learnable.down(torch.randn(batch.level_size(l), 16), bare_levels(batch), l, context_of(batch, True))
            learnable.up(torch.randn(batch.level_size(l + 1), 16), bare_levels(batch), l, context_of(batch, True))
        for l in range(N_LEVELS - 1):
            for kind, level in (("down", l), ("up", l + 1)):
                inputs = [torch.randn(g.level_size(level), 16) for g in graphs]
                alone = torch.cat([getattr(learnable, kind)(v, lv, l, c)
                                   for v, lv, c in zip(inputs, levels, contexts, strict=True)])
                together = getattr(learnable, kind)(torch.cat(inputs), bare_levels(batch), l, context_of(batch))
                torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)  # measured 0 on this CPU
        # moving the second graph changes its own rows only
        moved = batch.clone()
        second = (torch.arange(batch.num_nodes) >= graphs[0].num_nodes)[:, None]
        moved.pos = batch.pos + 0.01 * torch.randn(batch.pos.shape) * second
        v = torch.randn(batch.num_nodes, 16)
        before = learnable.down(v, bare_levels(batch), 0, context_of(batch))
        after = learnable.down(v, bare_levels(batch), 0, context_of(moved))
        first = graphs[0].level_size(1)
        assert torch.equal(after[:first], before[:first])
        assert (after[first:] - before[first:]).abs().amax(dim=1).min() > 0


def test_learnable_reads_any_dimension_with_the_same_parameters(meshes):
    """Offsets are padded to 3D: a 2D frame placed in the plane z = 0 gives exactly its 2D result."""
    torch.manual_seed(0)
    learnable = LearnableTransition(N_LEVELS, 16, 16, 2)
    _, graph = meshes[1]
    levels, flat = bare_levels(graph), context_of(graph, accumulate=True)
    zeros = torch.zeros(graph.num_nodes, 1)
    lifted = Context(torch.cat([graph.rest_pos, zeros, graph.pos, zeros], -1), flat.graph, 1, 3, True)
    v = torch.randn(graph.num_nodes, 16)
    with torch.no_grad():
        learnable.down(v, levels, 0, flat)  # normalisers that are not the identity
        assert torch.equal(learnable.down(v, levels, 0, lifted._replace(accumulate=False)),
                           learnable.down(v, levels, 0, flat._replace(accumulate=False)))


def test_learnable_parameters_learn_and_normalisers_accumulate_only_when_asked(meshes):
    simulator = model("learnable", latent=16)
    _, graph = meshes[1]
    keys = [k for k in simulator.state_dict() if k.startswith("core.transitions.")]
    # per pass: two MLPs of 3 Linear + 1 LayerNorm (8 tensors each) and a normaliser (4 buffers)
    assert len(keys) == (N_LEVELS - 1) * 2 * (2 * 8 + 4)
    assert "core.transitions.passes.1.0.normalizer.total" in keys
    simulator.loss(graph).backward()
    counts = {k: float(v) for k, v in simulator.state_dict().items() if k.endswith("normalizer.count")}
    assert all(v == 0 for k, v in counts.items() if k.startswith("core.transitions.")), "no accumulate, no statistics"
    for name, parameter in simulator.core.transitions.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name
    simulator.loss(graph, accumulate=True)
    pairs_0 = len(graph.down_rows_0)
    assert float(simulator.state_dict()["core.transitions.passes.0.0.normalizer.count"]) == pairs_0


# ----------------------------------------------------------------------------- the whole model
def old_forward(core: BSMSGNN, x, levels):
    """BSMS-GNN's forward as it was before the variants: the bi-stride weights inline."""
    v = core.encoder(x)
    skips = []
    for l in range(N_LEVELS - 1):
        v = core.down_blocks[l](v, levels[l].edge_sets)
        skips.append(v)
        v = apply_transition(v, levels[l].down)
    v = core.bottom_block(v, levels[N_LEVELS - 1].edge_sets)
    for l in reversed(range(N_LEVELS - 1)):
        v = apply_transition(v, levels[l].up)
        v = core.up_blocks[l](v, levels[l].edge_sets) + skips[l]
    return core.decoder(v)


def test_bistride_default_is_unchanged(meshes, monkeypatch):
    default = model("bistride")
    assert not default.core.needs_context
    assert not any("transitions" in k for k in default.state_dict()), "no state beyond the blocks"
    monkeypatch.setattr(LearnedSimulator, "_context", lambda *a: pytest.fail("bistride must not build a Context"))
    batch = Batch.from_data_list([g for _, g in meshes])
    default.loss(batch, accumulate=True)
    with torch.no_grad():
        out = default(batch)
        levels = [default._level(batch, l, False) for l in range(N_LEVELS)]
        assert torch.equal(out, old_forward(default.core, default.node_normalizer(default.node_features(batch)), levels))


@pytest.mark.parametrize("transition", TRANSITIONS)
def test_batch_equals_each_alone_and_translation_invariance(meshes, transition):
    simulator = model(transition)
    graphs = [g for _, g in meshes]
    simulator.loss(graphs[0], accumulate=True)
    simulator.eval()
    assert simulator.core.needs_context == (transition in ("pos_kernel", "learnable"))
    shifted = graphs[1].clone()
    shifted.pos = graphs[1].pos + torch.tensor([3.0, -2.0])
    shifted.rest_pos = graphs[1].rest_pos + torch.tensor([-1.0, 5.0])
    with torch.no_grad():
        alone = torch.cat([simulator(g) for g in graphs])
        together = simulator(Batch.from_data_list(graphs))
        torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)  # measured 0 on this CPU (other matmul shapes)
        # float32 positions shifted by O(3) lose a few ulps in the offsets
        torch.testing.assert_close(simulator(shifted), simulator(graphs[1]), rtol=0, atol=5e-6)  # measured <= 8.6e-7


# measured final/first loss after 40 Adam steps: bistride 0.13, none 0.052, graph_conv 0.11,
# pos_kernel 0.11, learnable 0.043
@pytest.mark.parametrize("transition", TRANSITIONS)
def test_overfits_one_batch(meshes, transition, one_thread):
    simulator = model(transition, latent=32)
    batch = Batch.from_data_list([g for _, g in meshes])
    simulator.loss(batch, accumulate=True)
    optimizer = torch.optim.Adam(simulator.parameters(), lr=3e-3)
    with torch.no_grad():
        first = float(simulator.loss(batch))
    for _ in range(40):
        optimizer.zero_grad()
        simulator.loss(batch).backward()
        optimizer.step()
    with torch.no_grad():
        final = float(simulator.loss(batch))
    assert final < 0.3 * first, f"loss fell from {first:.3g} to {final:.3g} only"


def test_transitions_without_their_inputs_are_refused(meshes):
    _, graph = meshes[0]
    levels = bare_levels(graph)
    with pytest.raises(ValueError, match="needs the level-0 index"):
        IndexTransition().down(torch.zeros(graph.num_nodes, 3), [lv._replace(nodes=None) for lv in levels], 0)
    core = BSMSGNN(5, 2, [3], N_LEVELS, latent=8, hidden=8, transition="pos_kernel")
    with pytest.raises(ValueError, match="reads positions: pass a Context"):
        core.transitions.down(torch.zeros(graph.num_nodes, 8), levels, 0, None)
    with pytest.raises(ValueError, match="unknown transition 'bilinear'"):
        BSMSGNN(5, 2, [3], N_LEVELS, transition="bilinear")


# ----------------------------------------------------------------------------- training and resume
@pytest.fixture(scope="module")
def folder(tiny_folder):
    return tiny_folder


@pytest.mark.parametrize("transition", ["learnable", "pos_kernel"])
def test_training_resumes_exactly(tiny_dataset, folder, tmp_path, transition, one_thread):
    def config(runs):
        return load_config(tiny_run_config(
            tiny_dataset, runs, model={"latent": 16, "transition": transition},
            train={"steps": 6, "normalizer_steps": 3, "log_every": 2, "valid_every": 6, "checkpoint_every": 3}))

    whole = Trainer(config(tmp_path / "a"), dataset_folder=folder)
    whole.fit()
    interrupted = Trainer(config(tmp_path / "b"), dataset_folder=folder)
    interrupted.fit(stop_at=3)
    del interrupted
    resumed = Trainer(config(tmp_path / "b"), dataset_folder=folder, resume=True)
    assert resumed.step == 3
    resumed.fit()
    state, again = whole.model.state_dict(), resumed.model.state_dict()
    assert list(state) == list(again)
    for name, value in state.items():
        assert torch.equal(value, again[name]), f"{name} differs after resume"
    if transition == "learnable":
        assert float(state["core.transitions.passes.0.1.normalizer.accumulations"]) == 3
