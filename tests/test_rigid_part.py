"""model.rigid_part: a body's velocity change as its rigid-motion part (2D similarity, 3D affine
field, bsms.models.body_motion) plus the rest, each with its own normaliser."""

import math

import numpy as np
import pytest
import torch
from conftest import tiny_run_config

from bsms.augment import position_noise
from bsms.config import ConfigError
from bsms.data import FrameDataset, GraphOptions, NodeType
from bsms.fields import FieldSpec
from bsms.infer.pretrained import export
from bsms.models.body_motion import rigid_part, rigid_step
from bsms.models.simulator import LearnedSimulator
from bsms.options import NoiseOptions
from bsms.run import load_config, load_model, split_files
from bsms.training.trainer import Trainer

DT = 0.04


def _turn(axis, angle):
    """Rotation matrix by ``angle`` about ``axis`` (None: the 2D turn)."""
    if axis is None:
        c, s = math.cos(angle), math.sin(angle)
        return torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    n = torch.as_tensor(axis, dtype=torch.float64)
    n = n / n.norm()
    k = torch.tensor([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _one(n):
    """One body of n nodes, all masked: (ids, mask)."""
    return torch.zeros(n, dtype=torch.long), torch.ones(n, dtype=torch.bool)


@pytest.mark.parametrize("dim", [2, 3])
def test_every_rigid_motions_velocity_change_is_its_own_rigid_part(dim):
    """Two steps of rigid motion of any size (turns of 0.5-1.3 rad about different points and, in
    3D, axes, and a translation): the secant velocity change lies in the space to round-off, while
    a field of random node values does not."""
    gen = torch.Generator().manual_seed(dim)
    x0 = torch.randn(50, dim, generator=gen, dtype=torch.float64)
    axes = (None, None) if dim == 2 else ([0.3, 0.5, 0.8], [0.0, 1.0, 0.2])
    p, q = torch.randn(2, dim, generator=gen, dtype=torch.float64)
    x1 = (x0 - p) @ _turn(axes[0], 0.5).T + p
    x2 = (x1 - q) @ _turn(axes[1], 1.3).T + q + 0.01
    change = (x2 - x1) / DT - (x1 - x0) / DT
    ids, mask = _one(50)
    rest = change - rigid_part(change, x1, ids, 1, mask)
    assert float(rest.abs().max()) < 1e-13 * float(change.abs().max())
    noise = torch.randn(50, dim, generator=gen, dtype=torch.float64)
    assert float((noise - rigid_part(noise, x1, ids, 1, mask)).norm()) > 0.5 * float(noise.norm())


@pytest.mark.parametrize("dim", [2, 3])
def test_the_rigid_part_is_an_orthogonal_projection_per_body_over_its_masked_nodes(dim):
    gen = torch.Generator().manual_seed(10 + dim)
    pos = torch.randn(70, dim, generator=gen, dtype=torch.float64)
    field = torch.randn(70, dim, generator=gen, dtype=torch.float64)
    ids = torch.cat([torch.zeros(30, dtype=torch.long), torch.ones(40, dtype=torch.long)])
    mask = torch.rand(70, generator=gen) < 0.8
    part = rigid_part(field, pos, ids, 2, mask)
    torch.testing.assert_close(rigid_part(part, pos, ids, 2, mask), part, rtol=0, atol=1e-13)  # idempotent
    rest = (field - part)[mask]
    for body in (0, 1):  # the rest is orthogonal to every field of the space over the body's masked nodes
        own = ids[mask] == body
        p = pos[mask][own] - pos[mask][own].mean(0)
        r = rest[own]
        torch.testing.assert_close(r.sum(0), torch.zeros(dim, dtype=torch.float64), rtol=0, atol=1e-12)
        if dim == 2:
            turned = torch.stack([-p[:, 1], p[:, 0]], 1)
            for basis in (p, turned):
                assert abs(float((r * basis).sum())) < 1e-12
        else:
            torch.testing.assert_close(r.T @ p, torch.zeros(3, 3, dtype=torch.float64), rtol=0, atol=1e-12)
    # each body alone gives the same; unmasked nodes' values change nothing, and get the fitted field
    for rows in (slice(0, 30), slice(30, 70)):
        alone = rigid_part(field[rows], pos[rows], torch.zeros(len(pos[rows]), dtype=torch.long), 1, mask[rows])
        torch.testing.assert_close(alone, part[rows], rtol=0, atol=1e-13)
    moved = torch.where(mask[:, None], field, 1e3)
    torch.testing.assert_close(rigid_part(moved, pos, ids, 2, mask), part, rtol=0, atol=1e-12)


def test_degenerate_bodies_get_what_they_resolve():
    pos = torch.tensor([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]], dtype=torch.float64)
    field = torch.tensor([[1.0, 2.0], [3.0, 4.0], [7.0, 8.0]], dtype=torch.float64)
    ids = torch.tensor([0, 0, 1])
    part = rigid_part(field, pos, ids, 2, torch.tensor([False, False, True]))
    assert torch.equal(part[:2], torch.zeros(2, 2, dtype=torch.float64)), "no masked node: zeros"
    assert torch.equal(part[2], field[2]), "one node: its translation"
    flat = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]], dtype=torch.float64)
    turn = (flat - 0.3) @ _turn([0.2, 0.4, 1.0], 0.7).T - flat  # an affine field on a plane of nodes:
    ids4, mask4 = _one(4)
    torch.testing.assert_close(rigid_part(turn, flat, ids4, 1, mask4), turn, rtol=0, atol=1e-14)  # met at the nodes
    with pytest.raises(ValueError, match="rigid parts are built for 2D and 3D positions, got 1D"):
        rigid_part(field[:, :1], pos[:, :1], ids, 2, torch.ones(3, dtype=torch.bool))


