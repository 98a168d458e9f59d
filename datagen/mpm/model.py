"""The static part of a simulation: :class:`Model` (background, kernel, transfer, materials,
boundary conditions, gravity) and the pieces it holds, :class:`WallPlane` and :class:`Grip`.

A model never changes during a run; everything that evolves lives in
:class:`~datagen.mpm.state.State`, and a step is ``step(model, state, dt) -> state``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from .kernels import Grid, KernelResult, MeshTables, bspline_kernel, linear_kernel, umls_kernel
from .materials import Material

__all__ = ["Model", "WallPlane", "Grip", "KERNELS", "TRANSFERS", "REFERENCES", "compute_kernel"]

KERNELS = {
    "umls": lambda bg, x, guess: umls_kernel(bg, x, guess=guess),
    "linear": lambda bg, x, guess: linear_kernel(bg, x, guess=guess),
    "bspline": lambda bg, x, guess: bspline_kernel(bg, x),
}
TRANSFERS = ("flip", "pic", "apic", "musl")  # their P2G / G2P: datagen.mpm.transfers.SLOT_TRANSFERS
REFERENCES = ("eulerian", "total", "adaptive")  # A-ULMPM reference configurations: datagen.mpm.reference
PRECISIONS = ("float64", "float32")  # the compiled substeps' kernel and transfer arithmetic: datagen.mpm.fused


@dataclass(frozen=True, eq=False)
class Model:
    """Everything that does not change during a run.

    background: MeshTables (mesh kernels) or Grid (the structured B-spline solver). kernel:
    'umls' | 'linear' | 'bspline'. transfer: 'flip' | 'pic' | 'apic' | 'musl' (FLIP with the
    modified update-stress-last strain, for the linear hat). materials: (material, particle ids
    or None for all) pairs. conditions: boundary conditions applied in order. gravity: (d,).
    node_positions: (N, d). h_cfl: the length used by the CFL condition.

    A-ULMPM reference configuration (:mod:`~datagen.mpm.reference`): reference 'eulerian' |
    'total' | 'adaptive'; epsilon, fraction: the A-ULMPM eq. 33 criterion; contact_margin: the
    contact trigger in cells (None: off). wall_planes: the walls as :class:`WallPlane` pieces,
    applied to the moved node positions in the total/adaptive modes (None: apply ``conditions``
    by node index there too, right only while no node near a wall moves); pinned: index
    conditions that hold in every mode (clamps). grips: :class:`Grip` particle sets moved as
    prescribed. colliders: moving rigid obstacles (:class:`~datagen.mpm.colliders.Collider`),
    applied after the walls and clamps, at the background nodes' positions in eulerian mode and at
    their moved positions otherwise. damping: mass-proportional damping rate (1/s) of the nodal
    velocities.
    fbar: the F-bar treatment against volumetric locking (:mod:`~datagen.mpm.inelastic`): each
    step's volume change is replaced by its average over the particles' nodal patches.
    precision: 'float64' | 'float32', the arithmetic of the compiled substeps' kernel, stress
    coefficients, node sums and G2P (:mod:`~datagen.mpm.fused`); the particle state, the mesh and the
    node velocities stay float64, and every step outside the compiled substeps runs in the state's dtype.
    """

    background: MeshTables | Grid
    kernel: str
    transfer: str
    materials: tuple[tuple[Material, torch.Tensor | None], ...]
    conditions: tuple
    gravity: torch.Tensor
    node_positions: torch.Tensor
    h_cfl: float
    reference: str = "eulerian"
    epsilon: float = 0.01
    fraction: float = 0.01
    contact_margin: float | None = 1.0
    wall_planes: tuple | None = None
    pinned: tuple = ()
    grips: tuple = ()
    colliders: tuple = ()
    damping: float = 0.0
    fbar: bool = False
    precision: str = "float64"

    def __post_init__(self):
        if self.reference not in REFERENCES:
            raise ValueError(f"unknown reference {self.reference!r}; choose one of {list(REFERENCES)}")
        if not (self.epsilon > 0 and 0 < self.fraction <= 1):
            raise ValueError(f"reference criterion needs epsilon > 0 and 0 < fraction <= 1, "
                             f"got {self.epsilon}, {self.fraction}")
        if self.contact_margin is not None and not self.contact_margin >= 0:
            raise ValueError(f"contact_margin must be >= 0 or None, got {self.contact_margin}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r}; choose one of {list(PRECISIONS)}")
        if self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {self.kernel!r}; choose one of {sorted(KERNELS)}")
        if self.transfer not in TRANSFERS:
            raise ValueError(f"unknown transfer {self.transfer!r}; choose one of {sorted(TRANSFERS)}")
        if (self.kernel == "bspline") != isinstance(self.background, Grid):
            raise ValueError("the bspline kernel needs a Grid background and the mesh kernels MeshTables")
        if self.wall_planes:
            object.__setattr__(self, "_walls", _wall_table(self.wall_planes))
        object.__setattr__(self, "colliders", tuple(self.colliders))
        for k, collider in enumerate(self.colliders):
            if collider.dim != self.dim:
                raise ValueError(f"collider {k} ({collider.shape}) moves in {collider.dim}D, but the background "
                                 f"nodes are {self.dim}D")

    @property
    def n_nodes(self) -> int:
        return self.node_positions.shape[0]

    @property
    def dim(self) -> int:
        return self.node_positions.shape[1]

    @property
    def wave_speed(self) -> float:
        return max(m.wave_speed for m, _ in self.materials)

    @property
    def cell_size(self) -> float:
        """The background's cell size: the B-spline length h of a mesh, the spacing of a grid."""
        return self.background.spacing if isinstance(self.background, Grid) else self.background.h

    @property
    def plastic(self) -> bool:
        """Whether a material is plastic (its particles carry F^e and a plastic strain)."""
        return any(getattr(m, "plastic", False) for m, _ in self.materials)

    @property
    def viscous(self) -> bool:
        return any(getattr(m, "viscosity", 0.0) > 0 for m, _ in self.materials)


