"""A-ULMPM reference configurations (eulerian / total / adaptive): equivalences, rigid motion,
numerical fracture, the droplet's rebuild savings, the contact trigger and the fluid material."""

from dataclasses import replace

import numpy as np
import pytest
import torch

import datagen
from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mpm import Model, State, compute_kernel, linalg, step
from datagen.mpm.boundary import Mirror, Wall, apply_conditions, mesh_conditions
from datagen.mpm.kernels import MeshTables
from datagen.mpm.materials import NeoHookean, WeaklyCompressibleFluid
from datagen.mpm.nodal import nodal_update
from datagen.mpm.reference import kernel_rebuilds, strain_criterion
from datagen.mpm.stress import kirchhoff_stress
from datagen.mpm.transfers import p2g_plain
from datagen.scenes import ConfigError
from datagen.scenes.base import lattice
from datagen.scenes.stretched_bar import bar_length
from datagen.simulation import build_simulation

pytestmark = pytest.mark.usefixtures("one_thread")


MODES = ("eulerian", "total", "adaptive")


@pytest.fixture(scope="module")
def scene_runs():
    """run(scene) -> {mode: Trajectory} of a scene at its defaults (the documented cases), each
    simulated once per module on one thread and shared by the tests that need it."""
    done = {}

    def run(scene: str) -> dict:
        if scene not in done:
            before = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                done[scene] = {mode: datagen.simulate({"scene": scene, "solver": {"reference": mode}}) for mode in MODES}
            finally:
                torch.set_num_threads(before)
        return done[scene]

    return run


def fracture(traj) -> np.ndarray:
    """(T,) fraction of body-mesh edges longer than twice the background cell size, per frame."""
    edges = traj.mesh.edges
    lengths = np.linalg.norm(traj.positions[:, edges[:, 0]] - traj.positions[:, edges[:, 1]], axis=-1)
    return (lengths > 2 * traj.config["params"]["mesh_size"]).mean(axis=1)


# ----------------------------------------------------------------------------- 1. equivalences
def _plain_umls_flip(model: Model, state: State, dt: float) -> State:
    """UMLS Algorithm 1 with FLIP, written out independently of the solver's transfer code."""
    k = compute_kernel(model, state.x, state.cell)
    n, d = model.n_nodes, model.dim
    idx = k.index.clamp(min=0)
    w = k.weight
    grad = k.grad  # (P, K, d)
    mass = torch.zeros(n, dtype=w.dtype).index_add_(0, idx.reshape(-1), (w * state.mass[:, None]).reshape(-1))
    momentum = torch.zeros(n, d, dtype=w.dtype).index_add_(
        0, idx.reshape(-1), (w[..., None] * (state.mass[:, None] * state.v)[:, None, :]).reshape(-1, d))
    tau = kirchhoff_stress(model, state.F)
    f_slots = -state.volume0[:, None, None] * torch.einsum("pab,pkb->pka", tau, grad)
    force = torch.zeros(n, d, dtype=w.dtype).index_add_(0, idx.reshape(-1), f_slots.reshape(-1, d))
    active = mass > 1e-10 * state.mass.mean()
    safe = torch.where(active, mass, torch.ones_like(mass))[:, None]
    v_old = torch.where(active[:, None], momentum / safe, 0.0)
    v_new = torch.where(active[:, None], v_old + dt * (force / safe + model.gravity), 0.0)
    v_new = apply_conditions(v_new.T.contiguous(), model.conditions).T
    vn, dv = v_new[idx], (v_new - v_old)[idx]  # (P, K, d)
    x = state.x + dt * (w[..., None] * vn).sum(1)
    v = state.v + (w[..., None] * dv).sum(1)
    grad_v = torch.einsum("pka,pkb->pab", vn, grad)
    return replace(state, x=x, v=v, F=state.F + dt * grad_v @ state.F, cell=k.cell, time=state.time + dt,
                   step=state.step + 1)


