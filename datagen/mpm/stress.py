"""Particle stresses of a model's materials: elastic (Kirchhoff), viscous, and the stress the
nodal force needs in the current or the A-ULMPM reference configuration."""

from __future__ import annotations

import torch

from . import linalg
from .model import Model
from .state import State

__all__ = ["kirchhoff_stress", "particle_stress", "force_stress"]


def kirchhoff_stress(model: Model, F: torch.Tensor, out_of_plane: torch.Tensor | None = None) -> torch.Tensor:
    """(P, d, d) Kirchhoff stress tau = J sigma of every particle. out_of_plane: (P,) the
    out-of-plane elastic log strain plastic materials take in 2D (State.out_of_plane)."""
    if len(model.materials) == 1 and model.materials[0][1] is None:
        return _tau(model.materials[0][0], F, out_of_plane)
    tau = torch.empty_like(F)
    for material, ids in model.materials:
        tau[ids] = _tau(material, F[ids], None if out_of_plane is None else out_of_plane[ids])
    return tau


def _tau(material, F: torch.Tensor, out_of_plane: torch.Tensor | None) -> torch.Tensor:
    if getattr(material, "plastic", False):
        return material.kirchhoff(F, out_of_plane)
    return material.kirchhoff(F)


def particle_stress(model: Model, state: State) -> torch.Tensor:
    """(P, d, d) the Kirchhoff stress tau of every particle plus the viscous Kirchhoff stress
    eta J (L + L^T) of viscous materials (L the last step's velocity gradient)."""
    tau = kirchhoff_stress(model, state.F, state.out_of_plane)
    if state.velocity_gradient is not None:
        L = state.velocity_gradient
        J = linalg.det(state.F)
        for material, ids in model.materials:
            eta = getattr(material, "viscosity", 0.0)
            if eta > 0:
                sel = slice(None) if ids is None else ids
                rate = L[sel] + L[sel].transpose(-1, -2)
                tau[sel] = tau[sel] + (eta * J[sel])[:, None, None] * rate
    return tau


def force_stress(model: Model, state: State) -> torch.Tensor:
    """(P, d, d) the stress the nodal force needs: tau in the current configuration; in an A-ULMPM
    reference configuration sigma~ = tau (F^{sn})^-T = P (F^{0s})^T (A-ULMPM App. B eq. 44),
    computed by component (the returned view is (d, d, P) contiguous in memory)."""
    tau = particle_stress(model, state)
    if state.reference is None:
        return tau
    Fsn = linalg.components(state.reference.Fsn)
    inv_t = linalg.component_inv(Fsn).transpose(0, 1)
    return linalg.matrices(linalg.component_mm(linalg.components(tau), inv_t))
