"""Explicit MPM (UMLS Algorithm 1): a static :class:`Model`, an evolving :class:`State`, and
``step(model, state, dt) -> state``.

One step: the kernel of every particle is computed by one call (:func:`compute_kernel`,
whose result a caller may cache and pass back in), P2G scatters mass, momentum and internal
force in one pass, nodal velocities are integrated and constrained, and G2P updates
particle velocities (FLIP, PIC, APIC or FLIP with MUSL), positions and deformation gradients.

Reference configuration (A-ULMPM §3.4, §5, App. B). ``Model.reference`` chooses where kernels
and their gradients are evaluated:

- ``eulerian`` (s = n): the kernel is recomputed at the current positions every step (the
  classic updated-Lagrangian MPM; this path is the plain UMLS solver, unchanged).
- ``total`` (s = 0): the kernel of the initial positions is kept for the whole run.
- ``adaptive``: the kernel of configuration s is kept until an update is triggered, by the
  A-ULMPM eq. 33 criterion (the fraction of particles with |det F^{s,n+1} - 1| >= epsilon
  reaches ``fraction``) or by the contact trigger (below).

Between updates particles carry F^{0s} and F^{sn} (:class:`Reference`), F = F^{sn} F^{0s}; the
nodal force is f_i = -sum_p V_p^0 P(F_p) (F_p^{0s})^T grad_s w_ip (App. B eq. 44), computed as
tau_p (F_p^{sn})^-T grad_s w_ip with tau = P F^T; F^{sn} <- F^{sn} + dt grad_s v_p (eqs. 45-47).
The background nodes move with their velocities, q_i <- q_i + dt v_i, and walls act on those
moved positions (:class:`WallPlane`). An update sets F^{0s} <- F, F^{sn} <- I and rebuilds the
kernel at the particles' current positions in the undeformed background.

Between updates the weights and gradients are fixed, so for FLIP, PIC and APIC the transfers
are fixed sparse products (:class:`Operators`, built at each update: one CSR matrix gathers
every particle quantity of G2P, two scatter momentum and force), one sparse matrix-vector
product per axis, and the particle matrices (F^{0s}, F^{sn}, F) are kept by component so that
their 2x2 / 3x3 algebra is a few contiguous vector operations. Nodal masses and the active
nodes are fixed too and cached. MUSL keeps the per-slot path of the eulerian mode.

Contact trigger (``contact_margin``, adaptive only). Between updates two bodies only interact
through background nodes they share at s, so bodies that approach each other would pass
through one another. At each update the active nodes are split into clusters (connected through
shared particles) and the gap between every pair of clusters is measured. Between updates
D_c = max |q_i - q_i^s| over the nodes of cluster c bounds how far it moved; an update is
forced when D_a + D_b >= gap_ab - contact_margin * h for some pair (h the background cell
size). A single body in free rigid motion has one cluster and never triggers; walls need no
trigger because they act on the moved node positions.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from . import linalg
from .boundary import apply_conditions, apply_mirrors, fold_mirrors
from .kernels import Grid, KernelResult, MeshTables, bspline_kernel, linear_kernel, umls_kernel
from .locate import LocateStatus
from .materials import Material

__all__ = [
    "Model", "State", "SimulationError", "step", "compute_kernel", "cfl_time_step", "diagnostics",
    "kirchhoff_stress", "KERNELS", "TRANSFERS", "REFERENCES", "Reference", "WallPlane", "Grip",
    "kernel_rebuilds", "Operators",
]

REFERENCES = ("eulerian", "total", "adaptive")

_CLUSTER_WEIGHT = 0.05  # particles join the clusters of nodes they weigh at least this much
_MASS_FLOOR = 1e-10  # nodes lighter than this fraction of the mean particle mass are treated as empty


class SimulationError(RuntimeError):
    """A run that cannot continue: particles lost or a non-finite state."""


@dataclass(frozen=True, eq=False)
class Model:
    """Everything that does not change during a run.

    background: MeshTables (mesh kernels) or Grid (bspline). kernel: 'umls' | 'linear' |
    'bspline'. transfer: 'flip' | 'pic' | 'apic' | 'musl' (FLIP with the modified
    update-stress-last strain, for the linear hat). materials: (material, particle ids or None
    for all) pairs. conditions: boundary conditions applied in order. gravity: (d,).
    node_positions: (N, d). h_cfl: the length used by the CFL condition.

    Reference configuration (see the module doc): reference 'eulerian' | 'total' |
    'adaptive'; epsilon, fraction: the eq. 33 criterion; contact_margin: the contact trigger
    in cells (None: off). wall_planes: the walls as :class:`WallPlane` pieces, applied to the
    moved node positions in the total/adaptive modes (None: apply ``conditions`` by node index
    there too, right only while no node near a wall moves); pinned: index conditions that hold
    in every mode (clamps). grips: :class:`Grip` particle sets moved as prescribed. damping:
    mass-proportional damping rate (1/s) of the nodal velocities.
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
    damping: float = 0.0

    def __post_init__(self):
        if self.reference not in REFERENCES:
            raise ValueError(f"unknown reference {self.reference!r}; choose one of {list(REFERENCES)}")
        if not (self.epsilon > 0 and 0 < self.fraction <= 1):
            raise ValueError(f"reference criterion needs epsilon > 0 and 0 < fraction <= 1, "
                             f"got {self.epsilon}, {self.fraction}")
        if self.contact_margin is not None and not self.contact_margin >= 0:
            raise ValueError(f"contact_margin must be >= 0 or None, got {self.contact_margin}")
        if self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {self.kernel!r}; choose one of {sorted(KERNELS)}")
        if self.transfer not in TRANSFERS:
            raise ValueError(f"unknown transfer {self.transfer!r}; choose one of {sorted(TRANSFERS)}")
        if (self.kernel == "bspline") != isinstance(self.background, Grid):
            raise ValueError("the bspline kernel needs a Grid background and the mesh kernels MeshTables")
        if self.wall_planes:  # the planes stacked, for testing every node against all of them at once
            planes = self.wall_planes
            column = lambda f: torch.stack([torch.as_tensor(f(w)).to(planes[0].normal) for w in planes])  # noqa: E731
            walls = {"normal": column(lambda w: w.normal), "offset": column(lambda w: w.offset)[:, None],
                     "low": column(lambda w: -w.tol)[:, None], "high": column(lambda w: w.depth)[:, None],
                     "tangents": column(lambda w: w.tangents),
                     "lower": column(lambda w: w.lower - w.margin)[:, :, None],
                     "upper": column(lambda w: w.upper + w.margin)[:, :, None]}
            object.__setattr__(self, "_walls", walls)

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
    def viscous(self) -> bool:
        return any(getattr(m, "viscosity", 0.0) > 0 for m, _ in self.materials)


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


