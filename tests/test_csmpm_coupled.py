"""CSMPM's gas-solid coupling (datagen.csmpm.coupled): MPM particles on the gas grid and one
pressure solve for both phases."""

import math

import numpy as np
import pytest

import datagen
from datagen import shapes
from datagen.config import ConfigError
from datagen.csmpm import coupled, coupled_scenes, euler, gas
from datagen.mpm.materials import NeoHookean
from datagen.mpm.plasticity import J2Softening


def _slab(lo: float, hi: float, dx: float, material, p0: float, per_cell: int = 4) -> coupled.Solid:
    """A 1D solid slab [lo, hi] of ``per_cell`` particles per cell."""
    x = np.arange(lo + dx / per_cell / 2, hi, dx / per_cell)[:, None]
    n = len(x)
    return coupled.Solid(x=x, v=np.zeros((n, 1)), C=np.zeros((n, 1, 1)), F=np.ones((n, 1, 1)),
                         volume=np.full(n, dx / per_cell), mass=np.full(n, material.density * dx / per_cell),
                         Jg=np.ones(n), material=material, ghost=material.lam, p0=p0)


def _box(n: int) -> euler.Grid:
    return euler.Grid((n, n), 1.0 / n, (("wall", "wall"), ("wall", "wall")))


def _totals(state, solid, dx):
    cell = dx ** (state.ndim - 1)
    return (state[0].sum() * cell, state[1:-1].reshape(state.shape[0] - 2, -1).sum(1) * cell + solid.momentum,
            state[-1].sum() * cell + coupled.solid_energy(solid))


def test_the_blocked_fraction_is_the_ball_of_the_solid_volume():
    dx = 0.1
    # 2D: a disk of diameter half a cell blocks half a face; a full cell blocks all of it
    assert coupled.blocked_fraction(np.array(math.pi * 0.025 ** 2), dx, 2) == pytest.approx(0.5, rel=1e-14)
    assert coupled.blocked_fraction(np.array(dx * dx), dx, 2) == 1.0
    # 3D: a ball's cross-section over the face's area
    r = 0.04
    assert coupled.blocked_fraction(np.array(4 / 3 * math.pi * r ** 3), dx, 3) == pytest.approx(math.pi * r * r / dx ** 2,
                                                                                               rel=1e-14)
    np.testing.assert_array_equal(coupled.blocked_fraction(np.array([0.0, 0.03, 0.2]), dx, 1), [0.0, 0.3, 1.0])


@pytest.mark.parametrize("outlet", euler.OUTLETS)
def test_without_a_solid_the_coupled_step_is_the_gas_step(outlet):
    """Also with outlets coupled to the far field (the top and right ends), on a random state
    whose outflow is partly subsonic, partly supersonic."""
    n = 24
    inflow = gas.conserved(np.array(1.4), np.array([3.0, 0.0]), np.array(1.0))
    grid = euler.Grid((n, n), 1.0 / n, (("inlet", "open"), ("wall", "open")), inflow=inflow, outlet=outlet,
                      attenuation=0.5, outflow=gas.conserved(np.array(1.0), np.array([0.5, 0.0]), np.array(1.0)))
    rng = np.random.default_rng(0)
    state = gas.conserved(rng.uniform(0.5, 2, (n, n)), rng.normal(0, 1, (2, n, n)), rng.uniform(0.5, 2, (n, n)))
    material = NeoHookean(E=1e3, nu=0.3, density=2.0)
    empty = coupled.Solid(x=np.zeros((0, 2)), v=np.zeros((0, 2)), C=np.zeros((0, 2, 2)), F=np.zeros((0, 2, 2)),
                          volume=np.zeros(0), mass=np.zeros(0), Jg=np.zeros(0), material=material, ghost=material.lam)
    dt = 0.3 / n / 5
    a, _, info = coupled.step(state, empty, grid, dt)
    b, gas_info = euler.step(state, grid, dt)
    assert np.abs(a - b).max() <= 4e-15
    assert info.cg_iterations == gas_info.cg_iterations


def test_a_body_at_rest_in_still_gas_stays_at_rest():
    n = 24
    grid = _box(n)
    solid = coupled.Solid.from_mesh(shapes.disk(0.15, 0.5 / n, center=(0.5, 0.5)),
                                    NeoHookean(E=100.0, nu=0.3, density=5.0), p0=1.0)
    state = gas.conserved(np.ones(grid.shape), np.zeros((2, n, n)), np.ones(grid.shape))
    start = state.copy()
    for _ in range(5):
        state, solid, info = coupled.step(state, solid, grid, coupled.time_step(state, solid, grid))
    assert np.abs(solid.v).max() == 0.0 and np.abs(solid.Jg - 1.0).max() == 0.0
    assert np.abs(state - start).max() == 0.0
    assert info.solid_cells.sum() > 0


