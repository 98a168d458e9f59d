"""Hencky-J2 return mapping with exponential softening on single particles, against closed forms."""

from __future__ import annotations

import math

import pytest
import torch

from datagen.mpm.plasticity import J2Softening, hencky_tau

CLAY = dict(E=25e6, nu=0.3, density=2150.0, kappa_peak=40.82e3, kappa_residual=2.45e3, eta=5.0)


@pytest.fixture(autouse=True)
def float64():
    """These closed forms are checked in float64; the default dtype is restored afterwards."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(before)


def _q(eps: torch.Tensor, m: J2Softening) -> torch.Tensor:
    tau = hencky_tau(eps, m.mu, m.lam)
    return math.sqrt(1.5) * (tau - tau.mean(-1, keepdim=True)).norm(dim=-1)


def _shear(a) -> torch.Tensor:
    """Principal log strains of a pure shear of amplitude a, plus a volumetric part."""
    a = torch.as_tensor(a, dtype=torch.float64)
    return torch.stack([a, -a, torch.zeros_like(a)], -1) + 1e-4


def test_elastic_states_are_left_alone():
    m = J2Softening(**CLAY)
    small = _shear(torch.linspace(0, 0.9, 7) * CLAY["kappa_peak"] / (2 * math.sqrt(3) * m.mu))
    eps, eps_q = m.return_principal(small, torch.zeros(7))
    assert torch.equal(eps, small) and torch.equal(eps_q, torch.zeros(7))


def test_perfect_plasticity_in_pure_shear_has_the_closed_form():
    """kappa constant: q = 2 sqrt(3) mu a returns to kappa, so a -> kappa / (2 sqrt(3) mu) and
    dgamma = (q_trial - kappa) / (3 mu); the volumetric strain is kept."""
    m = J2Softening(**{**CLAY, "kappa_residual": CLAY["kappa_peak"], "eta": 0.0})
    a = torch.tensor([2e-3, 5e-3, 0.05, 0.3])
    trial = _shear(a)
    eps, eps_q = m.return_principal(trial, torch.zeros(4))
    kappa = CLAY["kappa_peak"]
    expected = 1e-4 + torch.stack([torch.full_like(a, kappa / (2 * math.sqrt(3) * m.mu)),
                                   torch.full_like(a, -kappa / (2 * math.sqrt(3) * m.mu)), torch.zeros_like(a)], -1)
    torch.testing.assert_close(eps, expected, rtol=0, atol=1e-15)
    torch.testing.assert_close(eps_q, (2 * math.sqrt(3) * m.mu * a - kappa) / (3 * m.mu), rtol=1e-13, atol=0)
    torch.testing.assert_close(eps.sum(-1), trial.sum(-1), rtol=1e-12, atol=0)  # isochoric flow


@pytest.mark.parametrize("eps_q0", [0.0, 0.1, 0.7])
def test_softening_stays_on_the_yield_surface(eps_q0):
    """Consistency: after the return q = kappa(eps_q^p) with eps_q^p = eps_q0 + dgamma, and the
    return is along the deviatoric direction of the trial stress."""
    m = J2Softening(**CLAY)
    trial = torch.tensor([[0.02, -0.005, -0.01], [0.1, 0.0, -0.1], [3e-3, 1e-3, -4e-3]])
    start = torch.full((3,), eps_q0)
    eps, eps_q = m.return_principal(trial, start)
    assert (eps_q > start).all()
    torch.testing.assert_close(_q(eps, m), m.strength(eps_q), rtol=1e-12, atol=0)
    dev_trial = trial - trial.mean(-1, keepdim=True)
    dev = eps - eps.mean(-1, keepdim=True)
    torch.testing.assert_close(dev / dev.norm(dim=-1, keepdim=True),
                               dev_trial / dev_trial.norm(dim=-1, keepdim=True), rtol=0, atol=1e-14)


def test_softening_law_and_a_monotone_loading_path():
    """Loading in pure shear step by step: the strength follows kappa_r + (kappa_p - kappa_r)
    exp(-eta eps_q) and falls toward the residual strength."""
    m = J2Softening(**CLAY)
    eps, eps_q, q = torch.zeros(1, 3), torch.zeros(1), []
    for _ in range(400):
        eps, eps_q = m.return_principal(eps + torch.tensor([[2e-3, -2e-3, 0.0]]), eps_q)
        q.append(float(_q(eps, m)))
    assert q[0] < CLAY["kappa_peak"] and 0.99 * CLAY["kappa_peak"] < max(q) <= CLAY["kappa_peak"]
    assert all(b <= a + 1e-9 for a, b in zip(q[q.index(max(q)):], q[q.index(max(q)) + 1:], strict=False))
    assert q[-1] == pytest.approx(CLAY["kappa_residual"] + (CLAY["kappa_peak"] - CLAY["kappa_residual"])
                                  * math.exp(-CLAY["eta"] * float(eps_q[0])), rel=1e-12)
    assert q[-1] < 0.1 * CLAY["kappa_peak"]


@pytest.mark.parametrize("d", [2, 3])
def test_return_map_on_F_is_objective(d):
    m = J2Softening(**CLAY)
    generator = torch.Generator().manual_seed(0)
    F = torch.eye(d) + 0.05 * torch.randn(8, d, d, generator=generator)
    theta = torch.rand(8, generator=generator) * 6.0
    R = torch.eye(d).repeat(8, 1, 1)
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = theta.cos(), -theta.sin(), theta.sin(), theta.cos()
    Fe, eps_q, out = m.return_map(F, torch.zeros(8))
    Fe_r, eps_q_r, out_r = m.return_map(R @ F, torch.zeros(8))
    assert (eps_q > 0).all(), "these trial strains yield"
    torch.testing.assert_close(Fe_r, R @ Fe, rtol=0, atol=1e-14)
    torch.testing.assert_close(eps_q_r, eps_q, rtol=1e-12, atol=0)
    torch.testing.assert_close(torch.linalg.det(Fe), torch.linalg.det(F) * (torch.exp(-out) if d == 2 else 1.0),
                               rtol=1e-13, atol=0)
    tau = m.kirchhoff(Fe, out)
    torch.testing.assert_close(tau, tau.transpose(-1, -2), rtol=0, atol=1e-9)


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="kappa_peak >= kappa_residual > 0"):
        J2Softening(**{**CLAY, "kappa_residual": 5e4})
    with pytest.raises(ValueError, match="softening faster than the shear stiffness"):
        J2Softening(**{**CLAY, "E": 1e3, "kappa_peak": 1e4})