@pytest.fixture(scope="module")
def frame(tiny_folder):
    return FrameDataset(split_files(tiny_folder, "train")[:1], GraphOptions(levels=3))[4]


def _identity(normalizer, scale=1.0):
    normalizer.count.fill_(1.0), normalizer.total.zero_(), normalizer.total_squares.fill_(scale**2)


def test_a_rigid_part_model_splits_its_answer_and_scores_each_part_in_its_own_units(frame):
    torch.manual_seed(0)
    model = LearnedSimulator("bsms_gnn", 2, n_levels=3, latent=16, rigid_part=True)
    _identity(model.output_normalizer, 0.5)
    _identity(model.residual_normalizer, 0.01)
    with torch.no_grad():
        raw = model(frame)
    assert raw.shape == (frame.num_nodes, 4)
    change = model.physical(raw, frame)
    free = frame.node_type == NodeType.FREE
    ids = torch.zeros(frame.num_nodes, dtype=torch.long)
    rest = change - rigid_part(change, frame.pos, ids, 1, free)
    bound = 0.01 * float(raw[:, 2:].norm(dim=1).max())
    assert 0 < float(rest[free].norm(dim=1).max()) <= bound, "the rest is the residual channels at their scale"
    with pytest.raises(ValueError, match="give physical\\(\\) the graph it answers"):
        model.physical(raw)
    # the exact split of the target scores zero; anything else more
    target = frame.target.double()
    rigid = rigid_part(target, frame.pos.double(), ids, 1, free)
    exact = torch.cat([(target / 0.5), (target - rigid) / 0.01], 1).float()
    assert float(model.prediction_loss(exact, frame)) < 1e-9
    assert float(model.prediction_loss(exact + 0.1 * torch.randn_like(exact), frame)) > 1e-3
    with pytest.raises(ValueError, match="rigid_part and rigid_step split a body's velocity into its rigid-motion part"):
        LearnedSimulator("bsms_gnn", 3, rigid_part=True, fields=FieldSpec.lagrangian(3, 2))


def test_a_rigid_part_run_trains_validates_by_rollout_and_loads(tiny_dataset, tmp_path, one_thread):
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, model={"rigid_part": True}, train={
        "frame_stride": 2, "steps": 3, "valid_every": 3, "checkpoint_every": 3, "validation": "rollout"},
        evaluate={"enabled": False}))
    trainer = Trainer(config)
    metrics = trainer.fit()
    assert np.isfinite(metrics["loss"]) and np.isfinite(trainer.valid_vs_rest)
    model, loaded, _ = load_model(config.run_dir, "latest")
    assert model.rigid_part and loaded.model.rigid_part
    assert float(model.residual_normalizer.count) > 0
    assert torch.equal(model.residual_normalizer.total, trainer.model.residual_normalizer.total)
    assert not model.rigid_step
    export(config.run_dir, tmp_path / "stepped", "latest", ["model.rigid_step=true"])  # inference only
    stepped, saved, _ = load_model(tmp_path / "stepped")
    assert stepped.rigid_step and saved.model.rigid_step
    torch.testing.assert_close(stepped.state_dict(), model.state_dict(), rtol=0, atol=0)


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_noise_is_a_random_rigid_field_of_the_asked_variance_on_the_free_nodes(dim):
    rng = np.random.default_rng(dim)
    pos = rng.normal(size=(60, dim))
    free = (np.arange(60) % 5 != 0)[:, None]
    draws = np.stack([position_noise(rng, pos, free, 1e-3, rigid=True) for _ in range(400)])
    assert np.all(draws[:, ~free[:, 0]] == 0)
    ids, mask = torch.zeros(60, dtype=torch.long), torch.from_numpy(free[:, 0])
    for dx in draws[:5]:
        t = torch.from_numpy(dx)
        assert float((t - rigid_part(t, torch.from_numpy(pos), ids, 1, mask))[mask].abs().max()) < 1e-15
    variance = draws[:, free[:, 0]].var()
    assert abs(variance / 1e-6 - 1) < 0.1  # 400 draws of 4 (2D) or 12 (3D) dimensions
    assert np.array_equal(position_noise(np.random.default_rng(1), pos, free, 1e-3),
                          free * np.random.default_rng(1).normal(0.0, 1e-3, pos.shape)), "node noise as before"