def test_eulerian_mode_is_the_plain_umls_solver():
    config = {"scene": "rotating_plate", "solver": {"reference": "eulerian", "transfer": "flip"},
              "output": {"frames": 2}}
    traj = datagen.simulate(config)
    sim = build_simulation(config)
    state = sim.state
    for _ in range(2 * sim.substeps):
        state = _plain_umls_flip(sim.model, state, sim.dt)
    # summation order differs between the two: measured 1.5e-14 m (box 1 m) and 1.7e-13 of the speed (~20 m/s)
    speed = np.abs(traj.velocities[-1]).max()
    np.testing.assert_allclose(traj.positions[-1], state.x.numpy(), rtol=0, atol=1.5e-13)
    np.testing.assert_allclose(traj.velocities[-1], state.v.numpy(), rtol=0, atol=1.5e-12 * speed)
    assert np.abs(traj.positions[-1] - traj.positions[0]).max() > 0.05  # the plate really turned
    assert traj.kernel_rebuilds == 2 * sim.substeps  # one kernel per step


def test_adaptive_rebuilding_every_step_is_eulerian():
    """s = n recovers EMPM (A-ULMPM §5.3.4): with a criterion every step meets, the reference
    machinery (F^{0s}, F^{sn}, moved nodes, wall planes) gives the eulerian run."""
    runs = {ref: datagen.simulate({"scene": "stretched_bar", "solver": {"reference": ref, **extra},
                                   "output": {"frames": 2}})
            for ref, extra in (("eulerian", {}), ("adaptive", {"epsilon": 1e-300, "fraction": 1e-9}))}
    steps = 2 * runs["eulerian"].substeps
    assert runs["adaptive"].kernel_rebuilds == steps == runs["eulerian"].kernel_rebuilds
    # measured 2.2e-16 m and 8.4e-15 m/s (speeds up to 2.4 m/s)
    np.testing.assert_allclose(runs["adaptive"].positions, runs["eulerian"].positions, rtol=0, atol=2e-15)
    np.testing.assert_allclose(runs["adaptive"].velocities, runs["eulerian"].velocities, rtol=0, atol=8e-14)


def _clamped_block(transfer: str, reference: str, mirrors: bool = True, **options):
    """A prestrained, randomly moving block against a sticky wall at x = 0 whose extra-layer nodes are
    folded mirror ghosts, under gravity; the walls act by node index (no wall planes) in every mode."""
    domain = shapes.rectangle(1.0, 1.0, 0.1)
    extended = with_extra_layer(domain)
    tables = MeshTables.build(extended)
    conditions = mesh_conditions(domain, extended, [Wall("sticky", lambda c, n: n[:, 0] < -0.5)], [])
    assert isinstance(conditions[-1], Mirror) and conditions[-1].wall is not None
    if not mirrors:
        conditions = [c for c in conditions if not isinstance(c, Mirror)]
    model = Model(tables, "umls", transfer, ((NeoHookean(1e3, 0.3, 1.0), None),), tuple(conditions),
                  torch.tensor([0.0, -9.81], dtype=torch.float64), tables.nodes, 0.05, reference=reference, **options)
    x, _, spacing = lattice([0.0, 0.3], [0.3, 0.7], 0.025)
    rng = np.random.default_rng(0)
    state = State.at_rest_shape(x, 0.3 * rng.standard_normal(x.shape), np.full(len(x), np.prod(spacing)), 1.0)
    F = torch.eye(2, dtype=torch.float64) + 0.02 * torch.tensor(rng.standard_normal((len(x), 2, 2)))
    return model, replace(state, F=F)


