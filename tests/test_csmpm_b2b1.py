"""The gas's B2B1 projection (datagen.csmpm.b2b1): the 1D integrals' closed forms, the system's
symmetry and definiteness, conservation and symmetry in a closed box, Sod against the exact
solution, and the scheme through datagen.simulate."""

import re

import numpy as np
import pytest

import datagen
from datagen.config import ConfigError
from datagen.csmpm import b2b1, euler, gas

SOD = ((1.0, 0.0, 1.0), (0.125, 0.0, 0.1))


def _walls(shape, dx=0.1):
    return euler.Grid(shape, dx, (("wall", "wall"),) * len(shape))


@pytest.mark.parametrize("odd", [False, True])
def test_the_folded_quadratic_integrals_take_their_closed_forms(odd):
    n, dx = 9, 0.1
    P, D = b2b1.axis_matrices(n, dx, odd)
    # integral of a cell-centred N2 over the domain: dx, less the 1/6 dx its wall's ghost folds in
    # (odd: taken away twice, as the ghost's and the node's own part past the wall; even: given back)
    expected = np.full(n, dx)
    expected[[0, -1]] = dx * (2.0 / 3.0 if odd else 1.0)
    np.testing.assert_allclose(np.asarray(P.sum(axis=1)).ravel(), expected, rtol=1e-14)
    corners = np.arange(n + 1) * dx
    np.testing.assert_allclose(D @ corners, expected, rtol=1e-13)  # the gradient of p = x is 1
    assert np.abs(D @ np.ones(n + 1)).max() <= 1e-15, "a constant pressure has no gradient"
    # every entry against a brute-force midpoint rule over the mirrored basis (ghost nodes -1 and n)
    x = (np.arange(200_000 * n) + 0.5) * dx / 200_000
    sign = -1.0 if odd else 1.0
    quadratic = [b2b1._quadratic(x / dx - (i + 0.5)) for i in range(-1, n + 1)]
    phi = np.stack(quadratic[1:-1])
    phi[0] += sign * quadratic[0]
    phi[-1] += sign * quadratic[-1]
    hat = np.stack([np.maximum(0.0, 1.0 - np.abs(x / dx - k)) for k in range(n + 1)])
    slope = np.stack([np.where(np.abs(x / dx - k) < 1.0, -np.sign(x / dx - k) / dx, 0.0) for k in range(n + 1)])
    step = dx / 200_000
    np.testing.assert_allclose(P.toarray(), phi @ hat.T * step, atol=2e-12)  # measured 2.6e-13
    np.testing.assert_allclose(D.toarray(), phi @ slope.T * step, atol=3e-11)  # measured 4.2e-12


def test_the_pressure_system_is_symmetric_and_definite_and_its_kernel_never_reaches_the_gas():
    rng = np.random.default_rng(3)
    grid = _walls((6, 5))
    ops = b2b1.Operators(grid)
    inverse_mass = 1.0 / rng.uniform(0.2, 3.0, grid.shape)
    size = 7 * 6

    def dense(compressibility):
        operator = ops.matrix(inverse_mass, compressibility, 0.01)
        return np.column_stack([operator @ e for e in np.eye(size)])

    coupled = dense(ops.corner_sum(rng.uniform(0.5, 2.0, grid.shape)))
    assert np.abs(coupled - coupled.T).max() <= 1e-15 * np.abs(coupled).max()
    assert np.linalg.eigvalsh(coupled)[0] > 0.05 * np.abs(coupled).max()  # measured 0.094 of the largest entry
    gradient_only = dense(np.zeros((7, 6)))
    eigen = np.linalg.eigvalsh(gradient_only)
    assert np.all(np.abs(eigen[:2]) <= 1e-15 * eigen[-1]) and eigen[2] > 1e-3 * eigen[-1], \
        "the kernel of G: the constants and the corners' checkerboard"
    i, j = np.indices((7, 6))
    checkerboard = (-1.0) ** (i + j)
    for a in range(2):
        assert np.abs(ops.gradient(checkerboard, a)).max() <= 2e-16  # measured 1.9e-17
        _, face_pressure = b2b1._face_values(np.zeros(grid.shape), checkerboard, a, grid)
        assert np.abs(face_pressure).max() == 0.0, "nor does it reach the energy's face pressures"
    np.testing.assert_allclose(np.diag(gradient_only).reshape(7, 6), ops.gradient_diagonal(inverse_mass), rtol=1e-13)
    p, u = rng.normal(size=(7, 6)), rng.normal(size=grid.shape)
    for a in range(2):
        assert abs(np.sum(ops.gradient(p, a) * u) - np.sum(p * ops.gradient_transpose(u, a))) <= 1e-15