def test_rigid_noise_leaves_the_targets_rest_as_the_data_has_it(tiny_folder):
    noise = NoiseOptions(position=1e-3, rigid=True)
    files = split_files(tiny_folder, "train")[:1]
    noisy, clean = FrameDataset(files, GraphOptions(levels=2), noise), FrameDataset(files, GraphOptions(levels=2))
    model = LearnedSimulator("bsms_gnn", 2, n_levels=2, latent=8, rigid_part=True)
    for index in (1, 4):
        a, b = noisy[(index, 77)], clean[index]
        assert float((a.pos - b.pos).abs().max()) > 1e-4
        added = (a.target - b.target).double()
        ids = torch.zeros(a.num_nodes, dtype=torch.long)
        free = a.node_type == NodeType.FREE
        rest = added - rigid_part(added, a.pos.double(), ids, 1, free)
        assert float(rest[free].abs().max()) < 2e-6 * float(added.abs().max())  # float32 graphs: 2.6e-7
    assert model.rigid_part
    with pytest.raises(ConfigError, match="'noise.rigid' draws rigid motions of 2D or 3D bodies"):
        noise.check(FieldSpec.lagrangian(3, 2), "dataset cloth")


def _distances(x):
    return (x[:, None] - x[None]).norm(dim=-1)


@pytest.mark.parametrize("dim", [2, 3])
def test_a_rigid_step_keeps_rigid_motion_and_makes_any_affine_step_rigid(dim):
    gen = torch.Generator().manual_seed(20 + dim)
    x = torch.randn(40, dim, generator=gen, dtype=torch.float64)
    ids, mask = _one(40)
    dt = torch.tensor([0.04], dtype=torch.float64)
    axis = None if dim == 2 else [0.2, -0.5, 1.0]
    pivot = torch.randn(dim, generator=gen, dtype=torch.float64)
    turned = (x - pivot) @ _turn(axis, 0.9).T + pivot + 0.003
    velocity = (turned - x) / dt
    steps = dt.expand(40)  # each node's step
    torch.testing.assert_close(rigid_step(velocity, x, ids, 1, mask, steps), velocity, rtol=0, atol=1e-12)
    strain = 0.1 * torch.randn(dim, dim, generator=gen, dtype=torch.float64)  # stretch and shear of 10%
    stepped = rigid_step(velocity + (x - x.mean(0)) @ strain.T / dt, x, ids, 1, mask, steps)
    torch.testing.assert_close(_distances(x + dt * stepped), _distances(x), rtol=0, atol=1e-12)
    wobble = torch.randn(40, dim, generator=gen, dtype=torch.float64)
    basis = torch.cat([torch.ones(40, 1, dtype=torch.float64), x], 1)
    wobble = 1e-3 * (wobble - basis @ torch.linalg.lstsq(basis, wobble).solution)  # non-affine: kept as it is
    kept = rigid_step(velocity + (x - x.mean(0)) @ strain.T / dt + wobble, x, ids, 1, mask, steps) - stepped
    torch.testing.assert_close(kept, wobble, rtol=0, atol=1e-12)


def test_a_rigid_step_model_moves_a_stiff_body_without_changing_its_shape(frame):
    torch.manual_seed(1)
    frame = frame.clone()
    frame.velocity = 3.0 * (frame.pos - frame.pos.mean(0)) @ torch.tensor([[0.0, 1.0], [-1.0, 0.0]])  # turning
    model = LearnedSimulator("bsms_gnn", 2, n_levels=3, latent=16, rigid_part=True, rigid_step=True)
    _identity(model.output_normalizer, 0.5)
    _identity(model.residual_normalizer, 1e-12)  # no rest: what moves is the affine part
    free = frame.node_type == NodeType.FREE
    change = model.velocity_change(frame).double()
    coming = frame.pos.double() + frame.frame_dt.double()[:, None] * (frame.velocity.double() + change)
    before, after = _distances(frame.pos.double()[free]), _distances(coming[free])
    moved = float((after - before).abs().max())
    model.rigid_step = False
    loose = frame.pos.double() + frame.frame_dt.double()[:, None] * (frame.velocity.double()
                                                                      + model.velocity_change(frame).double())
    assert float((_distances(loose[free]) - before).abs().max()) > 1e3 * moved
    assert moved < 1e-6 * float(before.max())  # float32 graphs
