"""Explicit MPM (UMLS Algorithm 1): a static :class:`Model`, an evolving :class:`State`, and
``step(model, state, dt) -> state``.

One step: the kernel of every particle is computed by one call (:func:`compute_kernel`,
whose result a caller may cache and pass back in), P2G scatters mass, momentum and internal
force in one pass, nodal velocities are integrated and constrained, and G2P updates
particle velocities (FLIP, PIC, APIC or FLIP with MUSL), positions and deformation gradients.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from . import linalg
from .boundary import apply_conditions
from .kernels import Grid, KernelResult, MeshTables, bspline_kernel, linear_kernel, umls_kernel
from .locate import LocateStatus
from .materials import Material

__all__ = [
    "Model", "State", "SimulationError", "step", "compute_kernel", "cfl_time_step", "diagnostics",
    "kirchhoff_stress", "KERNELS", "TRANSFERS",
]

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
    """

    background: MeshTables | Grid
    kernel: str
    transfer: str
    materials: tuple[tuple[Material, torch.Tensor | None], ...]
    conditions: tuple
    gravity: torch.Tensor
    node_positions: torch.Tensor
    h_cfl: float

    def __post_init__(self):
        if self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {self.kernel!r}; choose one of {sorted(KERNELS)}")
        if self.transfer not in TRANSFERS:
            raise ValueError(f"unknown transfer {self.transfer!r}; choose one of {sorted(TRANSFERS)}")
        if (self.kernel == "bspline") != isinstance(self.background, Grid):
            raise ValueError("the bspline kernel needs a Grid background and the mesh kernels MeshTables")

    @property
    def n_nodes(self) -> int:
        return self.node_positions.shape[0]

    @property
    def dim(self) -> int:
        return self.node_positions.shape[1]

    @property
    def wave_speed(self) -> float:
        return max(m.wave_speed for m, _ in self.materials)


@dataclass(frozen=True)
class State:
    """Particle state at one time.

    x, v: (P, d); F: (P, d, d) deformation gradient; affine: (P, d, d) APIC matrix B_p (zero
    for FLIP/PIC); volume0, mass: (P,); cell: (P,) last containing cell (-1 unknown), a hint
    for the cell search; time; step.
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
    f_int_i = -sum_p V_p^0 tau_p grad w_ip with tau = J sigma the Kirchhoff stress.
    """
    d = model.dim
    wm = k.weight * state.mass[:, None]
    coef = kirchhoff_stress(model, state.F) * (-state.volume0[:, None, None])
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


def grid_update(model: Model, state: State, nodal: torch.Tensor, dt: float) -> Nodal:
    """Nodal velocities before and after the update, constrained (UMLS eq. 13, Alg. 1 l. 6)."""
    d = model.dim
    mass, momentum, force = nodal[0], nodal[1:1 + d], nodal[1 + d:]
    active = mass > _MASS_FLOOR * state.mass.mean()
    safe = torch.where(active, mass, torch.ones_like(mass))
    v = torch.where(active, momentum / safe, 0.0)
    accel = force / safe + model.gravity[:, None]  # gravity: f_ext = m_i g (UMLS eq. 11)
    v_new = torch.where(active, v + dt * accel, 0.0)
    return Nodal(mass=torch.where(active, mass, 0.0), v=v, v_new=apply_conditions(v_new, model.conditions))


def _deform(F: torch.Tensor, k: KernelResult, v_slots: torch.Tensor, dt: float) -> torch.Tensor:
    """F <- (I + dt sum_i v_i grad w_ip^T) F (UMLS eq. 17); v_slots: (d, P, K)."""
    grad_v = torch.bmm(v_slots.permute(1, 0, 2), k.grad_axes.permute(1, 2, 0))
    return F + dt * torch.bmm(grad_v, F)


def g2p_flip(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """FLIP: v_p += sum w (v~_i - v_i) (UMLS eq. 16); x_p += dt sum w v~_i (eq. 15)."""
    d = model.dim
    slots = _gather(k, torch.cat([grid.v_new, grid.v_new - grid.v]))
    moved_dv = _interpolate(k, slots)
    x = state.x + dt * moved_dv[:, :d]
    return replace(state, x=x, v=state.v + moved_dv[:, d:], F=_deform(state.F, k, slots[:d], dt))


def g2p_pic(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """PIC: v_p = sum w v~_i."""
    vi = _gather(k, grid.v_new)
    v = _interpolate(k, vi)
    return replace(state, x=state.x + dt * v, v=v, F=_deform(state.F, k, vi, dt))


def g2p_apic(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """APIC (UMLS eq. 49): v_p = sum w v~_i, B_p = sum w v~_i (x_i - x_p)^T."""
    vi = _gather(k, grid.v_new)
    v = _interpolate(k, vi)
    B = _moment(k, vi, k.offset_axes)
    return replace(state, x=state.x + dt * v, v=v, F=_deform(state.F, k, vi, dt), affine=B)


def g2p_musl(model: Model, state: State, k: KernelResult, grid: Nodal, dt: float) -> State:
    """FLIP velocities with the modified update-stress-last strain: F is updated with nodal
    velocities re-mapped from the new particle velocities, sum w m_p v_p^{n+1} / m_i, which
    stay bounded on nodes of tiny mass (the usual remedy for the linear hat's instability)."""
    new = g2p_flip(model, state, k, grid, dt)
    wm = k.weight * state.mass[:, None]
    momentum = _scatter(k, torch.stack([wm * new.v[:, a, None] for a in range(model.dim)]), model.n_nodes)
    active = grid.mass > 0
    v_map = torch.where(active, momentum / torch.where(active, grid.mass, 1.0), 0.0)
    v_map = apply_conditions(v_map, model.conditions)
    return replace(new, F=_deform(state.F, k, _gather(k, v_map), dt))


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
    """
    k = kernel if kernel is not None else compute_kernel(model, state.x, state.cell)
    if k.n_lost:
        raise _lost_error(model, state, k, dt)
    p2g, g2p = TRANSFERS[model.transfer]
    new = g2p(model, state, k, grid_update(model, state, p2g(model, state, k), dt), dt)
    if not bool(torch.isfinite(new.x.sum() + new.v.sum() + new.F.sum())):
        raise SimulationError(_advice(model, state, dt, "the state became non-finite (NaN or inf)"))
    cell = k.cell if k.cell is not None else state.cell
    return replace(new, cell=cell, time=state.time + dt, step=state.step + 1)


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