@dataclass(frozen=True, eq=False)
class Grip:
    """Particles moved as prescribed: velocity(t) -> (d,) sequence, or None once released.

    While held, every node the grip's particles touch takes the grip velocity, and the grip's
    particles move with it exactly. ids: (n,) int64 particle indices.
    """

    ids: torch.Tensor
    velocity: Callable[[float], object]


@dataclass(frozen=True, eq=False)
class Reference:
    """The reference configuration s of the total/adaptive modes.

    kernel: the kernel at the particles' positions at s; operators: its fixed sparse transfer
    operators (:class:`Operators`, None for transfers that use the slot path).
    F0s, Fsn: (P, d, d) F^{0s} and F^{sn}, stored by component ((d, d, P) memory, see
    :func:`by_component`). nodes: (d, N) moved node positions q_i (q_i^s = the
    background's nodes). active: (N,) bool, the nodes in the kernel's support. rebuilds: kernels computed
    so far; contact_rebuilds: how many of them the contact trigger forced. cluster: (N,) cluster
    of each active node (-1: inactive); gaps: (C, C) gap between clusters at s (inf on the diagonal).
    drift, wall_gap: while drift < wall_gap no node can be on a wall plane, and the test is skipped.
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


# ----------------------------------------------------------------------------- kernel
KERNELS = {
    "umls": lambda bg, x, guess: umls_kernel(bg, x, guess=guess),
    "linear": lambda bg, x, guess: linear_kernel(bg, x, guess=guess),
    "bspline": lambda bg, x, guess: bspline_kernel(bg, x),
}


def compute_kernel(model: Model, x: torch.Tensor, guess: torch.Tensor | None = None) -> KernelResult:
    """The model's kernel at positions x: (P, d) (UMLS Algorithm 1 line 1)."""
    return KERNELS[model.kernel](model.background, x, guess)


# ----------------------------------------------------------------------------- stresses
def kirchhoff_stress(model: Model, F: torch.Tensor) -> torch.Tensor:
    """(P, d, d) Kirchhoff stress tau = J sigma of every particle."""
    if len(model.materials) == 1 and model.materials[0][1] is None:
        return model.materials[0][0].kirchhoff(F)
    tau = torch.empty_like(F)
    for material, ids in model.materials:
        tau[ids] = material.kirchhoff(F[ids])
    return tau


def _stress(model: Model, state: State) -> torch.Tensor:
    """(P, d, d) the Kirchhoff stress tau of every particle plus the viscous Kirchhoff stress."""
    tau = kirchhoff_stress(model, state.F)
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


def _force_stress(model: Model, state: State) -> torch.Tensor:
    """(P, d, d) the stress the nodal force needs: tau (eulerian), tau (F^{sn})^-T = P (F^{0s})^T
    in a reference configuration (A-ULMPM App. B eq. 44)."""
    tau = _stress(model, state)
    if state.reference is not None:
        tau = tau @ linalg.inv_transpose(state.reference.Fsn)
    return tau


