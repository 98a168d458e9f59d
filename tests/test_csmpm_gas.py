"""CSMPM's gas (datagen.csmpm): EOS, the exact Riemann solution, WENO-LLF advection with the
semi-implicit pressure, and the shock_tube scene through datagen.simulate."""

import math
import re

import numpy as np
import pytest
import scipy.sparse as sp

import datagen
from datagen.config import ConfigError
from datagen.csmpm import b2b1, euler, gas

SOD = ((1.0, 0.0, 1.0), (0.125, 0.0, 0.1))


def test_the_ideal_gas_round_trips_and_sounds_like_air():
    rng = np.random.default_rng(0)
    rho, u, p = rng.uniform(0.1, 2, 50), rng.normal(0, 3, (2, 50)), rng.uniform(0.1, 5, 50)
    state = gas.conserved(rho, u, p)
    back = gas.primitive(state)
    np.testing.assert_allclose(back[0], rho, rtol=1e-15)
    np.testing.assert_allclose(back[1], u, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(back[2], p, rtol=1e-13)
    np.testing.assert_allclose(state[-1], p / 0.4 + 0.5 * rho * (u ** 2).sum(0), rtol=1e-15)  # rho E, gamma 1.4
    # air at sea level: 340.3 m/s
    assert gas.sound_speed(1.225, 101325.0) == pytest.approx(math.sqrt(1.4 * 101325.0 / 1.225), rel=1e-15)
    assert gas.sound_speed(1.225, 101325.0) == pytest.approx(340.294, abs=1e-3)


def test_the_exact_sod_solution_is_toros():
    x = np.linspace(0.0, 1.0, 1001)
    (rho, u, p), sol = gas.exact_riemann(*SOD, x, 0.2, interface=0.5)
    # Toro, table 4.2 / 4.3 (test 1): p* 0.30313, u* 0.92745, rho*L 0.42632, rho*R 0.26557
    assert (sol.p_star, sol.u_star) == pytest.approx((0.30313, 0.92745), abs=5e-6)
    assert (sol.rho_star_left, sol.rho_star_right) == pytest.approx((0.42632, 0.26557), abs=5e-6)
    assert sol.waves["right_shock"] == pytest.approx(1.75216, abs=5e-6)
    assert sol.waves["left_rarefaction_head"] == pytest.approx(-math.sqrt(1.4), rel=1e-15)
    # the star states hold between the waves, the fan is continuous at its ends
    star = (x > 0.5 + 0.2 * sol.waves["left_rarefaction_tail"] + 1e-3) & (x < 0.5 + 0.2 * sol.u_star - 1e-3)
    np.testing.assert_allclose(rho[star], sol.rho_star_left, rtol=1e-14)
    np.testing.assert_allclose(p[(x > 0.52) & (x < 0.85)], sol.p_star, rtol=1e-14)
    # left/right swapped and mirrored: the mirror image
    (rho2, u2, p2), _ = gas.exact_riemann(SOD[1], SOD[0], 1.0 - x, 0.2, interface=0.5)
    inside = np.abs(x - 0.5 - 0.2 * sol.waves["right_shock"]) > 1e-9
    np.testing.assert_allclose(rho2[inside], rho[inside], rtol=1e-12)
    np.testing.assert_allclose(u2[inside], -u[inside], rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="creates a vacuum"):
        gas.exact_riemann((1.0, -20.0, 1.0), (1.0, 20.0, 1.0), x, 0.1)


def _run(state, grid, t_end, cfl=0.5, acoustic=1.0, step=euler.step):
    t, iterations = 0.0, []
    while t < t_end - 1e-12:
        dt = min(euler.time_step(state, grid, cfl, acoustic), t_end - t)
        state, info = step(state, grid, dt)
        t += dt
        iterations.append(info.cg_iterations)
    return state, iterations


def test_a_constant_state_stays_constant():
    for shape in ((40,), (12, 9)):
        grid = euler.Grid(shape, 0.05, (("open", "open"),) * len(shape))
        velocity = np.stack([np.full(shape, 0.7 - 0.9 * a) for a in range(len(shape))])
        state = gas.conserved(np.full(shape, 1.3), velocity, np.full(shape, 2.1))
        after, _ = _run(state, grid, 0.3)
        assert np.abs(after - state).max() <= 1e-14 * np.abs(state).max()


def test_weno_converges_at_third_order_on_a_smooth_profile():
    """A density bump carried by a uniform flow (a contact: the exact solution is the bump moved)."""
    def error(n):
        dx = 1.0 / n
        x = (np.arange(n) + 0.5) * dx
        bump = lambda x: 1.0 + 0.5 * np.exp(-((x - 0.4) / 0.08) ** 2)  # noqa: E731
        state = gas.conserved(bump(x), np.ones((1, n)), np.ones(n))
        grid = euler.Grid((n,), dx, (("open", "open"),))
        t = 0.0
        while t < 0.2 - 1e-12:
            dt = min(0.4 * dx, 0.2 - t)
            state, _ = euler.step(state, grid, dt)
            t += dt
        return np.abs(state[0] - bump(x - 0.2)).mean()

    e = [error(n) for n in (200, 400, 800)]
    orders = np.log2(np.array(e[:-1]) / np.array(e[1:]))
    assert orders[0] >= 2.2 and orders[1] >= 2.9, orders  # measured 2.37 and 3.12 (WENO3-JS nears 3)


def _crossing(x, values, level, start, stop):
    """x where ``values`` crosses ``level`` between x = start and x = stop (linear interpolation)."""
    inside = np.flatnonzero((x >= start) & (x <= stop))
    v = values[inside] - level
    k = inside[np.flatnonzero(np.sign(v[:-1]) != np.sign(v[1:]))[0]]
    return x[k] + (x[k + 1] - x[k]) * (level - values[k]) / (values[k + 1] - values[k])


@pytest.mark.parametrize("acoustic", [1.0, 0.25])
def test_sod_waves_are_where_the_exact_solution_puts_them(acoustic):
    """Each wave located by where the density crosses a level of it, numerical against exact
    (acoustic 0.25: steps 4x the explicit acoustic limit while the sound speed dominates)."""
    trajectory = datagen.simulate({"scene": "shock_tube", "params": {"cells": 400},
                                   "solver": {"acoustic": acoustic, "cfl": 0.5},
                                   "output": {"frames": 4, "frame_interval": 0.05}})
    x, rho = trajectory.fields["x"], trajectory.fields["density"][-1]
    assert trajectory.times[-1] == pytest.approx(0.2, rel=1e-14)
    fine = np.linspace(0.0, 1.0, 40001)
    (exact, _, _), sol = gas.exact_riemann(*SOD, fine, 0.2, interface=0.5)
    w = {k: 0.5 + 0.2 * v for k, v in sol.waves.items()}
    levels = {  # wave: (density level, search from, to)
        "right_shock": (0.5 * (sol.rho_star_right + 0.125), w["contact"] + 0.03, 1.0),
        "contact": (0.5 * (sol.rho_star_left + sol.rho_star_right), w["left_rarefaction_tail"] + 0.03,
                    w["right_shock"] - 0.03),
        "left_rarefaction_head": (0.98, 0.0, 0.5),
        "left_rarefaction_tail": (sol.rho_star_left + 0.02, w["left_rarefaction_head"], w["contact"] - 0.03),
    }
    offsets = {wave: (_crossing(x, rho, *where) - _crossing(fine, exact, *where)) * 400 for wave, where in levels.items()}
    limits = MEASURED_OFFSETS[acoustic]
    for wave, offset in offsets.items():
        assert abs(offset) <= limits[wave], (wave, offsets)


# |numerical - exact| crossing in cells at 400 cells; measured: shock -0.23 / -0.39, contact -0.82 / -1.46,
# rarefaction head -5.1 / -7.8 (the fan's kink smeared), tail +3.4 / +4.9 (acoustic 1 / 0.25)
MEASURED_OFFSETS = {1.0: {"right_shock": 0.5, "contact": 1.5, "left_rarefaction_head": 7.0, "left_rarefaction_tail": 5.0},
                    0.25: {"right_shock": 0.8, "contact": 2.5, "left_rarefaction_head": 11.0,
                           "left_rarefaction_tail": 7.0}}


def test_sod_converges_toward_the_exact_solution():
    errors = []
    for n in (100, 200, 400):
        t = datagen.simulate({"scene": "shock_tube", "params": {"cells": n},
                              "output": {"frames": 1, "frame_interval": 0.2}})
        (rho, _, _), _ = gas.exact_riemann(*SOD, t.fields["x"], 0.2, interface=0.5)
        errors.append(np.abs(t.fields["density"][-1] - rho).mean())
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert errors[-1] <= 0.0042 and np.all(orders >= 0.75), (errors, orders)  # measured 0.00384; 0.83, 0.79


def _circular_shock(n):
    dx = 2.0 / n
    c = (np.arange(n) + 0.5) * dx - 1.0
    x, y = np.meshgrid(c, c, indexing="ij")
    inside = x ** 2 + y ** 2 < 0.4 ** 2
    state = gas.conserved(np.where(inside, 1.0, 0.125), np.zeros((2, n, n)), np.where(inside, 1.0, 0.1))
    return state, euler.Grid((n, n), dx, (("wall", "wall"), ("wall", "wall")))


@pytest.mark.parametrize(("step", "most"), [(euler.step, 20), (b2b1.step, 10)], ids=["B1B0", "B2B1"])
def test_a_closed_box_keeps_its_mass_and_energy_and_a_symmetric_blast_stays_symmetric(step, most):
    state, grid = _circular_shock(48)
    after, iterations = _run(state, grid, 0.5, step=step)  # the shock reflects off the walls
    mass, energy = state[0].sum(), state[-1].sum()
    assert abs(after[0].sum() - mass) <= 1e-14 * mass and abs(after[-1].sum() - energy) <= 1e-14 * energy
    assert np.abs(after[1:3].sum(axis=(1, 2))).max() <= 1e-12, "the walls push alike from both sides"
    rho = after[0]
    for image in (rho[::-1], rho[:, ::-1], rho.T):
        assert np.abs(image - rho).max() <= 1e-13
    assert np.abs(after[1] + after[1][::-1]).max() <= 1e-13, "x momentum is odd in x"
    assert np.abs(after[1] - after[2].T).max() <= 1e-13, "and the y momentum its transpose"
    assert max(iterations) <= most  # measured 16 (B1B0), 8 (B2B1)


def test_the_pressure_matrix_is_symmetric_positive_definite():
    rng = np.random.default_rng(1)
    grid = euler.Grid((7, 5), 0.1, (("wall", "open"), ("wall", "wall")))
    density = rng.uniform(0.2, 3.0, grid.shape)
    laplacian = euler._laplacian(euler._face_coefficients(density, grid), grid)
    assert (laplacian - laplacian.T).count_nonzero() == 0
    eigen = np.linalg.eigvalsh(laplacian.toarray())
    assert abs(eigen[0]) <= 1e-12 * eigen[-1], "without the compressibility term: constants are its null space"
    matrix = (laplacian + sp.diags(rng.uniform(0.01, 0.1, density.size))).toarray()
    assert np.linalg.eigvalsh(matrix)[0] > 0


def test_shock_tube_takes_any_riemann_problem_and_refuses_bad_input():
    t = datagen.simulate({"scene": "shock_tube", "params": {"left": [1.0, 0.75, 1.0], "right": [0.125, 0.0, 0.1],
                                                            "cells": 64, "length": 2.0, "interface": 0.6},
                          "output": {"frames": 3, "frame_interval": 0.05}})
    assert set(t.fields) == {"x", "density", "velocity", "pressure"}
    assert t.fields["x"].shape == (64,) and all(t.fields[k].shape == (4, 64) for k in ("density", "velocity",
                                                                                        "pressure"))
    np.testing.assert_allclose(t.fields["x"], (np.arange(64) + 0.5) * 2.0 / 64, rtol=1e-15)
    np.testing.assert_allclose(t.times, [0.0, 0.05, 0.1, 0.15], rtol=1e-14)
    assert t.fields["velocity"][0, 0] == 0.75 and t.fields["pressure"][0, -1] == 0.1
    for params, message in (({"left": [1.0, 0.0]}, "'params.left' must be [density, velocity, pressure]"),
                            ({"right": [0.0, 0.0, 1.0]}, "'params.right' needs positive density and pressure"),
                            ({"interface": 1.5}, "'params.interface' must lie inside the tube"),
                            ({"cells": 4}, "'params.cells' must be an integer > 7"),
                            ({"boundaries": "periodic"}, "'params.boundaries' must be one of wall, open")):
        with pytest.raises(ConfigError, match=re.escape(message)):
            datagen.simulate({"scene": "shock_tube", "params": params})
    with pytest.raises(ConfigError, match="unknown"):
        datagen.simulate({"scene": "shock_tube", "solver": {"kernel": "umls"}})


def test_circular_shock_runs_through_simulate_on_a_triangulated_grid():
    t = datagen.simulate({"scene": "circular_shock", "params": {"cells": 16, "radius": 0.5},
                          "output": {"frames": 2, "frame_interval": 0.05}})
    assert t.fields["x"].shape == (256, 2) and t.fields["velocity"].shape == (3, 256, 2)
    assert t.fields["density"].shape == t.fields["pressure"].shape == (3, 256)
    assert t.mesh.n_nodes == 256 and len(t.mesh.cells) == 2 * 15 * 15
    np.testing.assert_allclose(t.mesh.cell_measures, (2.0 / 16) ** 2 / 2, rtol=1e-12)
    np.testing.assert_array_equal(t.positions[0], t.fields["x"])
    mass = t.diagnostics["mass"]
    assert np.abs(mass - mass[0]).max() <= 1e-14 * mass[0] and t.diagnostics["cg_iterations"][0] == 0
    inside = np.sum((t.fields["x"] - 1.0) ** 2, axis=1) < 0.25
    assert np.all(t.fields["pressure"][0][inside] == 1.0) and np.all(t.fields["pressure"][0][~inside] == 0.1)
    with pytest.raises(ConfigError, match=re.escape("'params.radius' must be less than half the box")):
        datagen.simulate({"scene": "circular_shock", "params": {"radius": 1.0}})
    with pytest.raises(ConfigError, match=re.escape("'params.inside' must be [density, pressure]")):
        datagen.simulate({"scene": "circular_shock", "params": {"inside": [1.0, 0.0, 1.0]}})


def test_a_uniform_inflow_passes_an_empty_channel_unchanged():
    inflow = gas.conserved(np.array(1.4), np.array([3.0, 0.5]), np.array(1.0))
    grid = euler.Grid((30, 10), 0.1, (("inlet", "open"), ("open", "open")), inflow=inflow)
    state = np.broadcast_to(inflow[:, None, None], (4, 30, 10)).copy()
    after, _ = _run(state, grid, 0.5)
    assert np.abs(after - state).max() <= 1e-14 * np.abs(state).max()
    with pytest.raises(ValueError, match="an inlet needs the inflow's conserved state"):
        euler.Grid((30, 10), 0.1, (("inlet", "open"), ("wall", "wall")))


def test_solid_cells_keep_their_state_and_the_box_its_mass_and_energy():
    state, grid = _circular_shock(40)
    x = (np.arange(40) + 0.5) / 20 - 1.0
    block = (np.abs(x)[:, None] < 0.2) & (np.abs(x - 0.6)[None, :] < 0.15)  # a block above the blast
    grid = euler.Grid(grid.shape, grid.dx, grid.boundaries, solid=block)
    after, iterations = _run(state, grid, 0.4)
    np.testing.assert_array_equal(after[:, block], state[:, block])
    gas_cells = ~block
    for k in (0, -1):
        total = state[k][gas_cells].sum()
        assert abs(after[k][gas_cells].sum() - total) <= 1e-14 * total
    rho = after[0]
    assert np.abs(rho - rho[::-1]).max() <= 1e-13, "the block is symmetric in x: so is the flow"
    assert np.abs(rho[:, 30] - rho[:, 10]).max() > 1e-3, "and it breaks the symmetry in y"
    assert np.all(after[0][gas_cells] > 0) and max(iterations) <= 25


def test_stair_flow_stagnates_at_the_pitot_pressure_on_the_step():
    """Mach 3 against the step's face: behind the bow shock the gas comes to rest at Rayleigh's
    pitot pressure, 12.06 x the inflow's (gamma 1.4)."""
    t = datagen.simulate({"scene": "stair_flow", "params": {"cells": 40},
                          "output": {"frames": 1, "frame_interval": 2.0}})
    x, p = t.fields["x"], t.fields["pressure"][-1]
    g, mach = 1.4, 3.0
    pitot = ((g + 1) ** 2 * mach ** 2 / (4 * g * mach ** 2 - 2 * (g - 1))) ** (g / (g - 1)) * (
        1 - g + 2 * g * mach ** 2) / (g + 1)
    assert pitot == pytest.approx(12.06, abs=0.01)
    corner = np.flatnonzero((np.abs(x[:, 0] - 0.5875) < 1e-9) & (np.abs(x[:, 1] - 0.0125) < 1e-9))
    assert len(corner) == 1 and abs(p[corner[0]] / pitot - 1) <= 0.03  # measured 2.1% low (cell centre dx/2 away)
    assert not np.any((x[:, 0] > 0.6) & (x[:, 1] < 0.2)), "the step's cells are not gas"
    with pytest.raises(ConfigError, match=re.escape("'params.step' [start, height] must lie inside the channel")):
        datagen.simulate({"scene": "stair_flow", "params": {"step": [0.6, 1.2]}})


def _conserved(rho, u, p):
    return np.stack([rho, rho * u, p / (gas.GAMMA - 1.0) + 0.5 * rho * u * u])


def _run_outlet(state, outlet, seconds, boundaries=("wall", "open"), attenuation=1.0):
    """A 1D tube of 200 cells over [0, 1], far field at rest at p = rho = 1, acoustic CFL 0.5."""
    grid = euler.Grid((state.shape[1],), 1.0 / state.shape[1], (boundaries,), outlet=outlet,
                      attenuation=attenuation, outflow=_conserved(1.0, 0.0, 1.0))
    return _run(state, grid, seconds)[0]


def _acoustic_pulse(x, direction):
    c = math.sqrt(gas.GAMMA)
    dp = 1e-3 * np.exp(-(((x - 0.5) / 0.05) ** 2))
    return _conserved(1.0 + dp / c**2, direction * dp / c, 1.0 + dp)


@pytest.mark.parametrize(("outlet", "low", "high"), [("extrapolate", 0.3, 0.45), ("characteristic", 0.0, 0.005)])
def test_a_characteristic_outlet_lets_a_pressure_wave_out(outlet, low, high):
    """A right-going acoustic pulse (1e-3 of the ambient pressure) leaves through the outlet: the
    left-going wave it sends back, over the pulse's amplitude, is 0.38 with plain extrapolation
    and 0.0022 with the characteristic outlet (measured); a left outlet does the mirror image to
    round-off."""
    n, c = 200, math.sqrt(gas.GAMMA)
    x = (np.arange(n) + 0.5) / n
    state = _run_outlet(_acoustic_pulse(x, 1.0), outlet, 0.9 / c)
    p, u = gas.pressure(state) - 1.0, state[1] / state[0]
    reflected = np.abs(p - c * u).max() / 2 / 1e-3  # the left-going characteristic's amplitude
    assert low < reflected < high
    mirrored = _run_outlet(_acoustic_pulse(1.0 - x, -1.0), outlet, 0.9 / c, ("open", "wall"))
    np.testing.assert_allclose(mirrored[:, ::-1] * np.array([1, -1, 1])[:, None], state, rtol=0, atol=1e-13)


@pytest.mark.parametrize(("outlet", "attenuation", "expected", "tolerance"), [
    ("extrapolate", 1.0, 1.1, 1e-13), ("characteristic", 1.0, 1.0, 1e-3), ("attenuate", 0.5, 1.04, 0.01)])
def test_an_outlet_coupled_to_the_far_field_relaxes_an_overpressure(outlet, attenuation, expected, tolerance):
    """Gas at rest at p = 1.1 in a tube walled on the left, its right end an outlet to a far field at
    p = 1: plain extrapolation knows no far field and keeps 1.1 exactly; the characteristic outlet
    lets the overpressure out (mean 1.0002 after 3 s, measured), the attenuated one partly (1.042:
    its Dirichlet part reflects the expansion back in)."""
    n = 200
    start = _conserved(np.full(n, 1.1 ** (1 / gas.GAMMA)), np.zeros(n), np.full(n, 1.1))
    state = _run_outlet(start, outlet, 3.0, attenuation=attenuation)
    assert abs(gas.pressure(state).mean() - expected) < tolerance


def test_attenuated_ghost_cells_approach_the_far_field_and_bad_outlets_are_named():
    far = _conserved(1.0, 0.5, 1.0)
    state = _conserved(np.linspace(1.0, 2.0, 6), np.full(6, 0.2), np.linspace(1.5, 3.0, 6))
    grid = euler.Grid((6,), 0.1, (("open", "open"),), outlet="attenuate", attenuation=0.25, outflow=far)
    padded = euler._ghosts(state, 0, grid)
    for ghost, edge, power in ((1, 0, 1), (0, 0, 2), (8, 5, 1), (9, 5, 2)):
        np.testing.assert_allclose(padded[:, ghost], far + 0.25**power * (state[:, edge] - far), rtol=1e-15)
    with pytest.raises(ValueError, match="unknown outlet 'absorbing'; choose one of extrapolate, attenuate, "
                                         "characteristic"):
        euler.Grid((6,), 0.1, (("open", "open"),), outlet="absorbing")
    with pytest.raises(ValueError, match=re.escape("a characteristic outlet needs the far field's conserved state "
                                                   "(outflow, 3 values), got None")):
        euler.Grid((6,), 0.1, (("open", "open"),), outlet="characteristic")
    with pytest.raises(ValueError, match="attenuation must be from 0"):
        euler.Grid((6,), 0.1, (("open", "open"),), outlet="attenuate", attenuation=1.5, outflow=far)


def test_a_spherical_blast_in_a_closed_3d_box_keeps_mass_energy_and_symmetry():
    """The gas solver is dimension-free: a 3D central blast (24^3 cells, walls all round) keeps
    mass and energy to round-off (0 measured) and stays symmetric under axis swaps and mirrors
    (4.4e-16 measured)."""
    n = 24
    x = (np.arange(n) + 0.5) * (2.0 / n) - 1.0
    r2 = sum(c**2 for c in np.meshgrid(x, x, x, indexing="ij"))
    inside = r2 < 0.4**2
    state = gas.conserved(np.where(inside, 1.0, 0.125), np.zeros((3, n, n, n)), np.where(inside, 1.0, 0.1))
    grid = euler.Grid((n, n, n), 2.0 / n, (("wall", "wall"),) * 3)
    start = state.copy()
    state, iterations = _run(state, grid, 0.2)
    assert abs(state[0].sum() / start[0].sum() - 1.0) <= 1e-15 and abs(state[-1].sum() / start[-1].sum() - 1.0) <= 1e-15
    rho = state[0]
    for image in (rho.transpose(1, 0, 2), rho.transpose(2, 1, 0), rho[::-1], rho[:, :, ::-1]):
        assert np.abs(image - rho).max() <= 2e-15
    assert np.abs(state[1:4].sum(axis=(1, 2, 3))).max() <= 4e-14 and max(iterations) <= 25
