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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .materials import lame

__all__ = ["J2Softening", "hencky_tau"]

_NEWTON_ITERATIONS = 30


def hencky_tau(eps: torch.Tensor, mu: float, lam: float) -> torch.Tensor:
    """(P, 3) principal Kirchhoff stresses of (P, 3) principal Hencky strains."""
    return 2.0 * mu * eps + lam * eps.sum(-1, keepdim=True)


@dataclass(frozen=True)
class J2Softening:
    """Hencky-J2 with exponential softening: E, nu, density, peak and residual strength
    (kappa_p >= kappa_r > 0, Pa) and the softening rate eta >= 0."""

    E: float
    nu: float
    density: float
    kappa_peak: float
    kappa_residual: float
    eta: float

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

    @property
    def mu(self) -> float:
        return lame(self.E, self.nu)[0]

    @property
    def lam(self) -> float:
        return lame(self.E, self.nu)[1]

    def strength(self, eps_q: torch.Tensor) -> torch.Tensor:
        """kappa(eps_q^p) = (kappa_p - kappa_r) exp(-eta eps_q^p) + kappa_r."""
        return (self.kappa_peak - self.kappa_residual) * torch.exp(-self.eta * eps_q) + self.kappa_residual

    def return_principal(self, eps: torch.Tensor, eps_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trial principal strains (P, 3) and plastic strains (P,) -> returned (eps, eps_q)."""
        tau = hencky_tau(eps, self.mu, self.lam)
        dev = tau - tau.mean(-1, keepdim=True)
        q = math.sqrt(1.5) * dev.norm(dim=-1)
        yielding = q > self.strength(eps_q)
        dgamma = torch.zeros_like(q)
        for _ in range(_NEWTON_ITERATIONS):  # g(dg) = q - 3 mu dg - kappa(eps_q + dg), g' < 0
            g = q - 3.0 * self.mu * dgamma - self.strength(eps_q + dgamma)
            slope = -3.0 * self.mu + self.eta * (self.kappa_peak - self.kappa_residual) * torch.exp(
                -self.eta * (eps_q + dgamma))
            dgamma = torch.where(yielding, dgamma - g / slope, dgamma)
        direction = 1.5 * dev / torch.where(yielding, q, torch.ones_like(q))[:, None]
        return eps - dgamma[:, None] * direction, eps_q + dgamma

    def return_map(self, F: torch.Tensor, eps_q: torch.Tensor, eps_out: torch.Tensor | None = None):
        """Trial elastic F (P, d, d) -> (F^e (P, d, d), eps_q (P,), eps_out (P,) or None).

        eps_out: 2D only, the out-of-plane elastic log strain carried from the last step (zeros
        at rest); 3D takes None.
        """
        d = F.shape[-1]
        U, sigma, Vh = torch.linalg.svd(F)
        eps = torch.log(sigma)
        if d == 2:
            eps = torch.cat([eps, (torch.zeros_like(eps_q) if eps_out is None else eps_out)[:, None]], dim=-1)
        eps, eps_q = self.return_principal(eps, eps_q)
        Fe = U @ torch.diag_embed(torch.exp(eps[:, :d])) @ Vh
        return Fe, eps_q, (eps[:, 2] if d == 2 else None)

    def kirchhoff(self, F: torch.Tensor, eps_out: torch.Tensor | None = None) -> torch.Tensor:
        """(P, d, d) Kirchhoff stress of an elastic F (the in-plane part in 2D)."""
        d = F.shape[-1]
        U, sigma, _ = torch.linalg.svd(F)
        eps = torch.log(sigma)
        if d == 2:
            out = torch.zeros(len(F), dtype=F.dtype, device=F.device) if eps_out is None else eps_out
            eps = torch.cat([eps, out[:, None]], dim=-1)
        tau = hencky_tau(eps, self.mu, self.lam)[:, :d]
        return U @ torch.diag_embed(tau) @ U.transpose(-1, -2)