def compute_kernel(model: Model, x: torch.Tensor, guess: torch.Tensor | None = None) -> KernelResult:
    """The model's kernel at positions x: (P, d) (UMLS Algorithm 1 line 1)."""
    return KERNELS[model.kernel](model.background, x, guess)


@dataclass(frozen=True, eq=False)
class WallPlane:
    """A flat piece of wall that acts on background nodes at their current (moved) positions.

    A node at q is on the wall when -tol <= n.q - offset <= depth and its tangential
    coordinates t.q lie in [lower - margin, upper + margin]. kind: 'sticky' | 'slip' |
    'separating'; normal: (d,) unit outward; tangents: (d-1, d); lower, upper: (d-1,).
    """

    kind: str
    friction: float
    normal: torch.Tensor
    offset: float
    tangents: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor
    depth: float
    margin: float
    tol: float

    def members(self, q: torch.Tensor) -> torch.Tensor:
        """(N,) bool: nodes at q (d, N) on this wall piece."""
        height = self.normal @ q - self.offset
        inside = (height >= -self.tol) & (height <= self.depth)
        if self.tangents.shape[0]:
            along = self.tangents @ q  # (d-1, N)
            inside &= ((along >= self.lower[:, None] - self.margin)
                       & (along <= self.upper[:, None] + self.margin)).all(0)
        return inside

    def apply(self, v: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Constrain nodal velocities v (d, N) of the nodes at q (d, N) on this piece (in place)."""
        mask = self.members(q)
        if not bool(mask.any()):
            return v
        return self.apply_to(v, mask)

    def apply_to(self, v: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Constrain the nodal velocities v[:, mask] (v: (d, N); mask: bool (N,) or indices), in place."""
        vi = v[:, mask]
        n = self.normal[:, None]
        vn = (vi * n).sum(0)
        if self.kind == "sticky":
            v[:, mask] = 0.0
        elif self.kind == "slip":
            v[:, mask] = vi - vn * n
        else:
            tangential = vi - vn * n
            speed = tangential.norm(dim=0)
            scale = torch.clamp(1.0 - self.friction * vn / torch.clamp(speed, min=1e-300), min=0.0)
            v[:, mask] = torch.where(vn > 0, scale * tangential, vi)
        return v


def _wall_table(planes: tuple[WallPlane, ...]) -> dict[str, torch.Tensor]:
    """The planes' fields stacked, for testing every node against all of them at once."""
    def column(field):
        return torch.stack([torch.as_tensor(field(w)).to(planes[0].normal) for w in planes])

    return {"normal": column(lambda w: w.normal), "offset": column(lambda w: w.offset)[:, None],
            "low": column(lambda w: -w.tol)[:, None], "high": column(lambda w: w.depth)[:, None],
            "tangents": column(lambda w: w.tangents),
            "lower": column(lambda w: w.lower - w.margin)[:, :, None],
            "upper": column(lambda w: w.upper + w.margin)[:, :, None]}


@dataclass(frozen=True, eq=False)
class Grip:
    """Particles moved as prescribed: velocity(t) -> (d,) sequence, or None once released.

    While held, every node the grip's particles touch takes the grip velocity, and the grip's
    particles move with it exactly. ids: (n,) int64 particle indices.
    """

    ids: torch.Tensor
    velocity: Callable[[float], object]
