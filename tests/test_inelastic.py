"""The solver's material post-processing (datagen.mpm.inelastic): F-bar against volumetric locking
and the J2 return map inside the step."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from datagen import shapes
from datagen.mpm.boundary import Wall
from datagen.mpm.inelastic import patch_average
from datagen.mpm.materials import NeoHookean
from datagen.mpm.model import compute_kernel
from datagen.mpm.plasticity import J2Softening
from datagen.mpm.step import step
from datagen.mpm.stress import kirchhoff_stress
from datagen.scenes.base import Scene, lattice, lattice_mesh
from datagen.simulation import SOLVER_DEFAULTS, build_solver_model

pytestmark = pytest.mark.usefixtures("one_thread")

RHO, G, H = 1.0, 10.0, 1.0


def _column(material, **solver):
    """A 1 m x 1 m column on a fixed floor between rollers, under gravity, in a 1 x 1.5 m box."""
    x, counts, step_ = lattice([0.0, 0.0], [1.0, H], 0.1)
    walls = [Wall("sticky", lambda c, n: n[:, 1] <= -0.999), Wall("slip", lambda c, n: np.abs(n[:, 0]) >= 0.999),
             Wall("separating", lambda c, n: n[:, 1] >= 0.999)]
    scene = Scene(domain=shapes.rectangle(1.0, 1.5, 0.2), body=lattice_mesh(x, counts), x=x, v=np.zeros_like(x),
                  volume=np.full(len(x), float(np.prod(step_))), materials=[(material, None)],
                  tracked=np.arange(len(x)), walls=walls, gravity=np.array([0.0, -G]))
    scene.damping = 200.0  # mass-proportional damping, so that the column settles in a few hundred steps
    return build_solver_model(scene, {**SOLVER_DEFAULTS, "transfer": "apic", **solver})


def _settle(model, state, seconds: float, dt: float = 3e-5):
    for _ in range(int(round(seconds / dt))):
        state = step(model, state, dt)
    return state


def _pressure(model, state) -> np.ndarray:
    """(10, 10) the particles' in-plane pressure over rho g H, on the lattice (rows: x, columns: y)."""
    tau = kirchhoff_stress(model, state.F, state.out_of_plane)
    p = -(tau[:, 0, 0] + tau[:, 1, 1]) / (2 * torch.linalg.det(state.F))
    return (p / (RHO * G * H)).numpy().reshape(10, 10)


def _checkerboard(p: np.ndarray) -> float:
    """RMS over interior particles of p minus the mean of its four lattice neighbours."""
    inner = p[1:-1, 1:-1] - 0.25 * (p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:])
    return float(np.sqrt((inner**2).mean()))


def test_fbar_removes_the_pressure_checkerboard_of_a_nearly_incompressible_column():
    # nu = 0.499 Neo-Hookean column loaded by gravity (damped, 600 steps). Without F-bar the volumetric
    # constraints lock and the particle pressures jump from particle to particle; the nodal-patch F-bar leaves
    # a smooth field. Measured (of rho g H): checkerboard 0.149 without, 0.0038 with; RMS error against the
    # hydrostatic rho g (H - y) away from the walls 0.128 without, 0.031 with. (Averaging each step's
    # increment dJ instead of J, the earlier F-bar, gave 0.035 and 0.050.)
    material = NeoHookean(1e4, 0.499, RHO)
    rough, error = {}, {}
    for fbar in (False, True):
        model, state = _column(material, fbar=fbar)
        state = _settle(model, state, 600 * 3e-5)
        p = _pressure(model, state)
        rough[fbar] = _checkerboard(p)
        hydrostatic = (H - state.x[:, 1].numpy()).reshape(10, 10) / H
        error[fbar] = float(np.sqrt(((p - hydrostatic)[2:-2, 2:-1] ** 2).mean()))
    assert rough[True] < 0.01 and rough[False] > 10 * rough[True]
    assert error[True] < 0.05 and error[False] > 2 * error[True]