def test_a_gas_at_rest_in_a_closed_box_stays_at_rest():  # a blast in one: tests/test_csmpm_gas.py
    grid = _walls((12, 9))
    still = gas.conserved(np.full(grid.shape, 0.7), np.zeros((2, *grid.shape)), np.full(grid.shape, 2.0))
    after = still
    for _ in range(10):
        after, _ = b2b1.step(after, grid, 0.005)
    assert np.abs(after - still).max() <= 1e-15  # measured 1.4e-16


def test_b2b1_sod_in_a_closed_tube_converges_toward_the_exact_solution_next_to_b1b0():
    errors = {"B1B0": [], "B2B1": []}
    for n in (100, 200, 400):
        for scheme, values in errors.items():
            t = datagen.simulate({"scene": "shock_tube", "params": {"cells": n, "boundaries": "wall"},
                                  "solver": {"scheme": scheme}, "output": {"frames": 1, "frame_interval": 0.2}})
            (rho, _, _), _ = gas.exact_riemann(*SOD, t.fields["x"], 0.2, interface=0.5)
            values.append(np.abs(t.fields["density"][-1] - rho).mean())
    b2, b1 = np.array(errors["B2B1"]), np.array(errors["B1B0"])
    orders = np.log2(b2[:-1] / b2[1:])
    assert b2[-1] <= 0.0046 and np.all(orders >= 0.75), (b2, orders)  # measured 0.00422; 0.86, 0.83
    assert np.all(b2 >= b1) and np.all(b2 <= 1.2 * b1), (b1, b2)  # the smoother B2 velocity: 9-15% more error


def test_the_scheme_is_chosen_in_the_config_and_refused_where_it_does_not_apply():
    runs = {scheme: datagen.simulate({"scene": "circular_shock", "params": {"cells": 16},
                                      "solver": {"scheme": scheme}, "output": {"frames": 2}})
            for scheme in ("B1B0", "B2B1")}
    default = datagen.simulate({"scene": "circular_shock", "params": {"cells": 16}, "output": {"frames": 2}})
    assert np.array_equal(default.fields["density"], runs["B1B0"].fields["density"])
    difference = np.abs(runs["B2B1"].fields["density"][-1] - runs["B1B0"].fields["density"][-1]).max()
    assert 1e-3 < difference < 0.1, difference
    assert runs["B2B1"].config["solver"]["scheme"] == "B2B1"
    for config, message in (
            ({"scene": "circular_shock", "solver": {"scheme": "B2B0"}}, "'solver.scheme' must be one of B1B0, B2B1"),
            ({"scene": "shock_tube", "solver": {"scheme": "B2B1"}},
             "'solver.scheme' B2B1 takes the gas alone in a closed box (circular_shock, or shock_tube with "
             "params.boundaries wall), not scene 'shock_tube' as configured; use B1B0"),
            ({"scene": "stair_flow", "solver": {"scheme": "B2B1"}}, "not scene 'stair_flow' as configured")):
        with pytest.raises(ConfigError, match=re.escape(message)):
            datagen.simulate(config)
    open_grid = euler.Grid((8,), 0.1, (("wall", "open"),))
    with pytest.raises(ValueError, match=re.escape("the B2B1 projection takes closed boxes (walls on every side) "
                                                   "only, got open boundaries; use the scheme B1B0")):
        b2b1.Operators(open_grid)
