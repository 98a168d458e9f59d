"""Conserved quantities and energies of a state: mass, linear and angular momentum, energies."""

from __future__ import annotations

import torch

from .model import Model
from .state import State

__all__ = ["diagnostics", "elastic_energy"]


def diagnostics(model: Model, state: State) -> dict[str, torch.Tensor]:
    """Mass, linear and angular momentum (with the APIC term, UMLS App. D def. 4), energies."""
    m = state.mass
    spin = _cross(state.x, state.v) + _affine_spin(state.affine)
    angular = (m[:, None] * spin).sum(0) if spin.ndim == 2 else (m * spin).sum()
    return {
        "mass": m.sum(),
        "momentum": (m[:, None] * state.v).sum(0),
        "angular_momentum": angular,
        "kinetic_energy": 0.5 * (m * (state.v * state.v).sum(1)).sum(),
        "elastic_energy": elastic_energy(model, state),
        "gravitational_energy": -(m[:, None] * state.x * model.gravity).sum(),
    }


def elastic_energy(model: Model, state: State) -> torch.Tensor:
    """Total strain energy sum_p V_p^0 psi(F_p)."""
    total = state.x.new_zeros(())
    for material, ids in model.materials:
        F, v0 = (state.F, state.volume0) if ids is None else (state.F[ids], state.volume0[ids])
        if getattr(material, "plastic", False):  # F is F^e; in 2D with the out-of-plane strain
            out = state.out_of_plane
            psi = material.energy_density(F, out if out is None or ids is None else out[ids])
        else:
            psi = material.energy_density(F)
        total = total + (v0 * psi).sum()
    return total


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product of (P, d) vectors: (P,) z-component in 2D, (P, 3) in 3D, zeros in 1D."""
    d = a.shape[-1]
    if d == 1:
        return torch.zeros_like(a[..., 0])
    if d == 2:
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return torch.linalg.cross(a, b, dim=-1)


def _affine_spin(B: torch.Tensor) -> torch.Tensor:
    """B^T : epsilon, the angular momentum per unit mass held by an APIC matrix B = sum w v r^T."""
    d = B.shape[-1]
    if d == 1:
        return torch.zeros_like(B[..., 0, 0])
    if d == 2:
        return B[..., 1, 0] - B[..., 0, 1]
    spin = [B[..., 2, 1] - B[..., 1, 2], B[..., 0, 2] - B[..., 2, 0], B[..., 1, 0] - B[..., 0, 1]]
    return torch.stack(spin, -1)