def _struck_box(solid, n: int, steps: int):
    """A closed box of n cells per side (the solid's dimension): gas at 4x the pressure and 2x the
    density on the left quarter, at rest, striking ``solid`` for ``steps`` steps. -> (solid after,
    gas mass before and after, the largest per-step difference between the momentum change of gas
    and solid together and the walls' pressure impulse, the largest relative energy drift, CG
    iterations per step, the solid's mean displacement)."""
    d, dx = solid.x.shape[1], 1.0 / n
    grid = euler.Grid((n,) * d, dx, (("wall", "wall"),) * d)
    left = np.broadcast_to((((np.arange(n) + 0.5) * dx) < 0.25).reshape((n,) + (1,) * (d - 1)), (n,) * d)
    state = gas.conserved(np.where(left, 2.0, 1.0), np.zeros((d,) + (n,) * d), np.where(left, 4.0, 1.0))
    mass0, momentum, energy0 = _totals(state, solid, dx)
    worst, drift, iterations, start = 0.0, 0.0, [], solid.x.mean(axis=0)
    for _ in range(steps):
        dt = coupled.time_step(state, solid, grid)
        state, solid, info = coupled.step(state, solid, grid, dt)
        p = info.pressure
        wall = -dt * dx ** (d - 1) * np.array([np.take(p, -1, axis=a).sum() - np.take(p, 0, axis=a).sum()
                                               for a in range(d)])
        mass, now, energy = _totals(state, solid, dx)
        worst = max(worst, float(np.abs(now - momentum - wall).max()))
        drift = max(drift, abs(energy / energy0 - 1.0))
        momentum = now
        iterations.append(info.cg_iterations)
    return solid, mass0, mass, worst, drift, iterations, solid.x.mean(axis=0) - start


@pytest.mark.parametrize("material", [NeoHookean(E=200.0, nu=0.3, density=3.0),
                                      J2Softening(E=200.0, nu=0.3, density=3.0, kappa_peak=0.3, kappa_residual=0.1,
                                                  eta=1.0)], ids=["elastic", "plastic"])
def test_a_shock_pushes_a_body_conserving_mass_and_balancing_momentum(material):
    """A closed box: gas at 4x the pressure on the left quarter hits a disk. Mass is conserved to
    round-off; each step the momentum of gas and solid together changes by exactly the walls'
    pressure impulse; energy (gas, solid kinetic and elastic) drifts by little."""
    n = 32
    solid = coupled.Solid.from_mesh(shapes.disk(0.12, 0.5 / n, center=(0.55, 0.5)), material, p0=1.0)
    solid, mass0, mass, worst, drift, iterations, moved = _struck_box(solid, n, 150)
    assert mass == pytest.approx(mass0, rel=1e-15, abs=0.0)
    assert worst <= 1e-15
    assert drift <= 2e-3
    assert max(iterations) <= 12
    assert moved[0] > 0.02 and abs(moved[1]) < 1e-2 * moved[0], "pushed to the right, not sideways"
    assert solid.momentum[0] > 0.3 * solid.mass.sum()
    if solid.plastic_strain is not None:
        assert solid.plastic_strain.max() > 0.0, "the weak disk yields"


def test_a_slab_between_two_pressures_moves_as_an_acoustic_piston():
    """A heavy slab (mass M per area) between gas at p + dp and p: while its speed U is small
    against the sound speeds, M dU/dt = dp - Z U with Z = rho_l c_l + rho_r c_r (each side's
    acoustic impedance), so U = dp / Z (1 - exp(-Z t / M))."""
    n = 200
    dx = 1.0 / n
    grid = euler.Grid((n,), dx, (("wall", "wall"),))
    material = NeoHookean(E=1e4, nu=0.3, density=20.0)
    solid = _slab(0.45, 0.55, dx, material, p0=1.5)
    x = (np.arange(n) + 0.5) * dx
    state = gas.conserved(np.ones(n), np.zeros((1, n)), np.where(x < 0.5, 2.0, 1.0))
    mass = solid.mass.sum()
    impedance = 1.0 * gas.sound_speed(1.0, 2.0) + 1.0 * gas.sound_speed(1.0, 1.0)
    t, errors = 0.0, []
    for _ in range(300):
        dt = coupled.time_step(state, solid, grid, 0.4)
        state, solid, _ = coupled.step(state, solid, grid, dt)
        t += dt
        exact = 1.0 / impedance * (1.0 - math.exp(-impedance * t / mass))
        errors.append(solid.momentum[0] / mass / exact - 1.0)
    assert max(abs(e) for e in errors) <= 0.02


