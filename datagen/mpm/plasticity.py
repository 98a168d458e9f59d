"""Hencky elasticity with J2 (von Mises) plasticity and exponential softening (thesis §2.3.5,
the sensitive-clay slope), as a return map on the elastic deformation gradient.

The elastic state is F^e = U diag(exp(eps)) V^T with principal Hencky (logarithmic) strains
eps. Hencky elasticity gives the principal Kirchhoff stresses tau = 2 mu eps + lam tr(eps);
the yield function is f = q - kappa(eps_q^p) with the von Mises stress q = sqrt(3/2) |dev tau|
and the softening law kappa = (kappa_p - kappa_r) exp(-eta eps_q^p) + kappa_r. A trial state
with f > 0 returns along the deviatoric direction n = (3/2) dev tau / q (isochoric: tr(eps)
is kept): eps <- eps - dgamma n, eps_q^p <- eps_q^p + dgamma, with dgamma > 0 solving
q - 3 mu dgamma = kappa(eps_q^p + dgamma) (Newton; monotone while 3 mu > eta (kappa_p - kappa_r)).

2D is plane strain: the out-of-plane total stretch stays 1, so the out-of-plane elastic log
strain is carried per particle (it changes when plastic flow has an out-of-plane part).

The principal directions come from the symmetric eigenproblem of b = F F^T = U diag(exp(2 eps)) U^T
(about twice as fast as an SVD of F on the CPU); the returned F^e = U diag(exp(eps - eps_trial)) U^T F
has the same right rotation as F. In the solver (:mod:`~datagen.mpm.inelastic`) the particles keep
F^e as their F, the equivalent plastic strain in ``State.plastic_strain`` and, in 2D, the out-of-plane
elastic log strain in ``State.out_of_plane``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch

from .materials import Material

__all__ = ["J2Softening", "hencky_tau", "principal_strains"]

_NEWTON_ITERATIONS = 30
_NEWTON_TOL = 1e-15  # on the plastic multiplier's last Newton change (relative)


def hencky_tau(eps: torch.Tensor, mu: float, lam: float) -> torch.Tensor:
    """(P, 3) principal Kirchhoff stresses of (P, 3) principal Hencky strains."""
    return 2.0 * mu * eps + lam * eps.sum(-1, keepdim=True)


def principal_strains(F: torch.Tensor, out: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(U (P, d, d), eps (P, 3)): the left principal directions of F and its principal Hencky strains,
    with the out-of-plane elastic log strain ``out`` (P,) (zeros if None) appended in 2D."""
    d = F.shape[-1]
    lam2, U = torch.linalg.eigh(F @ F.transpose(-1, -2))
    eps = 0.5 * torch.log(lam2)
    if d == 2:
        eps = torch.cat([eps, (eps.new_zeros(len(F)) if out is None else out)[:, None]], dim=-1)
    return U, eps


