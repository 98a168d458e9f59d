"""Closed-form determinants and inverses of batches of 1x1, 2x2 and 3x3 matrices.

MPM needs one small matrix per particle every step (the MLS moment matrix, F, F^-T, the
APIC inertia D). A generic batched LAPACK call costs microseconds per matrix on a CPU;
the explicit cofactor formulas below are a handful of vectorised tensor operations.

Matrices stored by component: a batch of P matrices kept as a (d, d, P) tensor (the batch axis
fastest in memory). There 2x2 / 3x3 algebra is a few elementwise operations on contiguous
vectors, several times faster than batched products of tiny matrices; :func:`components` and
:func:`matrices` switch between the two views without copying.
"""

from __future__ import annotations

import torch

__all__ = [
    "det", "inv", "inv_transpose", "identity_like", "components", "matrices", "component_mm", "component_det",
    "component_inv",
]


def det(a: torch.Tensor) -> torch.Tensor:
    """Determinants of ``a: (..., d, d)``, d in {1, 2, 3} -> (...)."""
    d = a.shape[-1]
    if d == 1:
        return a[..., 0, 0]
    if d == 2:
        return a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    if d == 3:
        return (a[..., 0] * torch.linalg.cross(a[..., 1], a[..., 2], dim=-1)).sum(-1)
    raise ValueError(f"matrices must be 1x1, 2x2 or 3x3, got {d}x{d}")


def _adjugate(a: torch.Tensor) -> torch.Tensor:
    d = a.shape[-1]
    if d == 1:
        return torch.ones_like(a)
    if d == 2:
        row0 = torch.stack([a[..., 1, 1], -a[..., 0, 1]], dim=-1)
        row1 = torch.stack([-a[..., 1, 0], a[..., 0, 0]], dim=-1)
        return torch.stack([row0, row1], dim=-2)
    if d == 3:
        # Columns of the adjugate are cross products of the rows of a.
        cols = [torch.linalg.cross(a[..., (k + 1) % 3, :], a[..., (k + 2) % 3, :], dim=-1) for k in range(3)]
        return torch.stack(cols, dim=-1)
    raise ValueError(f"matrices must be 1x1, 2x2 or 3x3, got {d}x{d}")


def inv(a: torch.Tensor) -> torch.Tensor:
    """Inverses of ``a: (..., d, d)`` by the adjugate formula (no pivoting, no checks)."""
    return _adjugate(a) / det(a)[..., None, None]


def inv_transpose(a: torch.Tensor) -> torch.Tensor:
    """``a^{-T}`` for ``a: (..., d, d)``."""
    return inv(a).transpose(-1, -2)


def identity_like(a: torch.Tensor) -> torch.Tensor:
    """Identity matrices broadcastable against ``a: (..., d, d)``."""
    return torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)


# ----------------------------------------------------------------------------- matrices by component
def components(a: torch.Tensor) -> torch.Tensor:
    """(P, d, d) matrices -> the (d, d, P) view of their components."""
    return a.permute(1, 2, 0)


def matrices(c: torch.Tensor) -> torch.Tensor:
    """(d, d, P) components -> the (P, d, d) view of the matrices."""
    return c.permute(2, 0, 1)


def component_mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Products a_p b_p of matrices given by components (d, d, P) -> (d, d, P)."""
    out = a[:, 0, None] * b[None, 0]
    for j in range(1, a.shape[1]):
        out.addcmul_(a[:, j, None], b[None, j])
    return out


def component_det(a: torch.Tensor) -> torch.Tensor:
    """Determinants of matrices given by components (d, d, P) -> (P,)."""
    if a.shape[0] == 2:
        return a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    return det(matrices(a))


def component_inv(a: torch.Tensor) -> torch.Tensor:
    """Inverses of matrices given by components (d, d, P) -> (d, d, P)."""
    if a.shape[0] == 2:
        adjugate = torch.stack([a[1, 1], -a[0, 1], -a[1, 0], a[0, 0]]).view(a.shape)
        return adjugate / component_det(a)
    return components(inv(matrices(a)))