def test_lifting_cylinder_runs_through_simulate_and_the_shock_carries_it_downstream():
    t = datagen.simulate({"scene": "lifting_cylinder", "params": {"cells": 50},
                          "output": {"frames": 3, "frame_interval": 0.03}})
    nx, ny = 50, 10
    assert t.fields["x"].shape == (nx * ny, 2) and t.fields["density"].shape == (4, nx * ny)
    assert t.fields["velocity"].shape == (4, nx * ny, 2) and t.fields["solid"].shape == (4, nx * ny)
    assert t.positions.shape == (4, t.mesh.n_nodes, 2)
    centre = t.diagnostics["centre"]
    assert np.all(np.diff(centre[:, 0]) > 0) and centre[-1, 0] - centre[0, 0] > 0.06, "carried downstream"
    assert centre[-1, 1] > centre[0, 1] + 1e-3, "and lifted off the floor"
    assert t.fields["solid"][1:].sum(1).min() > 10 and max(t.diagnostics["cg_iterations"]) <= 12
    # behind the shock the inlet holds the Rankine-Hugoniot state of Mach 3 into (1.4, 1): (5.4, 2.222, 10.333)
    rho, u, p = coupled_scenes.shock_state(3.0, 1.4, 1.0)
    assert (rho, u, p) == pytest.approx((5.4, 20.0 / 9.0, 31.0 / 3.0), rel=1e-14)
    with pytest.raises(ConfigError, match="must put the cylinder inside the channel"):
        datagen.simulate({"scene": "lifting_cylinder", "params": {"centre": [0.15, 0.18]}})
    with pytest.raises(ConfigError, match="must be > 1 \\(a shock\\)"):
        datagen.simulate({"scene": "lifting_cylinder", "params": {"mach": 0.5}})


def test_shell_explosion_blows_the_ring_outwards_and_keeps_the_gas():
    t = datagen.simulate({"scene": "shell_explosion", "params": {"cells": 64, "radius": [0.1, 0.16]},
                          "output": {"frames": 2, "frame_interval": 0.015}})
    radius = np.hypot(*(t.positions - 0.5).transpose(2, 0, 1))  # (frames + 1, nodes)
    inner = radius.min(axis=1)
    assert inner[0] == pytest.approx(0.1, abs=1e-9) and inner[-1] > inner[1] > 0.1 + 0.01, "blown outwards"
    mass = t.diagnostics["mass"]
    assert np.abs(mass - mass[0]).max() <= 1e-14 * mass[0], "walls all round: the gas's mass is kept to round-off"
    momentum = t.diagnostics["momentum"][-1]
    scale = float((t.velocities[-1] ** 2).sum(1).max()) ** 0.5 * 1.0 * math.pi * (0.16 ** 2 - 0.1 ** 2)
    assert np.abs(momentum).max() <= 2e-3 * scale, "a symmetric blast leaves the ring's momentum near zero"


def test_bullet_leaves_the_barrel_along_its_axis():
    t = datagen.simulate({"scene": "bullet", "params": {"cells": 50}, "output": {"frames": 2, "frame_interval": 0.04}})
    centre = t.diagnostics["centre"]
    assert centre[-1, 0] - centre[0, 0] > 0.05 and np.all(np.diff(centre[:, 0]) > 0)
    assert abs(centre[-1, 1] - 0.5) < 2e-4, "guided by the barrel"
    assert t.diagnostics["momentum"][-1, 0] > 0
    with pytest.raises(ConfigError, match="must fit the bullet in the bore"):
        datagen.simulate({"scene": "bullet", "params": {"bullet": [0.2, 0.2]}})
    with pytest.raises(ConfigError, match="leaves the solid under 3 cells across"):
        datagen.simulate({"scene": "shell_explosion", "params": {"cells": 32}})


def test_the_coupling_runs_in_3d_conserving_mass_and_balancing_momentum():
    """The same box in 3D (16^3 cells, a tetrahedral ball of 1,078 particles), 60 steps: mass
    exact, gas and solid momentum together change by the walls' pressure impulse (4.5e-17 per
    step, measured), energy drifts 1.1e-6, the ball is pushed along x and not sideways."""
    n = 16
    solid = coupled.Solid.from_mesh(shapes.sphere(0.15, 0.5 / n, center=(0.55, 0.5, 0.5)),
                                    NeoHookean(E=1e3, nu=0.3, density=2.0), p0=1.0)
    _, mass0, mass, worst, drift, iterations, moved = _struck_box(solid, n, 60)
    assert mass == pytest.approx(mass0, rel=1e-15, abs=0.0)
    assert worst <= 4e-16 and drift <= 1e-5 and max(iterations) <= 10
    assert moved[0] > 1e-4 and np.abs(moved[1:]).max() < 1e-3 * moved[0]