def elastic_energy(model: Model, state: State) -> torch.Tensor:
    """Total strain energy sum_p V_p^0 psi(F_p)."""
    total = state.x.new_zeros(())
    for material, ids in model.materials:
        F, v0 = (state.F, state.volume0) if ids is None else (state.F[ids], state.volume0[ids])
        total = total + (v0 * material.energy_density(F)).sum()
    return total


# ----------------------------------------------------------------------------- transfers
# Node fields are stored by axis, (c, N), and slot fields as (c, P, K): every operation is
# then elementwise on contiguous blocks or a reduction over K, which torch does fast.
def _scatter(k: KernelResult, values: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """Sum slot values (c, P, K) onto nodes -> (c, N); empty slots carry zeros."""
    c = values.shape[0]
    flat = k.index.clamp(min=0).reshape(1, -1).expand(c, -1)
    return values.new_zeros((c, n_nodes)).scatter_add_(1, flat, values.reshape(c, -1))


def _gather(k: KernelResult, field: torch.Tensor) -> torch.Tensor:
    """Node field (c, N) seen from every slot -> (c, P, K)."""
    flat = k.index.clamp(min=0).reshape(-1)
    out = field.new_empty((field.shape[0], flat.numel()))
    for row, dest in zip(field, out, strict=True):
        torch.index_select(row, 0, flat, out=dest)
    return out.view((field.shape[0],) + k.index.shape)


def _interpolate(k: KernelResult, slots: torch.Tensor) -> torch.Tensor:
    """sum_i w_ip u_i for slot values (c, P, K) -> (P, c)."""
    return (slots * k.weight).sum(dim=-1).T


def _p2g(model: Model, state: State, k: KernelResult, velocity: torch.Tensor) -> torch.Tensor:
    """Scatter [m_i, m_i v_i, f_int_i] -> (1+2d, N) (UMLS Alg. 1 lines 2-3, eqs. 9-10).

    velocity: (d, P, K) or (d, P, 1), the particle velocity seen by each node.
    f_int_i = -sum_p V_p^0 tau_p grad w_ip with tau = J sigma the Kirchhoff stress (in a
    reference configuration: tau_p (F_p^{sn})^-T grad_s w_ip, see :func:`_force_stress`).
    """
    d = model.dim
    wm = k.weight * state.mass[:, None]
    coef = _force_stress(model, state) * (-state.volume0[:, None, None])
    g = k.grad_axes
    values = wm.new_empty((1 + 2 * d,) + wm.shape)
    values[0] = wm
    for a in range(d):
        values[1 + a] = wm * velocity[a]
        values[1 + d + a] = sum(coef[:, a, b, None] * g[b] for b in range(d))
    return _scatter(k, values, model.n_nodes)


def p2g_plain(model: Model, state: State, k: KernelResult) -> torch.Tensor:
    """FLIP/PIC P2G: nodes see the particle velocity v_p. Returns (1+2d, N) [m, p, f_int]."""
    return _p2g(model, state, k, state.v.T[:, :, None])


def _moment(k: KernelResult, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(P, c, e): sum_k w_pk a_p,k b_p,k^T for slot fields a (c, P, K) and b (e, P, K)."""
    return torch.bmm((a * k.weight).permute(1, 0, 2), b.permute(1, 2, 0))


def p2g_apic(model: Model, state: State, k: KernelResult) -> torch.Tensor:
    """APIC P2G (UMLS eq. 48): nodes see v_p + B_p D_p^-1 (x_i - x_p), D_p = sum w r r^T."""
    r = k.offset_axes
    C = state.affine @ linalg.inv(_moment(k, r, r))
    d = model.dim
    velocity = [state.v[:, a, None] + sum(C[:, a, b, None] * r[b] for b in range(d)) for a in range(d)]
    return _p2g(model, state, k, velocity)


@dataclass(frozen=True)
class Nodal:
    """Node fields of one step: mass (N,); velocity before (v) and after (v_new) the update, (d, N)."""

    mass: torch.Tensor
    v: torch.Tensor
    v_new: torch.Tensor


def _by_index(model: Model, state: State) -> tuple:
    """The conditions applied by node index: all of them in eulerian mode (or without wall
    planes), else the pinned ones (the walls act on moved node positions there)."""
    return model.conditions if state.reference is None or model.wall_planes is None else model.pinned


def constrain(model: Model, state: State, v: torch.Tensor) -> torch.Tensor:
    """Boundary conditions on nodal velocities v (d, N), in place: by node index in eulerian
    mode; on the moved node positions (wall planes) plus the pinned nodes otherwise."""
    ref = state.reference
    by_plane = ref is not None and bool(model.wall_planes)
    if by_plane and ref.drift >= ref.wall_gap:  # only nodes in the kernel's support carry velocity
        nodes, members = _wall_members(model, ref)
        for j, hit in enumerate(members.any(1).tolist()):
            if hit:
                model.wall_planes[j].apply_to(v, nodes[members[j]])
    return apply_conditions(v, _by_index(model, state))


def _wall_members(model: Model, ref: Reference) -> tuple[torch.Tensor, torch.Tensor]:
    """The active nodes at their moved positions on the wall planes, all planes at once (the
    test of :meth:`WallPlane.members`): (m,) candidate node ids and (planes, m) bool membership."""
    table = model._walls
    height = table["normal"] @ ref.nodes - table["offset"]  # (n, N)
    near = (height >= table["low"]) & (height <= table["high"])
    nodes = near.any(0).nonzero()[:, 0]
    nodes = nodes[ref.active[nodes]]
    inside = near[:, nodes]
    if table["tangents"].shape[1]:
        along = table["tangents"] @ ref.nodes[:, nodes]  # (n, d-1, m)
        inside &= ((along >= table["lower"]) & (along <= table["upper"])).all(1)
    return nodes, inside


def _parity(d: int) -> list[float]:
    """Parity about a mirroring wall of the rows [m, p, f] of the P2G sums: mass even, the rest odd."""
    return [1.0] + [-1.0] * (2 * d)


def grid_update(model: Model, state: State, nodal: torch.Tensor, dt: float) -> Nodal:
    """Nodal velocities before and after the update, constrained (UMLS eq. 13, Alg. 1 l. 6).

    nodal: (1+2d, N) [m, p, f_int], modified in place: the sums of mirror ghosts are first folded
    onto the nodes they mirror (:func:`~datagen.mpm.boundary.fold_mirrors`), and the ghosts'
    velocity before the update is mirrored as well as after it, so that FLIP's increment
    v_new - v is the odd extension of the physical nodes' increment.
    """
    d = model.dim
    by_index = _by_index(model, state)
    nodal = fold_mirrors(nodal, by_index, _parity(d))
    mass, momentum, force = nodal[0], nodal[1:1 + d], nodal[1 + d:]
    active = mass > _MASS_FLOOR * state.mass.mean()
    safe = torch.where(active, mass, torch.ones_like(mass))
    v = apply_mirrors(torch.where(active, momentum / safe, 0.0), by_index)
    accel = force / safe + model.gravity[:, None]  # gravity: f_ext = m_i g (UMLS eq. 11)
    v_new = torch.where(active, v + dt * accel, 0.0)
    if model.damping:
        v_new = v_new / (1.0 + model.damping * dt)
    return Nodal(mass=torch.where(active, mass, 0.0), v=v, v_new=constrain(model, state, v_new))


def _deformed(model: Model, state: State, k: KernelResult, v_slots: torch.Tensor, dt: float) -> dict:
    """The updated deformation fields of ``state``; v_slots: (d, P, K) new nodal velocities.

    Eulerian: F <- (I + dt sum_i v_i grad w_ip^T) F (UMLS eq. 17). In a reference
    configuration: F^{sn} <- F^{sn} + dt grad_s v_p with grad_s v_p = sum_i v_i grad_s w_ip^T
    (A-ULMPM eqs. 45-47), and F = F^{sn} F^{0s} (eq. 32).
    """
    grad_v = torch.bmm(v_slots.permute(1, 0, 2), k.grad_axes.permute(1, 2, 0))
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
    """FLIP: v_p += sum w (v~_i - v_i) (UMLS eq. 16); x_p += dt sum w v~_i (eq. 15)."""
    d = model.dim
    slots = _gather(k, torch.cat([grid.v_new, grid.v_new - grid.v]))
    moved_dv = _interpolate(k, slots)
    x = state.x + dt * moved_dv[:, :d]
    return replace(state, x=x, v=state.v + moved_dv[:, d:], **_deformed(model, state, k, slots[:d], dt))


def g2p_pic(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """PIC: v_p = sum w v~_i."""
    vi = _gather(k, grid.v_new)
    v = _interpolate(k, vi)
    return replace(state, x=state.x + dt * v, v=v, **_deformed(model, state, k, vi, dt))


def g2p_apic(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """APIC (UMLS eq. 49): v_p = sum w v~_i, B_p = sum w v~_i (x_i - x_p)^T."""
    vi = _gather(k, grid.v_new)
    v = _interpolate(k, vi)
    B = _moment(k, vi, k.offset_axes)
    return replace(state, x=state.x + dt * v, v=v, affine=B, **_deformed(model, state, k, vi, dt))


def g2p_musl(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """FLIP velocities with the modified update-stress-last strain: F is updated with nodal
    velocities re-mapped from the new particle velocities, sum w m_p v_p^{n+1} / m_i, which
    stay bounded on nodes of tiny mass (the usual remedy for the linear hat's instability)."""
    new = g2p_flip(model, state, k, grid, dt)
    wm = k.weight * state.mass[:, None]
    momentum = _scatter(k, torch.stack([wm * new.v[:, a, None] for a in range(model.dim)]), model.n_nodes)
    momentum = fold_mirrors(momentum, _by_index(model, state), [-1.0] * model.dim)  # as grid.mass was
    active = grid.mass > 0
    v_map = torch.where(active, momentum / torch.where(active, grid.mass, 1.0), 0.0)
    v_map = constrain(model, state, v_map)
    return replace(new, **_deformed(model, state, k, _gather(k, v_map), dt))


TRANSFERS = {
    "flip": (p2g_plain, g2p_flip), "pic": (p2g_plain, g2p_pic), "apic": (p2g_apic, g2p_apic),
    "musl": (p2g_plain, g2p_musl),
}


# ----------------------------------------------------------------------------- step
def cfl_time_step(model: Model, state: State, cfl: float) -> float:
    """dt = cfl * h / (c + max |v_p|), c the largest dilatational wave speed."""
    speed = model.wave_speed + float(state.v.norm(dim=1).max())
    return cfl * model.h_cfl / speed


def _lost_error(model: Model, state: State, k: KernelResult, dt: float) -> SimulationError:
    lost = k.status != LocateStatus.INSIDE
    nonfinite = int((k.status == LocateStatus.NONFINITE).sum())
    background = "grid" if model.kernel == "bspline" else "mesh"
    what = f"{int(lost.sum())} of {len(lost)} particles left the {background}"
    if nonfinite:
        what += f" ({nonfinite} with non-finite positions)"
    return SimulationError(_advice(model, state, dt, what))


def _advice(model: Model, state: State, dt: float, what: str) -> str:
    finite_v = state.v[torch.isfinite(state.v).all(dim=1)]
    vmax = float(finite_v.norm(dim=1).max()) if len(finite_v) else 0.0
    suggest = min(0.5 * dt, 0.3 * model.h_cfl / (model.wave_speed + vmax))
    return (f"step {state.step} (t = {state.time:.6g}): {what}; the run is unstable or leaves the "
            f"domain at dt = {dt:.3g}. Try dt <= {suggest:.3g} (solver.dt, or a smaller solver.cfl), "
            "or enlarge the domain")


def step(model: Model, state: State, dt: float, kernel: KernelResult | None = None) -> State:
    """Advance by dt (UMLS Algorithm 1). kernel: a precomputed kernel at state.x (else computed).

    Raises SimulationError naming the step if particles are outside the background or the
    new state is not finite.

    In the total/adaptive reference modes ``kernel`` is ignored: the cached kernel of the
    reference configuration (state.reference) is used and rebuilt when the mode says so.
    """
    if model.reference != "eulerian":
        return _step_reference(model, state, dt)
    k = kernel if kernel is not None else compute_kernel(model, state.x, state.cell)
    if k.n_lost:
        raise _lost_error(model, state, k, dt)
    p2g, g2p = TRANSFERS[model.transfer]
    grid = grid_update(model, state, p2g(model, state, k), dt)
    if model.grips:
        grid = _hold_grips(model, state, k, grid)
    new = g2p(model, state, k, grid, dt)
    if model.grips:
        new = _move_grips(model, state, new, dt)
    _check_finite(model, state, new, dt)
    cell = k.cell if k.cell is not None else state.cell
    return replace(new, cell=cell, time=state.time + dt, step=state.step + 1)


def _check_finite(model: Model, state: State, new: State, dt: float) -> None:
    if not bool(torch.isfinite(new.x.sum() + new.v.sum() + new.F.sum())):
        raise SimulationError(_advice(model, state, dt, "the state became non-finite (NaN or inf)"))


# ----------------------------------------------------------------------------- grips
def _held(model: Model, state: State):
    for grip in model.grips:
        velocity = grip.velocity(state.time)
        if velocity is not None:
            yield grip, torch.as_tensor(velocity, dtype=state.x.dtype, device=state.x.device)


def _hold_grips(model: Model, state: State, k: KernelResult, grid: Nodal) -> Nodal:
    """Every node a held grip's particles touch takes the grip velocity."""
    held = list(_held(model, state))
    if not held:
        return grid
    v_new = grid.v_new.clone()
    for grip, velocity in held:
        index = k.index[grip.ids]
        nodes = torch.unique(index[index >= 0])
        v_new[:, nodes] = velocity[:, None]
    return replace(grid, v_new=v_new)


def _move_grips(model: Model, state: State, new: State, dt: float) -> State:
    """Held grip particles move exactly with their grip."""
    held = list(_held(model, state))
    if not held:
        return new
    x, v = new.x.clone(), new.v.clone()
    for grip, velocity in held:
        v[grip.ids] = velocity
        x[grip.ids] = state.x[grip.ids] + dt * velocity
    return replace(new, x=x, v=v)


# ----------------------------------------------------------------------------- reference configuration
def kernel_rebuilds(state: State) -> int | None:
    """Kernels computed so far in a total/adaptive run (None for eulerian states: one per step)."""
    return None if state.reference is None else state.reference.rebuilds


def _clusters(model: Model, k: KernelResult) -> tuple[torch.Tensor, torch.Tensor]:
    """Clusters of active nodes (connected through shared particles) and their gaps at s.

    A particle links only the nodes it weighs >= _CLUSTER_WEIGHT: the far, faint ring nodes
    two bodies may share cells apart carry no real contact, and must not merge their clusters.

    Gaps are exact up to ``reach = (contact_margin + 4) h``; farther pairs get ``reach``,
    a lower bound, so the trigger stays conservative.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n_nodes, h = model.n_nodes, model.cell_size
    index = k.index.cpu().numpy()
    rows, cols = np.nonzero((index >= 0) & (k.weight.abs().cpu().numpy() >= _CLUSTER_WEIGHT))
    nodes = index[rows, cols]
    n_p = index.shape[0]
    graph = sp.coo_matrix((np.ones(len(nodes)), (rows, n_p + nodes)), shape=(n_p + n_nodes,) * 2)
    _, labels = connected_components(graph, directed=False)
    active = np.unique(nodes)
    if not len(active):
        return torch.full((n_nodes,), -1, device=model.node_positions.device), None
    _, cluster_of_active = np.unique(labels[n_p + active], return_inverse=True)
    cluster = np.full(n_nodes, -1, dtype=np.int64)
    cluster[active] = cluster_of_active
    n_clusters = int(cluster_of_active.max()) + 1 if len(active) else 0
    reach = (model.contact_margin + 4.0) * h
    gaps = np.full((n_clusters, n_clusters), reach)
    np.fill_diagonal(gaps, np.inf)
    if n_clusters > 1:
        points = model.node_positions.cpu().numpy()[active]
        pairs = cKDTree(points).query_pairs(reach, output_type="ndarray")
        a, b = cluster_of_active[pairs[:, 0]], cluster_of_active[pairs[:, 1]]
        apart = a != b
        dist = np.linalg.norm(points[pairs[apart, 0]] - points[pairs[apart, 1]], axis=1)
        np.minimum.at(gaps, (a[apart], b[apart]), dist)
        np.minimum.at(gaps, (b[apart], a[apart]), dist)
    device = model.node_positions.device
    return (torch.as_tensor(cluster, device=device),
            torch.as_tensor(gaps, dtype=model.node_positions.dtype, device=device))


def _apic_to_new_reference(state: State, old: Reference, k: KernelResult) -> torch.Tensor:
    """B such that B D_new^-1 = B_old D_old^-1 (F^{sn})^-1: the same velocity gradient, now
    measured in the new configuration (D = sum w r r^T, the APIC inertia)."""
    C = state.affine @ linalg.inv(_moment(old.kernel, old.kernel.offset_axes, old.kernel.offset_axes))
    return C @ linalg.inv(old.Fsn) @ _moment(k, k.offset_axes, k.offset_axes)


def _rebuild(model: Model, state: State, dt: float, contact: bool = False) -> State:
    """Make the current configuration the reference: F^{0s} <- F, F^{sn} <- I, new kernel."""
    k = compute_kernel(model, state.x, state.cell)
    if k.n_lost:
        raise _lost_error(model, state, k, dt)
    old = state.reference
    affine = state.affine
    if old is not None and model.transfer == "apic":
        affine = _apic_to_new_reference(state, old, k)
    cluster = gaps = None
    if model.reference == "adaptive" and model.contact_margin is not None:
        cluster, gaps = _clusters(model, k)
    d, n = model.dim, len(state.x)
    eye = linalg.identity_like(state.F)[:, :, None].expand(d, d, n).contiguous()
    ref = Reference(
        kernel=k, F0s=_matrices(_components(state.F).contiguous()), Fsn=_matrices(eye),
        nodes=model.node_positions.T.clone(), active=_support(model, k),
        rebuilds=(old.rebuilds if old is not None else 0) + 1,
        contact_rebuilds=(old.contact_rebuilds if old is not None else 0) + int(contact),
        cluster=cluster, gaps=gaps, operators=_operators(model, state, k),
    )
    ref = replace(ref, wall_gap=_wall_gap(model, ref))
    cell = k.cell if k.cell is not None else state.cell
    return replace(state, reference=ref, affine=affine, cell=cell)


def _support(model: Model, k: KernelResult) -> torch.Tensor:
    """(N,) bool: the nodes in the support of kernel k."""
    active = torch.zeros(model.n_nodes, dtype=torch.bool, device=k.index.device)
    active[k.index[k.index >= 0]] = True
    return active


def _wall_gap(model: Model, ref: Reference) -> float:
    """The smallest distance at s from an active node to the band [-tol, depth] of heights above
    a wall plane (tangential extents ignored: a lower bound); 0 without wall planes."""
    if not model.wall_planes:
        return 0.0
    table = model._walls
    height = (table["normal"] @ ref.nodes - table["offset"])[:, ref.active]
    gap = torch.maximum(table["low"] - height, height - table["high"])
    return max(float(gap.min()), 0.0) if gap.numel() else 0.0


def _contact_due(model: Model, ref: Reference) -> bool:
    """The contact trigger: two clusters may have come within contact_margin cells."""
    if ref.gaps is None or ref.gaps.shape[0] < 2:
        return False
    if 2.0 * ref.drift < float(ref.gaps.min()) - model.contact_margin * model.cell_size:
        return False  # D_a + D_b <= 2 drift: no pair can be due
    active = ref.cluster >= 0
    moved = (ref.nodes - model.node_positions.T).norm(dim=0)[active]
    D = moved.new_zeros(ref.gaps.shape[0]).scatter_reduce(0, ref.cluster[active], moved, "amax")
    return bool(((D[:, None] + D[None, :]) >= ref.gaps - model.contact_margin * model.cell_size).any())


def _step_reference(model: Model, state: State, dt: float) -> State:
    """One step in the total/adaptive modes (A-ULMPM App. B with this solver's transfers)."""
    ref = state.reference
    if ref is None or ref.kernel is None:
        state = _rebuild(model, state, dt)
    elif ref.stale:
        state = _rebuild(model, state, dt, contact=ref.stale == "contact")
    if state.reference.operators is not None:
        new, v_nodes = _transfer_by_operators(model, state, dt)
    else:
        k = state.reference.kernel
        p2g, g2p = TRANSFERS[model.transfer]
        grid = grid_update(model, state, p2g(model, state, k), dt)
        if model.grips:
            grid = _hold_grips(model, state, k, grid)
        new, v_nodes = g2p(model, state, k, grid, dt), grid.v_new
    if model.grips:
        new = _move_grips(model, state, new, dt)
    _check_finite(model, state, new, dt)
    speed = float(v_nodes.abs().max()) * math.sqrt(model.dim) if v_nodes.numel() else 0.0  # >= max_i |v_i|
    ref = replace(new.reference, nodes=state.reference.nodes + dt * v_nodes, drift=new.reference.drift + dt * speed)
    if model.reference == "adaptive":
        marked = ((_det(_components(ref.Fsn)) - 1.0).abs() >= model.epsilon).to(ref.Fsn.dtype).mean()
        if float(marked) >= model.fraction:  # A-ULMPM eq. 33
            ref = replace(ref, stale="strain")
        elif _contact_due(model, ref):
            ref = replace(ref, stale="contact")
    return replace(new, reference=ref, time=state.time + dt, step=state.step + 1)


# ----------------------------------------------------------------------------- fixed transfer operators
# Between updates of the reference configuration the weights and gradients do not change, so
# P2G and G2P are fixed sparse products, built once per update (:class:`Operators`). The
# particle matrices of this path (F^{0s}, F^{sn}, F, stresses) are stored by component, (d, d, P)
# in memory, and handed out as (P, d, d) views: 2x2 / 3x3 algebra is then a few operations on
# contiguous vectors instead of batched matrix products of tiny matrices.
OPERATOR_TRANSFERS = ("flip", "pic", "apic")  # musl keeps the slot path


def _components(a: torch.Tensor) -> torch.Tensor:
    """(P, d, d) matrices -> the (d, d, P) view of their components."""
    return a.permute(1, 2, 0)


def _matrices(c: torch.Tensor) -> torch.Tensor:
    """(d, d, P) components -> the (P, d, d) view of the matrices."""
    return c.permute(2, 0, 1)


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Products a_p b_p of matrices given by components (d, d, P) -> (d, d, P)."""
    out = a[:, 0, None] * b[None, 0]
    for j in range(1, a.shape[1]):
        out.addcmul_(a[:, j, None], b[None, j])
    return out


def _det(a: torch.Tensor) -> torch.Tensor:
    """Determinants of matrices given by components (d, d, P) -> (P,)."""
    if a.shape[0] == 2:
        return a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    return linalg.det(_matrices(a))


def _inv(a: torch.Tensor) -> torch.Tensor:
    """Inverses of matrices given by components (d, d, P) -> (d, d, P)."""
    if a.shape[0] == 2:
        adjugate = torch.stack([a[1, 1], -a[0, 1], -a[1, 0], a[0, 0]]).view(a.shape)
        return adjugate / _det(a)
    return _components(linalg.inv(_matrices(a)))


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
    inv_mass, active: (N,) 1/m_i and 1.0 on the active nodes, 0 elsewhere.
    inertia_inv: (d, d, P) D_p^-1 by component (APIC), else None.
    """

    gather: torch.Tensor
    weight: torch.Tensor | None
    scatter: torch.Tensor
    force: torch.Tensor
    inv_mass: torch.Tensor
    active: torch.Tensor
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


def _operators(model: Model, state: State, k: KernelResult) -> Operators | None:
    """The transfer operators of kernel k (None for transfers that keep the slot path)."""
    if model.transfer not in OPERATOR_TRANSFERS:
        return None
    n_p, n_k = k.index.shape
    n = model.n_nodes
    valid = k.index >= 0
    p = torch.arange(n_p, device=k.index.device)[:, None].expand(n_p, n_k)[valid]
    i = k.index[valid]
    w = k.weight[valid]
    grads = list(k.grad_axes[:, valid])
    offsets = [w * r for r in k.offset_axes[:, valid]] if model.transfer == "apic" else []

    def stacked(blocks: list[torch.Tensor], by_node: bool) -> torch.Tensor:
        rows = p.repeat(len(blocks)) + torch.arange(len(blocks), device=p.device).repeat_interleave(len(p)) * n_p
        if by_node:
            return _csr(i.repeat(len(blocks)), rows, torch.cat(blocks), (n, len(blocks) * n_p))
        return _csr(rows, i.repeat(len(blocks)), torch.cat(blocks), (len(blocks) * n_p, n))

    m, v0 = state.mass[p], state.volume0[p]
    mass = _scatter(k, (k.weight * state.mass[:, None])[None], n)[0]
    active = mass > _MASS_FLOOR * state.mass.mean()
    inertia_inv = None
    if model.transfer == "apic":
        inertia_inv = _components(linalg.inv(_moment(k, k.offset_axes, k.offset_axes))).contiguous()
    gather = stacked([w, *grads, *offsets], by_node=False)
    return Operators(
        gather=gather, weight=_leading_rows(gather, n_p) if model.transfer == "flip" else None,
        scatter=stacked([m * w, *(m * o for o in offsets)], by_node=True),
        force=stacked([-v0 * g for g in grads], by_node=True),
        inv_mass=torch.where(active, 1.0 / torch.where(active, mass, 1.0), 0.0),
        active=active.to(mass.dtype), inertia_inv=inertia_inv,
    )


def _transfer_by_operators(model: Model, state: State, dt: float) -> tuple[State, torch.Tensor]:
    """P2G, grid update and G2P of one step by the fixed operators (FLIP, PIC or APIC).

    Every product is a sparse matrix times one vector, one per axis. Returns the new state
    (without the grips' prescribed motion) and the constrained new nodal velocities (d, N).
    Same equations as the slot path: A-ULMPM App. B eqs. 44-47.
    """
    ref = state.reference
    ops, d = ref.operators, model.dim
    Fsn = _components(ref.Fsn)
    stress = _mm(_components(_stress(model, state)), _inv(Fsn).transpose(0, 1))  # tau (F^{sn})^-T
    particle = state.v.T.contiguous()  # (d, P)
    if model.transfer == "apic":  # nodes see v_p + C_p (x_i - x_p), C = B D^-1 (UMLS eq. 48)
        C = _mm(_components(state.affine), ops.inertia_inv)  # (a, b, P)
        particle = torch.cat([particle[:, None], C], 1).view(d, -1)
    momentum = torch.stack([ops.scatter @ row for row in particle])
    force = torch.stack([ops.force @ row for row in stress.reshape(d, -1)])
    v_old = momentum * ops.inv_mass
    v_new = torch.addcmul(v_old, force, ops.inv_mass, value=dt)
    if model.gravity.any():
        v_new.addcmul_(ops.active, dt * model.gravity[:, None])
    if model.damping:
        v_new = v_new / (1.0 + model.damping * dt)
    v_new = constrain(model, state, v_new)
    for grip, velocity in _held(model, state):
        index = ref.kernel.index[grip.ids]
        v_new[:, torch.unique(index[index >= 0])] = velocity[:, None]
    out = torch.stack([ops.gather @ row for row in v_new]).view(d, -1, len(state.x))  # (a, J, P)
    x = state.x + dt * out[:, 0].T
    if model.transfer == "flip":
        v = state.v + torch.stack([ops.weight @ row for row in v_new - v_old], 1)
    else:
        v = out[:, 0].T.contiguous()
    grad_v = out[:, 1:1 + d]  # (a, b, P): d v_a / d X^s_b
    Fsn_new = torch.add(Fsn, grad_v, alpha=dt)  # A-ULMPM eqs. 45-47
    fields = {"x": x, "v": v, "F": _matrices(_mm(Fsn_new, _components(ref.F0s))),
              "reference": replace(ref, Fsn=_matrices(Fsn_new))}
    if model.transfer == "apic":  # B_p = sum_i w_ip v_i (x_i - x_p)^T
        fields["affine"] = _matrices(out[:, 1 + d:])
    if model.viscous:  # grad_x v = grad_s v (F^{sn})^-1
        fields["velocity_gradient"] = _matrices(_mm(grad_v, _inv(Fsn)))
    return replace(state, **fields), v_new


# ----------------------------------------------------------------------------- diagnostics
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

