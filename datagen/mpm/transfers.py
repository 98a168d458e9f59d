"""P2G and G2P over kernel slots (UMLS Algorithm 1 lines 2-3 and 7-9): FLIP, PIC, APIC and MUSL.

The eulerian step uses them every step; the A-ULMPM reference step uses them for MUSL (the
other transfers there go through the fixed operators, :mod:`~datagen.mpm.operators`).
P2G returns the sums [m, p, f_int] that :func:`~datagen.mpm.nodal.nodal_update` turns into
nodal velocities; G2P reads those back into the particles.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from . import linalg, native
from .boundary import fold_mirrors
from .kernels import KernelResult, umls_kernel_p2g
from .model import Model, compute_kernel
from .nodal import Nodal, constrain, index_conditions
from .slots import apic_inertia, scatter, slot_sums
from .state import State
from .stress import force_stress

__all__ = ["SLOT_TRANSFERS", "kernel_and_p2g", "p2g_plain", "p2g_apic", "g2p_flip", "g2p_pic", "g2p_apic", "g2p_musl"]


def _p2g(model: Model, state: State, k: KernelResult, affine: torch.Tensor | None = None) -> torch.Tensor:
    """Scatter [m_i, m_i v_i, f_int_i] -> (1+2d, N) (UMLS Alg. 1 lines 2-3, UMLS eqs. 9-10).

    Nodes see the particle velocity v_p, or with ``affine`` (P, d, d) the APIC v_p + C_p (x_i - x_p).
    f_int_i = -sum_p V_p^0 tau_p grad w_ip with tau = J sigma the Kirchhoff stress (in a
    reference configuration: tau_p (F_p^{sn})^-T grad_s w_ip, see :func:`force_stress`).
    """
    return _p2g_sums(k, state.mass, state.v, _force_coef(model, state), affine, model.n_nodes)


def _force_coef(model: Model, state: State) -> torch.Tensor:
    """(P, d, d) -V_p^0 times the force stress: f_int_i = sum_p coef_p grad w_ip."""
    return force_stress(model, state) * (-state.volume0[:, None, None])


def _p2g_sums(k: KernelResult, mass: torch.Tensor, v: torch.Tensor, coef: torch.Tensor,
              affine: torch.Tensor | None, n_nodes: int) -> torch.Tensor:
    compiled = native.p2g(k, mass, v, coef, affine, n_nodes)
    if compiled is not None:
        return compiled
    d = v.shape[1]
    if affine is None:
        velocity = v.T[:, :, None]
    else:
        r = k.offset_axes
        velocity = [v[:, a, None] + sum(affine[:, a, b, None] * r[b] for b in range(d)) for a in range(d)]
    wm = k.weight * mass[:, None]
    g = k.grad_axes
    values = wm.new_empty((1 + 2 * d,) + wm.shape)
    values[0] = wm
    for a in range(d):
        values[1 + a] = wm * velocity[a]
        values[1 + d + a] = sum(coef[:, a, b, None] * g[b] for b in range(d))
    return scatter(k, values, n_nodes)


def kernel_and_p2g(model: Model, state: State) -> tuple[KernelResult, torch.Tensor]:
    """The kernel at the particles' positions and the P2G sums of the model's transfer (UMLS
    Algorithm 1 lines 1-3). With the UMLS kernel, a P2G without an affine part (FLIP, PIC, MUSL)
    and the compiled loops, both are made in one pass over the particles
    (:func:`~datagen.mpm.kernels.umls_kernel_p2g`: the sums of each particle's slots are taken
    while they are in cache) and only the particles whose kernel was made non-negative are
    summed again; otherwise the kernel, then the P2G."""
    p2g = SLOT_TRANSFERS[model.transfer][0]
    if model.kernel == "umls" and p2g is p2g_plain and native.available():
        coef = _force_coef(model, state)
        k, sums, left_out = umls_kernel_p2g(model.background, state.x, state.mass, state.v, coef, model.n_nodes,
                                            guess=state.cell)
        if sums is None:  # not compiled here (another device or dtype)
            return k, _p2g_sums(k, state.mass, state.v, coef, None, model.n_nodes)
        if left_out.numel():
            sums += _p2g_sums(k.select(left_out), state.mass[left_out], state.v[left_out], coef[left_out],
                              None, model.n_nodes)
        return k, sums
    k = compute_kernel(model, state.x, state.cell)
    return k, p2g(model, state, k)


def p2g_plain(model: Model, state: State, k: KernelResult) -> torch.Tensor:
    """FLIP/PIC P2G: nodes see the particle velocity v_p. Returns (1+2d, N) [m, p, f_int]."""
    return _p2g(model, state, k)


def p2g_apic(model: Model, state: State, k: KernelResult) -> torch.Tensor:
    """APIC P2G (UMLS eq. 48): nodes see v_p + B_p D_p^-1 (x_i - x_p), D_p = sum w r r^T."""
    return _p2g(model, state, k, state.affine @ linalg.inv(apic_inertia(k)))


def _deformed(model: Model, state: State, grad_v: torch.Tensor, dt: float) -> dict:
    """The updated deformation fields of ``state``; grad_v: (P, d, d) sum_i v_i grad w_ip^T of the
    new nodal velocities.

    Eulerian: F <- (I + dt sum_i v_i grad w_ip^T) F (UMLS eq. 17). In a reference
    configuration: F^{sn} <- F^{sn} + dt grad_s v_p with grad_s v_p = sum_i v_i grad_s w_ip^T
    (A-ULMPM eqs. 45-47), and F = F^{sn} F^{0s} (A-ULMPM eq. 32).
    """
    ref = state.reference
    if ref is None:
        out = {"F": state.F + dt * torch.bmm(grad_v, state.F)}
        current = grad_v
    else:
        Fsn = ref.Fsn + dt * grad_v
        out = {"F": torch.bmm(Fsn, ref.F0s), "reference": replace(ref, Fsn=Fsn)}
        current = grad_v @ linalg.inv(ref.Fsn) if model.viscous else None  # grad_x v = grad_s v (F^{sn})^-1
    if model.viscous:
        out["velocity_gradient"] = current
    return out


def g2p_flip(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """FLIP: v_p += sum w (v~_i - v_i) (UMLS eq. 16); x_p += dt sum w v~_i (UMLS eq. 15)."""
    d = model.dim
    moved_dv, grad_v, _ = slot_sums(k, torch.cat([grid.v_new, grid.v_new - grid.v]))
    x = state.x + dt * moved_dv[:, :d]
    return replace(state, x=x, v=state.v + moved_dv[:, d:], **_deformed(model, state, grad_v, dt))


def g2p_pic(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """PIC: v_p = sum w v~_i."""
    v, grad_v, _ = slot_sums(k, grid.v_new)
    return replace(state, x=state.x + dt * v, v=v, **_deformed(model, state, grad_v, dt))


def g2p_apic(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """APIC (UMLS eq. 49): v_p = sum w v~_i, B_p = sum w v~_i (x_i - x_p)^T."""
    v, grad_v, B = slot_sums(k, grid.v_new, moments=True)
    return replace(state, x=state.x + dt * v, v=v, affine=B, **_deformed(model, state, grad_v, dt))


def g2p_musl(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """FLIP velocities with the modified update-stress-last strain: F is updated with nodal
    velocities re-mapped from the new particle velocities, sum w m_p v_p^{n+1} / m_i, which
    stay bounded on nodes of tiny mass (the usual remedy for the linear hat's instability)."""
    new = g2p_flip(model, state, k, grid, dt)
    wm = k.weight * state.mass[:, None]
    momentum = scatter(k, torch.stack([wm * new.v[:, a, None] for a in range(model.dim)]), model.n_nodes)
    momentum = fold_mirrors(momentum, index_conditions(model, state), [-1.0] * model.dim)  # as grid.mass was
    active = grid.mass > 0
    v_map = torch.where(active, momentum / torch.where(active, grid.mass, 1.0), 0.0)
    v_map = constrain(model, state, v_map, dt, active)
    return replace(new, **_deformed(model, state, slot_sums(k, v_map)[1], dt))


SLOT_TRANSFERS = {  # transfer name -> (P2G, G2P)
    "flip": (p2g_plain, g2p_flip), "pic": (p2g_plain, g2p_pic), "apic": (p2g_apic, g2p_apic),
    "musl": (p2g_plain, g2p_musl),
}