@dataclass(frozen=True)
class J2Softening(Material):
    """Hencky-J2 with exponential softening: E, nu, density, peak and residual strength
    (kappa_p >= kappa_r > 0, Pa) and the softening rate eta >= 0.

    A :class:`~datagen.mpm.materials.Material` whose F is the elastic part F^e; its stress and energy
    take, in 2D, the out-of-plane elastic log strain as a second argument (zeros if omitted).
    """

    kappa_peak: float
    kappa_residual: float
    eta: float
    plastic: ClassVar[bool] = True

    def __post_init__(self):
        if not (self.E > 0 and -1.0 < self.nu < 0.5 and self.density > 0):
            raise ValueError(f"J2Softening needs E > 0, -1 < nu < 0.5 and density > 0; got E={self.E}, "
                             f"nu={self.nu}, density={self.density}")
        if not (self.kappa_peak >= self.kappa_residual > 0 and self.eta >= 0):
            raise ValueError("J2Softening needs kappa_peak >= kappa_residual > 0 and eta >= 0; got "
                             f"{self.kappa_peak}, {self.kappa_residual}, {self.eta}")
        if 3.0 * self.mu <= self.eta * (self.kappa_peak - self.kappa_residual):
            raise ValueError("J2Softening: softening faster than the shear stiffness (eta (kappa_p - kappa_r) >= "
                             "3 mu) has no unique return; lower eta or the strength drop")

    def strength(self, eps_q: torch.Tensor) -> torch.Tensor:
        """kappa(eps_q^p) = (kappa_p - kappa_r) exp(-eta eps_q^p) + kappa_r."""
        return (self.kappa_peak - self.kappa_residual) * torch.exp(-self.eta * eps_q) + self.kappa_residual

    def return_principal(self, eps: torch.Tensor, eps_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trial principal strains (P, 3) and plastic strains (P,) -> returned (eps, eps_q)."""
        tau = hencky_tau(eps, self.mu, self.lam)
        dev = tau - tau.mean(-1, keepdim=True)
        q = math.sqrt(1.5) * dev.norm(dim=-1)
        yielding = (q > self.strength(eps_q)).nonzero()[:, 0]
        if not yielding.numel():
            return eps, eps_q
        qy, ey = q[yielding], eps_q[yielding]
        dgamma = torch.zeros_like(qy)
        drop = self.eta * (self.kappa_peak - self.kappa_residual)
        for _ in range(_NEWTON_ITERATIONS):  # g(dg) = q - 3 mu dg - kappa(eps_q + dg), g' < 0
            g = qy - 3.0 * self.mu * dgamma - self.strength(ey + dgamma)
            change = g / (-3.0 * self.mu + drop * torch.exp(-self.eta * (ey + dgamma)))
            dgamma = dgamma - change
            if float(change.abs().max()) <= _NEWTON_TOL * (1.0 + float(dgamma.abs().max())):
                break
        direction = 1.5 * dev[yielding] / qy[:, None]
        eps, eps_q = eps.clone(), eps_q.clone()
        eps[yielding] -= dgamma[:, None] * direction
        eps_q[yielding] += dgamma
        return eps, eps_q

    def return_map(self, F: torch.Tensor, eps_q: torch.Tensor, eps_out: torch.Tensor | None = None):
        """Trial elastic F (P, d, d) -> (F^e (P, d, d), eps_q (P,), eps_out (P,) or None).

        eps_out: 2D only, the out-of-plane elastic log strain carried from the last step (zeros
        at rest); 3D takes None.
        """
        d = F.shape[-1]
        U, trial = principal_strains(F, eps_out)
        eps, eps_q = self.return_principal(trial, eps_q)
        stretch = torch.exp(eps[:, :d] - trial[:, :d])  # F^e = U diag(exp(eps - eps_trial)) U^T F
        Fe = (U * stretch[:, None, :]) @ (U.transpose(-1, -2) @ F)
        return Fe, eps_q, (eps[:, 2] if d == 2 else None)

    def kirchhoff(self, F: torch.Tensor, eps_out: torch.Tensor | None = None) -> torch.Tensor:
        """(P, d, d) Kirchhoff stress of an elastic F (the in-plane part in 2D)."""
        d = F.shape[-1]
        U, eps = principal_strains(F, eps_out)
        tau = hencky_tau(eps, self.mu, self.lam)[:, :d]
        return (U * tau[:, None, :]) @ U.transpose(-1, -2)

    def energy_density(self, F: torch.Tensor, eps_out: torch.Tensor | None = None) -> torch.Tensor:
        """(P,) Hencky strain energy mu |eps|^2 + lam/2 tr(eps)^2 of an elastic F."""
        eps = principal_strains(F, eps_out)[1]
        return self.mu * (eps * eps).sum(-1) + 0.5 * self.lam * eps.sum(-1) ** 2

    def mean_stress(self, F: torch.Tensor, eps_out: torch.Tensor | None = None) -> torch.Tensor:
        """(P,) mean normal (Cauchy) stress tr(sigma)/3 = K theta exp(-theta), theta = tr(eps) = ln J
        (K = lam + 2 mu / 3; with the out-of-plane stress in 2D; negative in compression)."""
        theta = principal_strains(F, eps_out)[1].sum(-1)
        return (self.lam + 2.0 * self.mu / 3.0) * theta * torch.exp(-theta)

    def equivalent_stress(self, F: torch.Tensor, eps_out: torch.Tensor | None = None) -> torch.Tensor:
        """(P,) von Mises stress q = sqrt(3/2) |dev tau| of an elastic F (the yield function's q)."""
        tau = hencky_tau(principal_strains(F, eps_out)[1], self.mu, self.lam)
        return math.sqrt(1.5) * (tau - tau.mean(-1, keepdim=True)).norm(dim=-1)