def test_fbar_sets_each_particles_volume_ratio_to_its_patch_average():
    """After a step with F-bar, det F_p is the reference-volume-weighted patch average of the trial
    J = det F (of the step without F-bar from the same state), and F's deviatoric part is the trial's."""
    material = NeoHookean(1e4, 0.499, RHO)
    model, state = _column(material, fbar=True)
    state = _settle(model, state, 50 * 3e-5)
    plain, _ = _column(material, fbar=False)
    k = compute_kernel(model, state.x, state.cell)
    trial = step(plain, state, 3e-5)
    new = step(model, state, 3e-5)
    J_trial = torch.linalg.det(trial.F)
    expected = patch_average(k, J_trial, state.volume0, model.n_nodes)
    assert float((torch.linalg.det(new.F) - expected).abs().max()) < 4e-15  # measured 4.4e-16
    assert float((J_trial - expected).abs().max()) > 1e-7  # F-bar acted: measured 4.8e-7, far above round-off
    iso = lambda F: F / torch.linalg.det(F).pow(0.5)[:, None, None]  # noqa: E731
    assert float((iso(new.F) - iso(trial.F)).abs().max()) < 2e-15  # measured 2.2e-16


def test_patch_average_is_a_convex_average_that_keeps_constants():
    model, state = _column(NeoHookean(1e4, 0.3, RHO))
    k = compute_kernel(model, state.x, state.cell)
    volume = state.volume0
    assert torch.allclose(patch_average(k, torch.full_like(volume, 1.7), volume, model.n_nodes),
                          torch.full_like(volume, 1.7), rtol=0, atol=1e-14)
    value = torch.rand(len(volume), generator=torch.Generator().manual_seed(0), dtype=volume.dtype)
    averaged = patch_average(k, value, volume, model.n_nodes)
    assert float(averaged.min()) >= float(value.min()) and float(averaged.max()) <= float(value.max())
    assert float(averaged.std()) < 0.5 * float(value.std())  # it smooths


def test_elastic_models_are_untouched_without_fbar():
    model, state = _column(NeoHookean(1e4, 0.3, RHO))
    new = _settle(model, state, 3e-4)
    assert new.plastic_strain is None and new.out_of_plane is None


def test_plastic_column_stays_on_or_inside_the_yield_surface_and_softens():
    # A weak J2 column slumps under its own weight: every particle's von Mises stress stays <= its current
    # strength kappa(eps_q) (to round-off: measured max q / kappa - 1 = 1e-15), eps_q never decreases, and
    # plastic flow has begun (at the bottom).
    clay = J2Softening(1e4, 0.45, RHO, kappa_peak=1.0, kappa_residual=0.3, eta=5.0)
    model, state = _column(clay, fbar=True)
    assert state.plastic_strain is not None and state.out_of_plane is not None
    before = state.plastic_strain
    for _ in range(4):
        state = _settle(model, state, 0.01)
        q = clay.equivalent_stress(state.F, state.out_of_plane)
        assert float((q / clay.strength(state.plastic_strain)).max()) <= 1.0 + 1e-9
        assert bool((state.plastic_strain >= before).all())
        before = state.plastic_strain
    # measured 1.4e-3 (the rollers confine the column; 1.1e-4 with the earlier F-bar of increments dJ,
    # which locked more)
    assert float(state.plastic_strain.max()) > 5e-4
    assert float(state.out_of_plane.abs().max()) > 0  # plane strain: the out-of-plane elastic strain moves


@pytest.mark.parametrize("reference", ["total", "adaptive"])
def test_plasticity_and_fbar_keep_F_equal_to_Fsn_F0s_in_the_reference_modes(reference):
    clay = J2Softening(1e4, 0.45, RHO, kappa_peak=1.0, kappa_residual=0.3, eta=5.0)
    model, state = _column(clay, fbar=True, reference=reference)
    state = _settle(model, state, 0.005)
    ref = state.reference
    assert torch.allclose(state.F, ref.Fsn @ ref.F0s, rtol=0, atol=1e-13)
    assert float(state.plastic_strain.max()) > 0
    q = clay.equivalent_stress(state.F, state.out_of_plane)
    assert float((q / clay.strength(state.plastic_strain)).max()) <= 1.0 + 1e-9
