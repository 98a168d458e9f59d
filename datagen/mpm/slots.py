"""Kernel slots and background nodes: the scatter, gather and weighted sums every transfer uses.

A kernel gives each particle p a row of K slots (node index, weight w_ip, gradient grad w_ip).
Node fields are stored by axis, (c, N), and slot fields as (c, P, K): every operation is then
elementwise on contiguous blocks or a reduction over K, which torch does fast.
"""

from __future__ import annotations

import torch

from . import native
from .kernels import KernelResult

__all__ = ["scatter", "gather", "interpolate", "moment", "apic_inertia", "slot_sums"]


def scatter(k: KernelResult, values: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """Sum slot values (c, P, K) onto nodes -> (c, N); empty slots carry zeros."""
    c = values.shape[0]
    flat = k.index.clamp(min=0).reshape(1, -1).expand(c, -1)
    return values.new_zeros((c, n_nodes)).scatter_add_(1, flat, values.reshape(c, -1))


def gather(k: KernelResult, field: torch.Tensor) -> torch.Tensor:
    """Node field (c, N) seen from every slot -> (c, P, K)."""
    flat = k.index.clamp(min=0).reshape(-1)
    out = field.new_empty((field.shape[0], flat.numel()))
    for row, dest in zip(field, out, strict=True):
        torch.index_select(row, 0, flat, out=dest)
    return out.view((field.shape[0],) + k.index.shape)


def interpolate(k: KernelResult, slots: torch.Tensor) -> torch.Tensor:
    """sum_i w_ip u_i for slot values (c, P, K) -> (P, c)."""
    return (slots * k.weight).sum(dim=-1).T


def moment(k: KernelResult, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(P, c, e): sum_k w_pk a_p,k b_p,k^T for slot fields a (c, P, K) and b (e, P, K)."""
    return torch.bmm((a * k.weight).permute(1, 0, 2), b.permute(1, 2, 0))


def apic_inertia(k: KernelResult) -> torch.Tensor:
    """(P, d, d) the APIC inertia D_p = sum_i w_ip (x_i - x_p)(x_i - x_p)^T (UMLS eq. 48)."""
    return moment(k, k.offset_axes, k.offset_axes)


def slot_sums(k: KernelResult, field: torch.Tensor, moments: bool = False):
    """G2P's sums for node fields (c, N) whose first d rows are velocities: interp (P, c) =
    sum_i w_ip f_i, grad_v (P, d, d) = sum_i v_i grad w_ip^T and, with ``moments``, the APIC
    B (P, d, d) = sum_i w_ip v_i (x_i - x_p)^T (else None). Compiled where it can be
    (:func:`~datagen.mpm.native.g2p`), else in torch."""
    compiled = native.g2p(k, field, moments)
    if compiled is not None:
        return compiled
    d = k.grad_axes.shape[0]
    slots = gather(k, field)
    grad_v = torch.bmm(slots[:d].permute(1, 0, 2), k.grad_axes.permute(1, 2, 0))
    return interpolate(k, slots), grad_v, moment(k, slots[:d], k.offset_axes) if moments else None
