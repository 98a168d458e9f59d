"""The evolving part of a simulation: :class:`State` (particles) and, in the A-ULMPM total and
adaptive modes, its :class:`Reference` configuration. A step never mutates a state; it returns
a new one (``dataclasses.replace``), so states are easy to snapshot and compare.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from . import linalg
from .kernels import KernelResult
from .operators import Operators

__all__ = ["State", "Reference"]


@dataclass(frozen=True, eq=False)
class Reference:
    """The reference configuration s of the total/adaptive modes (A-ULMPM §3.4).

    kernel: the kernel at the particles' positions at s; operators: its fixed sparse transfer
    operators (:class:`~datagen.mpm.operators.Operators`, None for transfers that use the slot
    path). F0s, Fsn: (P, d, d) F^{0s} and F^{sn}, stored by component ((d, d, P) memory, see
    :mod:`~datagen.mpm.linalg`). nodes: (d, N) moved node positions q_i (q_i^s = the
    background's nodes). active: (N,) bool, the nodes in the kernel's support. rebuilds: kernels
    computed so far; contact_rebuilds: how many of them the contact trigger forced. cluster: (N,)
    cluster of each active node (-1: inactive); gaps: (C, C) gap between clusters at s (inf on
    the diagonal). drift, wall_gap: while drift < wall_gap no node can be on a wall plane, and
    the test is skipped.
    """

    kernel: KernelResult | None
    F0s: torch.Tensor
    Fsn: torch.Tensor
    nodes: torch.Tensor
    rebuilds: int = 0
    contact_rebuilds: int = 0
    active: torch.Tensor | None = None
    cluster: torch.Tensor | None = None
    gaps: torch.Tensor | None = None
    stale: str = ""  # why the next step rebuilds: "strain" or "contact"; "" while current
    operators: Operators | None = None
    drift: float = 0.0  # bound on max_i |q_i - q_i^s|: the sum over the steps of dt max_i |v_i|
    wall_gap: float = 0.0  # smallest distance at s from an active node to a wall plane's band


@dataclass(frozen=True)
class State:
    """Particle state at one time.

    x, v: (P, d); F: (P, d, d) deformation gradient; affine: (P, d, d) APIC matrix B_p (zero
    for FLIP/PIC); volume0, mass: (P,); cell: (P,) last containing cell (-1 unknown), a hint
    for the cell search; time; step. reference: the :class:`Reference` of the total/adaptive
    modes (None in eulerian mode or before the first step). velocity_gradient: (P, d, d) the
    last step's grad v in the current configuration, kept only for viscous materials.
    plastic_strain: (P,) equivalent plastic strain eps_q^p and out_of_plane: (P,) the out-of-plane
    elastic log strain of plane strain (2D), kept only when a material is plastic (F is then the
    elastic part F^e; see :mod:`~datagen.mpm.inelastic`).
    """

    x: torch.Tensor
    v: torch.Tensor
    F: torch.Tensor
    affine: torch.Tensor
    volume0: torch.Tensor
    mass: torch.Tensor
    cell: torch.Tensor
    time: float = 0.0
    step: int = 0
    reference: Reference | None = None
    velocity_gradient: torch.Tensor | None = None
    plastic_strain: torch.Tensor | None = None
    out_of_plane: torch.Tensor | None = None

    @classmethod
    def at_rest_shape(cls, x, v, volume0, density, *, device="cpu", dtype=torch.float64) -> State:
        """Undeformed particles (F = I) with masses density * volume0 (density: (P,) or scalar)."""
        as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
        x, v, volume0 = as_t(x), as_t(v), as_t(volume0)
        n, d = x.shape
        eye = torch.eye(d, dtype=dtype, device=device).expand(n, d, d).clone()
        return cls(x=x, v=v, F=eye, affine=torch.zeros_like(eye), volume0=volume0,
                   mass=as_t(density) * volume0, cell=torch.full((n,), -1, dtype=torch.int64, device=device))

    @property
    def volume(self) -> torch.Tensor:
        """(P,) current volumes V_p = det(F_p) V_p^0 (UMLS eq. 18)."""
        return linalg.det(self.F) * self.volume0
