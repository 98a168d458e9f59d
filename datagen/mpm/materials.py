"""Elastic constitutive models, vectorised over particles.

Each material gives, for deformation gradients ``F: (P, d, d)``, the Kirchhoff stress
``tau = P F^T = J sigma`` (what the nodal force needs: f_i = -sum_p V_p^0 tau_p grad w_ip,
UMLS eq. 10 with V_p = J V_p^0), the first Piola-Kirchhoff stress ``P`` and the strain energy
density ``psi`` per unit undeformed volume. Lamé parameters follow from (E, nu) with the 3D
formulas in every dimension (plane strain in 2D; in 1D exact only for nu = 0).

:class:`WeaklyCompressibleFluid` has no shear stiffness: a pressure from J (Tait equation of
state) and an optional Newtonian viscosity, which the solver adds from the velocity gradient.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch

from . import linalg

__all__ = [
    "Material", "LinearElastic", "NeoHookean", "FixedCorotated", "WeaklyCompressibleFluid", "MATERIALS",
    "rotation_part", "lame",
]

_POLAR_ITERATIONS = 12


def lame(E: float, nu: float) -> tuple[float, float]:
    """(mu, lambda) of Young's modulus E and Poisson ratio nu (3D formulas)."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@dataclass(frozen=True)