@pytest.mark.parametrize("transfer", ["flip", "pic", "apic", "musl"])
def test_every_engine_folds_and_applies_the_mirror_ghosts(transfer):
    """One nodal update for every engine: a total-mode step (fixed sparse operators for FLIP, PIC and
    APIC, the slot path for MUSL) from s = n is the eulerian step, sticky-wall mirror ghosts included,
    to round-off (measured: x equal, v 1.1e-16, F 2.2e-16, B 2.6e-18). Without the mirrors the step
    differs by 1.6e-2 to 5.9e-2 m/s, so the comparison sees them (the operators once skipped them)."""
    eulerian, state = _clamped_block(transfer, "eulerian")
    total, _ = _clamped_block(transfer, "total")
    a, b = step(eulerian, state, 1e-3), step(total, state, 1e-3)
    np.testing.assert_allclose(b.x.numpy(), a.x.numpy(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(b.v.numpy(), a.v.numpy(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(b.F.numpy(), a.F.numpy(), rtol=0, atol=2e-15)
    np.testing.assert_allclose(b.affine.numpy(), a.affine.numpy(), rtol=0, atol=2.5e-17)
    unmirrored, _ = _clamped_block(transfer, "eulerian", mirrors=False)
    assert float((step(unmirrored, state, 1e-3).v - a.v).abs().max()) > 1e-2


def test_nodal_update_folds_ghost_sums_and_mirrors_both_velocities():
    """The nodal update every engine shares: the P2G sums of the mirror ghosts are folded onto the nodes
    they mirror (ghosts carry no mass, the total mass is kept), and the ghosts' velocities before and
    after the update are both the mirror images of their sources' (so FLIP's increment is too)."""
    model, state = _clamped_block("flip", "eulerian")
    mirror = model.conditions[-1]
    k = compute_kernel(model, state.x)
    grid = nodal_update(model, state, k, p2g_plain(model, state, k), 1e-3)
    assert float(grid.mass[mirror.ghosts].abs().max()) == 0.0
    assert float(grid.mass.sum()) == pytest.approx(float(state.mass.sum()), rel=1e-14)
    touched = grid.v[:, mirror.sources].abs().amax(dim=(0, 2)) > 0
    assert touched.float().mean() > 0.5  # the block reaches most ghosts' sources (measured 9 of 11)
    for v in (grid.v, grid.v_new):
        mirrored = -(v[:, mirror.sources] * mirror.weights).sum(-1)
        np.testing.assert_allclose(v[:, mirror.ghosts].numpy(), mirrored.numpy(), rtol=0, atol=1e-15)
    assert float(grid.v_new[:, mirror.wall].abs().max()) == 0.0  # the sticky wall itself


@pytest.mark.parametrize("transfer", ["flip", "pic", "musl"])
def test_adaptive_rebuilding_every_step_folds_mirrors_like_eulerian(transfer):
    """30 steps against the mirrored sticky wall, the reference rebuilt every step: the eulerian run to
    round-off (measured 2.2e-16 m, 1.6e-14 m/s, 2.0e-15 in F at most)."""
    eulerian, a = _clamped_block(transfer, "eulerian")
    adaptive, b = _clamped_block(transfer, "adaptive", epsilon=1e-300, fraction=1e-9)
    for _ in range(30):
        a, b = step(eulerian, a, 1e-3), step(adaptive, b, 1e-3)
    assert kernel_rebuilds(b) == 30
    np.testing.assert_allclose(b.x.numpy(), a.x.numpy(), rtol=0, atol=2e-15)
    np.testing.assert_allclose(b.v.numpy(), a.v.numpy(), rtol=0, atol=1.5e-13)
    np.testing.assert_allclose(b.F.numpy(), a.F.numpy(), rtol=0, atol=2e-14)


def test_strain_criterion_is_a_ulmpm_eq_33():
    """delta J_p = |det F^{s,n+1}_p - 1| >= epsilon marks a particle; the reference is updated when the
    marked fraction reaches eta (``fraction``). Rotations and isochoric shears mark nothing."""
    eye = torch.eye(2, dtype=torch.float64)
    c, s_ = np.cos(1.2), np.sin(1.2)
    rotation = torch.tensor([[c, -s_], [s_, c]], dtype=torch.float64)
    shear = torch.tensor([[1.0, 0.9], [0.0, 1.0]], dtype=torch.float64)
    Fsn = torch.stack([rotation, shear, 1.02 * eye, 0.99 * eye, eye])  # delta J = 0, 0, 0.0404, 0.0199, 0
    assert not strain_criterion(Fsn[:2], 1e-12, 1e-9)  # rigid rotation and isochoric shear: no marks
    assert strain_criterion(Fsn, 0.019, 0.4) and not strain_criterion(Fsn, 0.021, 0.4)  # 2 of 5 marked, 1 of 5
    assert not strain_criterion(Fsn, 0.019, 0.41)  # 2 of 5 reach a fraction of 0.4, not more
    by_component = linalg.matrices(linalg.components(Fsn).contiguous())  # the layout the reference step keeps
    assert strain_criterion(by_component, 0.04, 0.2) and not strain_criterion(by_component, 0.041, 0.2)


def test_adaptive_with_unreachable_epsilon_is_total():
    short = {"output": {"frames": 4}}
    total = datagen.simulate({"scene": "rotating_plate", "solver": {"reference": "total"}, **short})
    adaptive = datagen.simulate({"scene": "rotating_plate", "solver": {"reference": "adaptive", "epsilon": 1e9}, **short})
    assert total.kernel_rebuilds == adaptive.kernel_rebuilds == 1
    assert np.array_equal(total.positions, adaptive.positions)
    assert np.array_equal(total.velocities, adaptive.velocities)


# ----------------------------------------------------------------------------- 2. rigid motion
def _block(velocity, reference="adaptive", **options):
    """A 0.3 x 0.2 Neo-Hookean block in a 2 x 2 box (walls far away), no gravity."""
    x, _, spacing = lattice([0.5, 0.8], [0.8, 1.0], 0.025)
    tables = MeshTables.build(with_extra_layer(shapes.rectangle(2.0, 2.0, 0.05)))
    model = Model(tables, "umls", "flip", ((NeoHookean(200.0, 0.3, 1.0), None),), (),
                  torch.zeros(2, dtype=torch.float64), tables.nodes, 0.04, reference=reference, **options)
    v = velocity(torch.as_tensor(x))
    return model, State.at_rest_shape(x, v, np.full(len(x), np.prod(spacing)), 1.0)


def test_rigid_translation_and_rotation_trigger_no_rebuild():
    centre = torch.tensor([0.65, 0.9], dtype=torch.float64)
    omega, drift = 4.0, torch.tensor([1.0, 0.5], dtype=torch.float64)

    def rigid(x):
        r = x - centre
        return drift + omega * torch.stack([-r[:, 1], r[:, 0]], 1)

    model, state = _block(rigid)
    x0 = state.x.clone()
    dt = 7e-4
    for _ in range(500):
        state = step(model, state, dt)
    assert kernel_rebuilds(state) == 1  # the initial kernel only: zero updates
    moved = (state.x.mean(0) - x0.mean(0)).norm()
    assert moved > 6 * model.cell_size  # it travelled many cells (measured 6.5) ...
    r0, r1 = x0[0] - x0.mean(0), state.x[0] - state.x.mean(0)
    turned = torch.atan2(r0[0] * r1[1] - r0[1] * r1[0], r0 @ r1)
    assert turned > 1.0  # ... and turned by more than 57 degrees (measured 1.1 rad)
    assert float((linalg.det(state.F) - 1).abs().max()) < 0.01  # and stayed rigid (measured 4.1e-3)


def test_a_deforming_block_does_trigger_updates():
    centre = torch.tensor([0.65, 0.9], dtype=torch.float64)
    model, state = _block(lambda x: -3.0 * (x - centre))  # squeezed towards its centre
    for _ in range(100):
        state = step(model, state, 7e-4)
    assert kernel_rebuilds(state) >= 10  # measured 20 in 100 steps


def test_contact_trigger_lets_approaching_bodies_collide():
    """Two blocks flying at each other: without the contact trigger (or in total mode) they share
    no nodes at s and pass through each other; with it the reference is updated before they
    meet and they collide."""
    def two_blocks(reference, margin):
        xa, _, spacing = lattice([0.3, 0.9], [0.5, 1.1], 0.025)
        xb = xa + np.array([0.5, 0.0])
        x = np.concatenate([xa, xb])
        v = np.zeros_like(x)
        v[: len(xa), 0], v[len(xa):, 0] = 1.5, -1.5
        tables = MeshTables.build(with_extra_layer(shapes.rectangle(2.0, 2.0, 0.05)))
        model = Model(tables, "umls", "flip", ((NeoHookean(200.0, 0.3, 1.0), None),), (),
                      torch.zeros(2, dtype=torch.float64), tables.nodes, 0.04, reference=reference,
                      contact_margin=margin)
        return model, State.at_rest_shape(x, v, np.full(len(x), np.prod(spacing)), 1.0), len(xa)

    results = {}
    for name, reference, margin in (("trigger", "adaptive", 1.0), ("no trigger", "adaptive", None),
                                    ("total", "total", 1.0)):
        model, state, n_a = two_blocks(reference, margin)
        for _ in range(250):  # 0.175 s: at 1.5 m/s each, the 0.3 gap closes after 0.1 s
            state = step(model, state, 7e-4)
        results[name] = (float(state.v[:n_a, 0].mean()), state.reference.contact_rebuilds)
    assert results["trigger"][1] > 0 and results["trigger"][0] < -0.5  # they hit and bounced back (measured -1.14)
    # free flight keeps the velocity to round-off (measured exactly)
    assert results["no trigger"][1] == 0 and results["no trigger"][0] == pytest.approx(1.5, abs=1e-13)
    assert results["total"][0] == pytest.approx(1.5, abs=1e-13)


# ----------------------------------------------------------------------------- 3. numerical fracture
def test_stretched_bar_tears_in_eulerian_mode_only(scene_runs):
    """Measured: every mode pulled to 2.11x its length; eulerian tears (3.5% of edges longer than two
    cells) and stays 110% too long after release, total and adaptive spring back to within 0.44% and
    2.2% with 1 and 2 kernels against 560."""
    runs = scene_runs("stretched_bar")
    p = runs["total"].config["params"]
    released = runs["total"].times > p["release_time"] + 0.25  # the damped bar settles within 0.25 s
    assert released.sum() >= 3
    recovers = {"total": 0.01, "adaptive": 0.05}
    for mode, traj in runs.items():
        length = bar_length(p, traj.positions)
        rest = length[0]
        error = np.abs(length[released] - rest).max() / rest
        peak = length.max() / rest
        assert peak > 1.9  # every mode was pulled to about twice its length
        if mode == "eulerian":
            assert fracture(traj).max() > 0.01
            assert error > 0.5, f"{mode} bar recovered its rest length ({error:.3f})"
        else:
            assert fracture(traj).max() == 0
            assert error < recovers[mode], f"{mode} bar did not recover its rest length ({error:.3f})"
    assert runs["adaptive"].kernel_rebuilds < runs["eulerian"].kernel_rebuilds / 100


def test_rotating_plate_tears_in_eulerian_mode_only(scene_runs):
    runs = scene_runs("rotating_plate")  # measured: 7.0% of edges torn in eulerian mode, 17 kernels against 680
    assert fracture(runs["eulerian"]).max() > 0.03
    assert fracture(runs["total"]).max() == 0
    assert fracture(runs["adaptive"]).max() == 0
    assert 1 < runs["adaptive"].kernel_rebuilds < runs["eulerian"].kernel_rebuilds / 20


# ----------------------------------------------------------------------------- 4. droplet
def test_droplet_adaptive_rebuilds_rarely_and_follows_eulerian(scene_runs):
    runs = scene_runs("droplet")
    eul = runs["eulerian"].diagnostics["center_of_mass"]
    scale = np.linalg.norm(eul - eul[0], axis=1).max()  # how far the eulerian centre of mass travels
    error = {m: np.linalg.norm(t.diagnostics["center_of_mass"] - eul, axis=1).max() / scale for m, t in runs.items()}
    solver = runs["adaptive"].config["solver"]
    assert (solver["epsilon"], solver["fraction"], solver["contact_margin"]) == (0.01, 0.01, None)
    # measured: 728 kernels against 56, errors 1.05% (adaptive) and 13.7% (total), lowest vertex 3.2 mm up
    assert runs["eulerian"].kernel_rebuilds >= 4 * runs["adaptive"].kernel_rebuilds
    assert error["adaptive"] < 0.02
    assert error["total"] > 0.07
    assert runs["total"].positions[:, :, 1].min() > 0.0  # walls act on the moved nodes: nothing fell through
    frames_rebuilds = runs["adaptive"].diagnostics["kernel_rebuilds"]
    assert frames_rebuilds[-1] == runs["adaptive"].kernel_rebuilds and np.all(np.diff(frames_rebuilds) >= 0)


# ----------------------------------------------------------------------------- materials and config
@pytest.mark.parametrize("gamma", [1.0, 7.0])
def test_fluid_stress_is_the_energy_gradient_and_a_pressure(gamma):
    fluid = WeaklyCompressibleFluid(300.0, 0.0, 1.0, gamma=gamma)
    g = torch.Generator().manual_seed(0)
    F = (torch.eye(2, dtype=torch.float64) + 0.1 * torch.randn(8, 2, 2, generator=g, dtype=torch.float64))
    F.requires_grad_(True)
    (dpsi,) = torch.autograd.grad(fluid.energy_density(F).sum(), F)
    with torch.no_grad():  # stresses ~30 Pa: measured 1.7e-14
        np.testing.assert_allclose(fluid.first_piola(F).numpy(), dpsi.numpy(), rtol=0, atol=1.5e-13)
        tau = fluid.kirchhoff(F)
        J = linalg.det(F)
        assert float(tau[:, 0, 1].abs().max()) == 0.0  # no shear stress
        compressed = J < 1
        assert bool((tau[compressed, 0, 0] < 0).all()) and bool((tau[~compressed, 0, 0] > 0).all())
    assert fluid.wave_speed == pytest.approx(10.0)  # K = E / 3 = 100


def test_viscosity_damps_a_shear_flow():
    def shear_energy(viscosity):
        x, _, spacing = lattice([0.3, 0.3], [0.7, 0.7], 0.025)
        tables = MeshTables.build(with_extra_layer(shapes.rectangle(1.0, 1.0, 0.05)))
        fluid = WeaklyCompressibleFluid(300.0, 0.0, 1.0, fluid_viscosity=viscosity)
        model = Model(tables, "umls", "apic", ((fluid, None),), (), torch.zeros(2, dtype=torch.float64),
                      tables.nodes, 0.04)
        v = np.stack([np.sin(2 * np.pi * (x[:, 1] - 0.3) / 0.4), np.zeros(len(x))], 1)
        state = State.at_rest_shape(x, v, np.full(len(x), np.prod(spacing)), 1.0)
        for _ in range(60):
            state = step(model, state, 1e-3)
        return float((state.mass * (state.v ** 2).sum(1)).sum())

    # Measured 0.768. The analytic decay exp(-2 nu k^2 t) = 0.23 of a periodic shear wave does not apply:
    # 8 cells per wavelength smooth the velocity gradient to about half (its dissipation to a quarter).
    assert 0.7 < shear_energy(0.05) / shear_energy(0.0) < 0.8


@pytest.mark.parametrize(("key", "value"), [("reference", "lagrangian"), ("epsilon", -1.0), ("fraction", 1.5),
                                            ("fraction", 0), ("contact_margin", "far"), ("contact_margin", -1)])
def test_bad_reference_options_name_the_key(key, value):
    with pytest.raises(ConfigError, match=f"solver.{key}"):
        datagen.simulate({"scene": "droplet", "solver": {key: value}})
