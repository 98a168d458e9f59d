"""The fixed sparse-operator engine of the A-ULMPM total and adaptive modes.

Between updates of the reference configuration the weights and gradients do not change, so
P2G and G2P are fixed sparse products, built once per update (:class:`Operators`): one CSR
matrix gathers every particle quantity of G2P, two scatter momentum and force, and each
transfer is one sparse matrix-vector product per axis. The particle matrices are passed by
component ((d, d, P), see :mod:`~datagen.mpm.linalg`). The nodal update between
:func:`operator_p2g` and :func:`operator_g2p` is the one of every engine
(:func:`~datagen.mpm.nodal.nodal_update`); MUSL keeps the slot path.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from . import linalg
from .kernels import KernelResult
from .slots import apic_inertia, scatter

__all__ = ["Operators", "OPERATOR_TRANSFERS", "build_operators", "operator_p2g", "operator_g2p", "flip_increment"]

OPERATOR_TRANSFERS = ("flip", "pic", "apic")  # musl keeps the slot path


@dataclass(frozen=True, eq=False)
class Operators:
    """The fixed transfer operators of a reference configuration: sparse CSR matrices.

    With W the (P, N) weights w_ip, G_b the (P, N) gradient components (grad_s w_ip)_b and (APIC)
    R_b the (P, N) weighted offsets w_ip (x_i - x_p)_b at s, M = diag(m_p), V = diag(V_p^0):
    gather: (J P, N) the row blocks [W; G_0; ...; G_{d-1}] (APIC: then R_0, ..., R_{d-1}); one
    product with a nodal velocity component v_a (N,) gives, per particle, sum_i w_ip v_ia, the
    row a of grad_s v and (APIC) the row a of B = sum_i w_ip v_i (x_i - x_p)^T. weight: (P, N)
    W alone (FLIP: the velocity increment), else None.
    scatter: (N, S P) [W^T M] (APIC: [W^T M, R_0^T M, ...]): component a of the nodal momentum
    from [v_pa] (APIC: [v_pa, C_p[a, 0], ...], C = B D^-1, UMLS eq. 48). force: (N, d P)
    [-G_0^T V, ..., -G_{d-1}^T V]: component a of f_i = -sum_p V_p^0 sigma~_p grad_s w_ip from
    the row a of sigma~ = tau (F^{sn})^-T (A-ULMPM App. B eq. 44).
    mass: (N,) the nodal masses sum_p w_ip m_p (fixed too). inertia_inv: (d, d, P) D_p^-1 by
    component (APIC), else None.
    """

    gather: torch.Tensor
    weight: torch.Tensor | None
    scatter: torch.Tensor
    force: torch.Tensor
    mass: torch.Tensor
    inertia_inv: torch.Tensor | None = None


def _csr(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A CSR matrix from COO entries (int32 indices where they fit: faster products)."""
    order = torch.argsort(rows * shape[1] + cols)
    crow = torch.zeros(shape[0] + 1, dtype=torch.int64, device=rows.device)
    crow[1:] = torch.bincount(rows, minlength=shape[0]).cumsum(0)
    index = torch.int32 if len(values) < 2**31 and max(shape) < 2**31 else torch.int64
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        return torch.sparse_csr_tensor(crow.to(index), cols[order].to(index), values[order], size=shape)


def _leading_rows(a: torch.Tensor, rows: int) -> torch.Tensor:
    """The first ``rows`` rows of CSR matrix a, sharing its memory."""
    crow = a.crow_indices()[:rows + 1]
    end = int(crow[-1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, a.col_indices()[:end], a.values()[:end], size=(rows, a.shape[1]))


def build_operators(transfer: str, k: KernelResult, mass: torch.Tensor, volume0: torch.Tensor,
                    n_nodes: int) -> Operators | None:
    """The transfer operators of kernel k for particles of masses and volumes (P,) (None for
    transfers that keep the slot path)."""
    if transfer not in OPERATOR_TRANSFERS:
        return None
    n_p, n_k = k.index.shape
    valid = k.index >= 0
    p = torch.arange(n_p, device=k.index.device)[:, None].expand(n_p, n_k)[valid]
    i = k.index[valid]
    w = k.weight[valid]
    grads = list(k.grad_axes[:, valid])
    offsets = [w * r for r in k.offset_axes[:, valid]] if transfer == "apic" else []

    def stacked(blocks: list[torch.Tensor], by_node: bool) -> torch.Tensor:
        rows = p.repeat(len(blocks)) + torch.arange(len(blocks), device=p.device).repeat_interleave(len(p)) * n_p
        if by_node:
            return _csr(i.repeat(len(blocks)), rows, torch.cat(blocks), (n_nodes, len(blocks) * n_p))
        return _csr(rows, i.repeat(len(blocks)), torch.cat(blocks), (len(blocks) * n_p, n_nodes))

    m, v0 = mass[p], volume0[p]
    gather = stacked([w, *grads, *offsets], by_node=False)
    inertia_inv = linalg.components(linalg.inv(apic_inertia(k))).contiguous() if transfer == "apic" else None
    return Operators(
        gather=gather, weight=_leading_rows(gather, n_p) if transfer == "flip" else None,
        scatter=stacked([m * w, *(m * o for o in offsets)], by_node=True),
        force=stacked([-v0 * g for g in grads], by_node=True),
        mass=scatter(k, (k.weight * mass[:, None])[None], n_nodes)[0], inertia_inv=inertia_inv,
    )


def operator_p2g(ops: Operators, v: torch.Tensor, stress: torch.Tensor, affine: torch.Tensor) -> torch.Tensor:
    """P2G by the operators -> (1+2d, N) [m, p, f_int] (A-ULMPM App. B eq. 44).

    v: (P, d) particle velocities; stress: (d, d, P) sigma~ = tau (F^{sn})^-T by component,
    contiguous; affine: (P, d, d) the APIC matrices B_p (used only with APIC operators).
    """
    d = v.shape[1]
    particle = v.T.contiguous()  # (d, P)
    if ops.inertia_inv is not None:  # nodes see v_p + C_p (x_i - x_p), C = B D^-1 (UMLS eq. 48)
        C = linalg.component_mm(linalg.components(affine), ops.inertia_inv)  # (a, b, P)
        particle = torch.cat([particle[:, None], C], 1).view(d, -1)
    momentum = torch.stack([ops.scatter @ row for row in particle])
    force = torch.stack([ops.force @ row for row in stress.reshape(d, -1)])
    return torch.cat([ops.mass[None], momentum, force])


def operator_g2p(ops: Operators, v_new: torch.Tensor, n_particles: int) -> torch.Tensor:
    """G2P by the operators: (d, J, P) per axis a the rows sum_i w_ip v_ia, (grad_s v)_ab for
    every b, and (APIC) B_ab = sum_i w_ip v_ia (x_i - x_p)_b. v_new: (d, N) nodal velocities."""
    return torch.stack([ops.gather @ row for row in v_new]).view(v_new.shape[0], -1, n_particles)


def flip_increment(ops: Operators, dv: torch.Tensor) -> torch.Tensor:
    """(P, d) sum_i w_ip dv_i for the nodal velocity increments dv: (d, N) (FLIP operators only)."""
    return torch.stack([ops.weight @ row for row in dv], 1)