class Material(ABC):
    """Base: Young's modulus E, Poisson ratio nu, rest density."""

    E: float
    nu: float
    density: float

    def __post_init__(self):
        if not (self.E > 0 and -1.0 < self.nu < 0.5 and self.density > 0):
            raise ValueError(
                f"{type(self).__name__} needs E > 0, -1 < nu < 0.5 and density > 0; "
                f"got E={self.E}, nu={self.nu}, density={self.density}"
            )

    @property
    def mu(self) -> float:
        return lame(self.E, self.nu)[0]

    @property
    def lam(self) -> float:
        return lame(self.E, self.nu)[1]

    @property
    def wave_speed(self) -> float:
        """Dilatational (P-wave) speed sqrt((lambda + 2 mu) / rho), for the CFL condition."""
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    @abstractmethod
    def kirchhoff(self, F: torch.Tensor) -> torch.Tensor:
        """(P, d, d) Kirchhoff stress tau = P F^T."""

    @abstractmethod
    def energy_density(self, F: torch.Tensor) -> torch.Tensor:
        """(P,) strain energy per unit undeformed volume."""

    def first_piola(self, F: torch.Tensor) -> torch.Tensor:
        """P = tau F^-T."""
        return self.kirchhoff(F) @ linalg.inv_transpose(F)

    @property
    def viscosity(self) -> float:
        """Dynamic viscosity (Pa s) of the viscous stress the solver adds; 0 for elastic solids."""
        return 0.0


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Batched products a b of small matrices (P, d, d).

    The A-ULMPM reference-configuration step keeps F by component (the batch axis fastest in
    memory, see :mod:`~datagen.mpm.linalg`); there the component product is several times
    faster than a batched matrix product, which is kept for the usual layout.
    """
    if a.dim() == 3 and a.shape[0] > 1 and a.stride(0) == 1:
        return linalg.matrices(linalg.component_mm(linalg.components(a), linalg.components(b)))
    return a @ b


def _trace(a: torch.Tensor) -> torch.Tensor:
    return a.diagonal(dim1=-2, dim2=-1).sum(-1)


class LinearElastic(Material):
    """Small-strain elasticity: psi = mu eps:eps + lambda/2 tr(eps)^2 with eps = sym(F) - I.

    P = dpsi/dF = 2 mu eps + lambda tr(eps) I and tau = P F^T. Not rotation invariant: use
    it for small rotations (e.g. the vibrating bar, whose closed form it reproduces in 1D).
    """

    def _strain(self, F):
        return 0.5 * (F + F.transpose(-1, -2)) - linalg.identity_like(F)

    def first_piola(self, F):
        eps = self._strain(F)
        return 2.0 * self.mu * eps + self.lam * _trace(eps)[..., None, None] * linalg.identity_like(F)

    def kirchhoff(self, F):
        return _mm(self.first_piola(F), F.transpose(-1, -2))

    def energy_density(self, F):
        eps = self._strain(F)
        return self.mu * (eps * eps).sum((-1, -2)) + 0.5 * self.lam * _trace(eps) ** 2


class NeoHookean(Material):
    """Compressible Neo-Hookean: psi = mu/2 (tr F^T F - d) - mu ln J + lambda/2 (ln J)^2.

    tau = mu (F F^T - I) + lambda ln J I. A non-positive J gives NaN (the run then stops).
    """

    def kirchhoff(self, F):
        log_j = torch.log(linalg.det(F))
        tau = _mm(F, F.transpose(-1, -2))  # mu (F F^T - I) + lambda ln J I, in F's memory layout
        diagonal = tau.diagonal(dim1=-2, dim2=-1)
        diagonal.sub_(1.0)
        tau.mul_(self.mu)
        diagonal.add_(self.lam * log_j[..., None])
        return tau

    def energy_density(self, F):
        log_j = torch.log(linalg.det(F))
        d = F.shape[-1]
        return 0.5 * self.mu * ((F * F).sum((-1, -2)) - d) - self.mu * log_j + 0.5 * self.lam * log_j**2


def rotation_part(F: torch.Tensor) -> torch.Tensor:
    """R of the polar decomposition F = R S (det F > 0): closed form in 1D/2D, scaled Newton in 3D."""
    d = F.shape[-1]
    if d == 1:
        return torch.sign(F)
    if d == 2:
        c = F[..., 0, 0] + F[..., 1, 1]
        s = F[..., 1, 0] - F[..., 0, 1]
        norm = torch.sqrt(c * c + s * s)
        c, s = c / norm, s / norm
        return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    R = F
    for _ in range(_POLAR_ITERATIONS):  # R <- (g R + R^-T / g) / 2, g = |det R|^(-1/3)
        g = linalg.det(R).abs().pow(-1.0 / 3.0)[..., None, None]
        R = 0.5 * (g * R + linalg.inv_transpose(R) / g)
    return R


class FixedCorotated(Material):
    """Fixed corotated: psi = mu |F - R|^2 + lambda/2 (J - 1)^2; tau = 2 mu (F - R) F^T + lambda (J-1) J I."""

    def kirchhoff(self, F):
        R = rotation_part(F)
        J = linalg.det(F)
        eye = linalg.identity_like(F)
        volumetric = (self.lam * (J - 1.0) * J)[..., None, None] * eye
        return 2.0 * self.mu * _mm(F - R, F.transpose(-1, -2)) + volumetric

    def energy_density(self, F):
        R = rotation_part(F)
        J = linalg.det(F)
        return self.mu * ((F - R) ** 2).sum((-1, -2)) + 0.5 * self.lam * (J - 1.0) ** 2


@dataclass(frozen=True)
class WeaklyCompressibleFluid(Material):
    """Weakly compressible fluid: pressure from J by the Tait equation of state, no shear stiffness.

    The stiffness is given like a solid's: bulk modulus K = E / (3 (1 - 2 nu)) (so a fluid and a
    solid built from the same E, nu resist compression alike). p(J) = K / gamma (J^-gamma - 1)
    (gamma = 1: p = K (1/J - 1)), psi(J) = -int_1^J p, tau = J sigma = -p J I. ``viscosity``:
    dynamic viscosity eta; the solver adds tau_visc = J eta (L + L^T) from the velocity gradient L.
    """

    gamma: float = 7.0
    fluid_viscosity: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if not (self.gamma >= 1.0 and self.fluid_viscosity >= 0.0):
            raise ValueError(f"WeaklyCompressibleFluid needs gamma >= 1 and viscosity >= 0; "
                             f"got gamma={self.gamma}, viscosity={self.fluid_viscosity}")

    @property
    def bulk(self) -> float:
        return self.E / (3.0 * (1.0 - 2.0 * self.nu))

    @property
    def viscosity(self) -> float:
        return self.fluid_viscosity

    @property
    def wave_speed(self) -> float:
        """Sound speed at rest, sqrt(K / rho)."""
        return math.sqrt(self.bulk / self.density)

    def pressure(self, J: torch.Tensor) -> torch.Tensor:
        if self.gamma == 1.0:
            return self.bulk * (1.0 / J - 1.0)
        return self.bulk / self.gamma * (J.pow(-self.gamma) - 1.0)

    def kirchhoff(self, F):
        J = linalg.det(F)
        tau = torch.zeros_like(F)  # -p J I, in F's memory layout
        tau.diagonal(dim1=-2, dim2=-1).copy_((-self.pressure(J) * J)[..., None])
        return tau

    def energy_density(self, F):
        J = linalg.det(F)
        if self.gamma == 1.0:
            return self.bulk * ((J - 1.0) - torch.log(J))
        g = self.gamma
        return self.bulk / g * ((J - 1.0) + (J.pow(1.0 - g) - 1.0) / (g - 1.0))


MATERIALS = {
    "linear": LinearElastic, "neo_hookean": NeoHookean, "fixed_corotated": FixedCorotated,
    "fluid": WeaklyCompressibleFluid,
}
"""Config name -> material class."""
