"""CSMPM's coupling: MPM solids on the gas grid, one pressure solve for both (thesis §3.2.2–3.2.8).

A step follows the thesis' Algorithm 3.1 in its order:

1. **P2G.** Solid particles (any body mesh of the package, any material of
   :mod:`datagen.mpm.materials`, plastic ones with their return map) spread mass and APIC momentum
   with quadratic B-splines onto the gas grid's **faces** (one staggered node set per axis, a
   MAC layout), and volume and ghost strain J^g onto its cells.
2. **Moving interface.** A cell whose solid volume fraction is at least a half is a *solid cell*.
   Each face's blocked fraction beta comes from the larger solid volume V of its two cells, as if
   V were a ball (2D: the ball's diameter 2 sqrt(V / pi) over dx; 3D: its cross-section pi
   (3 V / 4 pi)^(2/3) over dx^2; 1D: V / dx; capped at 1).
3. **Advection** of the gas (:func:`datagen.csmpm.euler.advect`): every face's WENO-LLF flux is
   the blend (1 - beta) passable + beta reflective (the reflective flux carries nothing through
   the face); stencils reaching into solid cells take the face-side gas value. The gas inside
   solid cells stays where it is (mass is conserved to round-off).
4. **Coupled pressure solve.** One pressure per cell: the gas's (K = rho c^2, p* from the
   equation of state) or, in a solid cell, the solid's ghost pressure p^g = p0 - lambda^g (J^g - 1)
   (K = lambda^g J^g; thesis eqs. 3.17, 3.19; ``p0`` the pressure a solid at J^g = 1 carries,
   by default the gas pressure around it, so that a body at rest in still gas stays at rest). Each
   interior face carries one normal velocity shared by gas and solid (the slip condition 3.6)
   with the lumped mass m_f = (1 - beta) rho_f V + m^s_f; eliminating it (eqs. 3.35–3.36) leaves
   the SPD system  V p / (K dt^2) + sum_f A^2 / m_f (p - p_nb) = V p* / (K dt^2) - A sum +-u*_f / dt,
   the gas-only system of :mod:`~datagen.csmpm.euler` where no solid is; pressure is continuous
   across the interface by construction (3.7). Jacobi-preconditioned CG.
5. **Corrections.** Each interior face's impulse -dt A (p_R - p_L) is shared between the phases:
   the solid takes the share m^s_f / m_f of it and all of the half that belongs to a solid cell,
   the gas the rest (Kwatra's cell update with face pressures where no solid is), so the impulse
   gas and solid exchange balances to round-off. The gas's energy changes by the work p_f u_f of
   its faces; at a face between a gas and a solid cell only the gas side's (the work on the solid).
6. **MPM grid update** after the coupled solve (the thesis' order, §3.2.8): elastic forces
   -sum_p V0 tau grad w, gravity; the domain's ends are separable slip walls (face nodes at or
   past an end keep no normal velocity into it), and so are the faces between static solid cells
   and the rest.
7. **G2P**: velocities and APIC affine matrices, F <- (I + dt C) F (then the material's return
   map), J^g <- J^g (1 + dt tr C) (eq. 3.20), positions.

Why faces and not the thesis' B2B1 (which the gas alone takes: :mod:`~datagen.csmpm.b2b1`): with
the gas's velocities on faces (the B1B0 layout of :mod:`~datagen.csmpm.euler`), putting the
solid's velocity on the same faces gives both phases one velocity per face and one pressure per
cell, so the coupled system is the gas's system with other coefficients and no interface
unknowns (the h and Y blocks of eq. 3.34 vanish), and the solid's update is the exact transpose
of the divergence the solve used (eq. 3.36, the stable choice of the thesis' Fig. 3.3).
Quadratic B-splines keep the solid's velocity field C^1 for the elastic forces.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from dataclasses import dataclass

import numpy as np
import torch

from . import euler
from .gas import GAMMA, pressure, sound_speed

__all__ = ["Solid", "CoupledInfo", "step", "time_step", "blocked_fraction", "solid_energy"]


@dataclass
class Solid:
    """MPM particles on the gas grid: positions ``x`` (P, d), velocities ``v``, APIC matrices ``C``
    (P, d, d), deformation gradients ``F`` (the elastic part for plastic materials), rest volumes
    ``volume`` and masses ``mass`` (P,), ghost strains ``Jg`` (P,), the ``material``, the ghost
    stiffness ``ghost`` (lambda^g, Pa) and ``p0``, the pressure the solid carries at J^g = 1."""

    x: np.ndarray
    v: np.ndarray
    C: np.ndarray
    F: np.ndarray
    volume: np.ndarray
    mass: np.ndarray
    Jg: np.ndarray
    material: object
    ghost: float
    p0: float = 0.0
    plastic_strain: np.ndarray | None = None
    out_of_plane: np.ndarray | None = None

    @classmethod
    def from_mesh(cls, mesh, material, *, velocity=None, p0: float = 0.0, ghost: float | None = None) -> Solid:
        """One particle per mesh node (so the body's mesh moves with the particles), its volume the
        node's share of the cells around it (each cell's measure split evenly among its nodes);
        ``ghost`` defaults to the material's first Lamé parameter (the thesis' lambda^g), or its
        bulk modulus where that is not positive."""
        nodes, cells = np.asarray(mesh.nodes, np.float64), np.asarray(mesh.cells)
        x = nodes.copy()
        share = np.repeat(np.asarray(mesh.cell_measures, np.float64) / cells.shape[1], cells.shape[1])
        volume = np.bincount(cells.ravel(), share, minlength=len(nodes))
        n, d = x.shape
        v = np.zeros((n, d)) if velocity is None else np.broadcast_to(np.asarray(velocity, np.float64), (n, d)).copy()
        if ghost is None:
            ghost = material.lam if material.lam > 0 else material.lam + 2.0 * material.mu / 3.0
        if not ghost > 0:
            raise ValueError(f"the ghost stiffness lambda^g must be > 0, got {ghost}")
        plastic = getattr(material, "plastic", False)
        return cls(x=x, v=v, C=np.zeros((n, d, d)), F=np.tile(np.eye(d), (n, 1, 1)), volume=volume,
                   mass=material.density * volume, Jg=np.ones(n), material=material, ghost=float(ghost), p0=float(p0),
                   plastic_strain=np.zeros(n) if plastic else None,
                   out_of_plane=np.zeros(n) if plastic and d == 2 else None)

    def copy(self) -> Solid:
        return dataclasses.replace(self, **{f.name: getattr(self, f.name).copy() for f in dataclasses.fields(self)
                                            if isinstance(getattr(self, f.name), np.ndarray)})

    @property
    def momentum(self) -> np.ndarray:
        return (self.mass[:, None] * self.v).sum(axis=0)


@dataclass(frozen=True)
class CoupledInfo:
    """What a coupled step did: dt, CG iterations and relative residual, the cell pressures
    (gas or ghost), the solid cells and how many gas cells had their pressure floored."""

    dt: float
    cg_iterations: int
    residual: float
    pressure: np.ndarray
    solid_cells: np.ndarray
    floored: int = 0


def blocked_fraction(volume: np.ndarray, dx: float, dim: int) -> np.ndarray:
    """The fraction of a face a solid of volume V blocks, the solid taken as a ball (module
    docstring, step 2)."""
    volume = np.maximum(volume, 0.0)
    if dim == 1:
        width = volume / dx
    elif dim == 2:
        width = 2.0 * np.sqrt(volume / np.pi) / dx
    else:
        width = np.pi * (3.0 * volume / (4.0 * np.pi)) ** (2.0 / 3.0) / dx ** 2
    return np.minimum(width, 1.0)


# ----------------------------------------------------------------------------------- B-splines

@dataclass(frozen=True)
class _Stencil:
    """Quadratic B-spline weights of particles on a node set at (k + shift) dx: ``base`` (P, d)
    the first of three nodes per axis, ``w``/``dw`` (P, d, 3) weights and their x-derivatives,
    ``f`` (P, d) the particle's offset from the base node in cells."""

    base: np.ndarray
    w: np.ndarray
    dw: np.ndarray
    f: np.ndarray
    shape: tuple[int, ...]

    @functools.cached_property
    def nodes(self) -> list[tuple]:
        """Per node of the 3^d stencil: (flat index or -1 outside the grid, weight (P,), weight
        gradient (P, d), offset x_i - x_p over dx (P, d)); made once, read by every transfer of the
        step (P2G of mass and momentum, the elastic forces, G2P)."""
        return list(self._nodes())

    def _nodes(self):
        d = self.base.shape[1]
        rows = np.arange(self.base.shape[0])
        for offset in itertools.product(range(3), repeat=d):
            index = self.base + np.asarray(offset)
            inside = np.all((index >= 0) & (index < np.asarray(self.shape)), axis=1)
            flat = np.where(inside, np.ravel_multi_index(tuple(np.clip(index, 0, np.asarray(self.shape) - 1).T),
                                                         self.shape), -1)
            ws = [self.w[rows, a, offset[a]] for a in range(d)]
            weight = np.prod(ws, axis=0)
            gradient = np.stack([self.dw[rows, a, offset[a]] * np.prod([ws[b] for b in range(d) if b != a], axis=0)
                                 for a in range(d)], axis=1)
            yield flat, weight, gradient, np.asarray(offset) - self.f


def _stencil(x: np.ndarray, dx: float, shift: np.ndarray, shape: tuple[int, ...]) -> _Stencil:
    s = x / dx - shift
    base = np.floor(s - 0.5).astype(np.int64)
    f = s - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)
    dw = np.stack([f - 1.5, -2.0 * (f - 1.0), f - 0.5], axis=-1) / dx
    return _Stencil(base, w, dw, f, shape)


def _scatter(stencil: _Stencil, values) -> np.ndarray:
    """sum_p w_ip values_p on the nodes; ``values`` (P,) or a callable (weight, gradient, offset) -> (P,)."""
    size = int(np.prod(stencil.shape))
    out = np.zeros(size)
    for flat, weight, gradient, offset in stencil.nodes:
        contribution = values(weight, gradient, offset) if callable(values) else weight * values
        keep = flat >= 0
        out += np.bincount(flat[keep], contribution[keep], minlength=size)
    return out.reshape(stencil.shape)


PAD = 2  # ghost nodes past each end of every axis, so that no particle's stencil leaves the node set


def _face_stencils(x: np.ndarray, grid: euler.Grid) -> list[_Stencil]:
    """Per axis the particles' stencils on that axis's face nodes, padded by PAD nodes past both
    ends of every axis (node k of axis a's set sits at (k - PAD) dx along a and (k - PAD + 1/2) dx
    along the others)."""
    out = []
    for axis in range(grid.dim):
        shift = np.full(grid.dim, 0.5 - PAD)
        shift[axis] = -PAD
        shape = [n + 2 * PAD for n in grid.shape]
        shape[axis] += 1
        out.append(_stencil(x, grid.dx, shift, tuple(shape)))
    return out


def _crop(array: np.ndarray) -> np.ndarray:
    """The grid's own nodes of a padded node array (a view)."""
    return array[(slice(PAD, -PAD),) * array.ndim]


# ----------------------------------------------------------------------------------- the step

def _interior(array: np.ndarray, axis: int) -> np.ndarray:
    """The interior faces (indices 1 .. n - 1 along ``axis``) of a face array (a view)."""
    index = [slice(None)] * array.ndim
    index[axis] = slice(1, array.shape[axis] - 1)
    return array[tuple(index)]


def _kirchhoff(solid: Solid) -> np.ndarray:
    F = torch.from_numpy(solid.F)
    if solid.out_of_plane is not None:
        return solid.material.kirchhoff(F, torch.from_numpy(solid.out_of_plane)).numpy()
    return solid.material.kirchhoff(F).numpy()


def time_step(state: np.ndarray, solid: Solid, grid: euler.Grid, cfl: float = 0.5) -> float:
    """The gas's flow-speed limit (:func:`datagen.csmpm.euler.time_step`) and the solid's explicit
    elastic limit cfl dx / (|v| + sqrt((lambda + 2 mu) / rho)), whichever is smaller."""
    wave = float(np.sqrt((solid.material.lam + 2.0 * solid.material.mu) / solid.material.density))
    speed = float(np.abs(solid.v).max(initial=0.0)) + wave
    return min(euler.time_step(state, grid, cfl), cfl * grid.dx / speed)


def _solid_on_grid(solid: Solid, grid: euler.Grid):
    """P2G: per axis the face nodes' solid mass and momentum (padded: :func:`_face_stencils`); per
    cell the solid volume and J^g."""
    stencils = _face_stencils(solid.x, grid)
    masses, momenta = [], []
    for axis, stencil in enumerate(stencils):
        masses.append(_scatter(stencil, solid.mass))
        affine = solid.C[:, axis, :]
        momenta.append(_scatter(stencil, lambda w, g, o, a=axis, c=affine:
                                w * solid.mass * (solid.v[:, a] + grid.dx * (c * o).sum(axis=1))))
    cells = _stencil(solid.x, grid.dx, np.full(grid.dim, 0.5 - PAD), tuple(n + 2 * PAD for n in grid.shape))
    current = solid.volume * np.linalg.det(solid.F)
    volume = _crop(_scatter(cells, current))
    ghost = _crop(_scatter(cells, current * solid.Jg))
    Jg = np.where(volume > 0, ghost / np.where(volume > 0, volume, 1.0), 1.0)
    return stencils, masses, momenta, volume, Jg


def _blocked_faces(volume: np.ndarray, grid: euler.Grid) -> list[np.ndarray]:
    """Per axis the faces' blocked fractions (n + 1 along it) from the larger solid volume of the
    two cells (the edge cell's at the domain's ends); static solids block their faces wholly."""
    out = []
    for axis in range(grid.dim):
        below, above = euler._pairs(volume, axis, grid)
        ends = [np.take(volume, [0], axis=axis), np.take(volume, [-1], axis=axis)]
        faces = blocked_fraction(np.concatenate([ends[0], np.maximum(below, above), ends[1]], axis=axis),
                                 grid.dx, grid.dim)
        if grid.solid is not None:
            static = euler._solid_sides(axis, grid)
            inner = _interior(faces, axis)
            inner[static[0] | static[1]] = 1.0
        out.append(faces)
    return out


def _face_system(advected: np.ndarray, moving: np.ndarray, blocked: list, solid_mass: list, solid_momentum: list,
                 grid: euler.Grid):
    """Per axis the faces' velocities u* before the solve (interior faces: gas and solid mixed by
    their lumped masses), the coefficients V / m_f of the pressure system (0 on faces without
    mass or next to static solids) and the solid's share m^s_f / m_f of each interior face."""
    d, volume_cell = grid.dim, grid.dx ** grid.dim
    rho = advected[0]
    gas_velocity = advected[1:-1] / rho
    u_star, coefficients, shares = [], [], []
    for axis in range(d):
        faces = euler._faces(gas_velocity[axis], axis, grid, "velocity")  # boundaries and static solids
        below, above = euler._pairs(gas_velocity[axis], axis, grid)
        gas_below, gas_above = (~m for m in euler._pairs(moving, axis, grid))
        u_gas = np.where(gas_below & ~gas_above, below, np.where(gas_above & ~gas_below, above, 0.5 * (below + above)))
        rho_f = 0.5 * np.add(*euler._pairs(rho, axis, grid))
        m_gas = (1.0 - _interior(blocked[axis], axis)) * rho_f * volume_cell
        m_solid, q_solid = _interior(_crop(solid_mass[axis]), axis), _interior(_crop(solid_momentum[axis]), axis)
        m_face = m_gas + m_solid
        open_face = m_face > 1e-300
        if grid.solid is not None:
            sides = euler._solid_sides(axis, grid)
            open_face &= ~(sides[0] | sides[1])
        safe = np.where(open_face, m_face, 1.0)
        _interior(faces, axis)[:] = np.where(open_face, (m_gas * u_gas + q_solid) / safe, 0.0)
        u_star.append(faces)
        coefficients.append(np.where(open_face, volume_cell / safe, 0.0))
        shares.append(np.where(open_face, m_solid / safe, 0.0))
    return u_star, coefficients, shares


def _corrections(advected: np.ndarray, p: np.ndarray, system, moving: np.ndarray, solid_mass: list,
                 solid_momentum: list, grid: euler.Grid, dt: float, ends: list):
    """The gas after the pressure correction (face pressures less the solid's share of each
    face's impulse; energy by the faces' work) and per axis the solid's face-node velocities
    with its share added (module docstring, step 5)."""
    u_star, coefficients, shares = system
    d, dx, volume_cell = grid.dim, grid.dx, grid.dx ** grid.dim
    out = advected.copy()
    energy_flux, solid_velocity = [], []
    for axis in range(d):
        below, above = euler._pairs(p, axis, grid)
        impulse = -dt * (above - below) / dx  # the face's momentum change per unit cell volume
        solid_below, solid_above = euler._pairs(moving, axis, grid)
        has_solid = _interior(_crop(solid_mass[axis]), axis) > 0
        share = shares[axis]
        take_below = np.where(has_solid, share + (1.0 - share) * solid_below, 0.0)
        take_above = np.where(has_solid, share + (1.0 - share) * solid_above, 0.0)
        u_f = u_star[axis].copy()
        p_f = euler._faces(p, axis, grid, "pressure")
        euler.correct_outlets(u_f, p_f, p, ends, axis)  # outlets coupled to the far field
        out[1 + axis] -= dt * euler._difference(p_f, axis, grid)
        lower, upper = [slice(None)] * d, [slice(None)] * d
        lower[axis], upper[axis] = slice(0, grid.shape[axis] - 1), slice(1, grid.shape[axis])
        out[1 + axis][tuple(lower)] -= 0.5 * impulse * take_below  # the solid's part, taken from the gas
        out[1 + axis][tuple(upper)] -= 0.5 * impulse * take_above
        to_solid = 0.5 * impulse * (take_below + take_above) * volume_cell
        mass = solid_mass[axis]
        velocity = np.divide(solid_momentum[axis], mass, out=np.zeros_like(mass), where=mass > 0)
        inner = _interior(_crop(velocity), axis)  # a view
        inner += np.divide(to_solid, _interior(_crop(mass), axis), out=np.zeros_like(to_solid), where=has_solid)
        solid_velocity.append(velocity)
        _interior(u_f, axis)[:] += coefficients[axis] * impulse
        energy_flux.append(p_f * u_f)
    out[-1] -= dt * euler._divergence(energy_flux, grid)
    return out, solid_velocity


def _cavitation_floor(out: np.ndarray, state: np.ndarray, gas_cells: np.ndarray, gamma: float,
                      floor_ratio: float) -> int:
    """Where a solid pulls away faster than gas can follow (a body lifting off a wall), the
    continuous pressure would go below zero: the gas cavitates. Floors the pressure of such gas
    cells of ``out`` (in place) at ``floor_ratio`` times the step's mean gas pressure; returns how
    many there were."""
    floor = floor_ratio * float(np.mean(pressure(state, gamma), where=gas_cells)) if gas_cells.any() else 0.0
    low = gas_cells & (pressure(out, gamma) < floor)
    if low.any():
        kinetic = 0.5 * (out[1:-1, low] ** 2).sum(axis=0) / out[0, low]
        out[-1, low] = kinetic + floor / (gamma - 1.0)
    return int(low.sum())


def step(state: np.ndarray, solid: Solid, grid: euler.Grid, dt: float, *, gravity=None, gamma: float = GAMMA,
         rtol: float = 1e-10, floor_ratio: float = 1e-3) -> tuple[np.ndarray, Solid, CoupledInfo]:
    """One coupled step of dt (module docstring): the gas state (d + 2, *cells) and the solid
    after it, and what the step did. ``grid.solid`` may hold static solid cells besides. A gas
    cell whose pressure would fall below ``floor_ratio`` times the step's mean gas pressure is
    held there (cavitation; energy is added, counted in the info's ``floored``)."""
    stencils, solid_mass, solid_momentum, solid_volume, Jg = _solid_on_grid(solid, grid)
    moving = solid_volume >= 0.5 * grid.dx ** grid.dim
    static = np.zeros(grid.shape, bool) if grid.solid is None else grid.solid
    blocked = _blocked_faces(solid_volume, grid)
    advected = euler.advect(state, dataclasses.replace(grid, solid=moving | static), dt,
                            passable=[1.0 - b for b in blocked])
    stiffness = np.where(moving, solid.ghost * Jg, state[0] * sound_speed(state[0], pressure(state, gamma), gamma) ** 2)
    p_star = np.where(moving, solid.p0 - solid.ghost * (Jg - 1.0), pressure(advected, gamma))
    system = _face_system(advected, moving, blocked, solid_mass, solid_momentum, grid)
    diagonal = (1.0 / (stiffness * dt ** 2)).ravel()
    rhs = diagonal * p_star.ravel() - euler._divergence(system[0], grid).ravel() / dt
    ends = euler.outlet_ends(advected, system[0], grid, dt, gamma)
    outlet_diagonal, outlet_rhs = euler.outlet_terms(ends, grid)
    p, iterations, residual = euler.solve_pressure(system[1], diagonal + outlet_diagonal, rhs + outlet_rhs, p_star,
                                                   grid, dt, rtol)
    out, solid_velocity = _corrections(advected, p, system, moving, solid_mass, solid_momentum, grid, dt, ends)
    keep = moving | static  # the gas inside solids stays as advected (its impulse went to the solid)
    out[:, keep] = advected[:, keep]
    floored = _cavitation_floor(out, state, ~keep, gamma, floor_ratio)
    new_solid = _mpm_update(solid, grid, stencils, solid_mass, solid_velocity, dt, gravity)
    return out, new_solid, CoupledInfo(dt, iterations, residual, p, moving, floored)


def _mpm_update(solid: Solid, grid: euler.Grid, stencils, masses, velocities, dt: float, gravity) -> Solid:
    """The MPM grid update (elastic forces, gravity, walls) on the face nodes, then G2P."""
    d = grid.dim
    tau = _kirchhoff(solid)
    new = solid.copy()
    new.v = np.zeros_like(solid.v)
    new.C = np.zeros_like(solid.C)
    for axis, stencil in enumerate(stencils):
        mass, velocity = masses[axis], velocities[axis]
        force = _scatter(stencil, lambda w, g, o, a=axis: -solid.volume * (tau[:, a, :] * g).sum(axis=1))
        velocity = velocity + np.divide(dt * force, mass, out=np.zeros_like(mass), where=mass > 0)
        if gravity is not None:
            velocity = np.where(mass > 0, velocity + dt * float(gravity[axis]), velocity)
        index = np.indices(stencil.shape)[axis] - PAD  # the domain's ends: the solid may leave them, not cross
        velocity = np.where(index <= 0, np.maximum(velocity, 0.0),
                            np.where(index >= grid.shape[axis], np.minimum(velocity, 0.0), velocity))
        if grid.solid is not None:
            below, above = euler._solid_sides(axis, grid)
            inner = _interior(_crop(velocity), axis)  # a view: the grid's interior faces
            # a face between a static solid and the rest is a separable slip wall; faces inside it are free
            inner[:] = np.where(below & ~above, np.maximum(inner, 0.0), np.where(above & ~below, np.minimum(inner, 0.0),
                                                                                  inner))
        flat_velocity = velocity.ravel()
        for flat, weight, _, offset in stencil.nodes:
            value = np.where(flat >= 0, flat_velocity[np.maximum(flat, 0)], 0.0) * weight
            new.v[:, axis] += value
            new.C[:, axis, :] += (4.0 / grid.dx) * value[:, None] * offset
    new.F = np.einsum("pij,pjk->pik", np.eye(d) + dt * new.C, solid.F)
    if new.plastic_strain is not None:
        out_of_plane = None if new.out_of_plane is None else torch.from_numpy(new.out_of_plane)
        F, eps_q, out = solid.material.return_map(torch.from_numpy(new.F), torch.from_numpy(new.plastic_strain),
                                                  out_of_plane)
        new.F, new.plastic_strain = F.numpy(), eps_q.numpy()
        new.out_of_plane = None if out is None else out.numpy()
    new.Jg = solid.Jg * (1.0 + dt * np.trace(new.C, axis1=1, axis2=2))
    new.x = solid.x + dt * new.v
    return new


def solid_energy(solid: Solid) -> float:
    """The solid's kinetic and elastic energy (J per unit depth in 2D)."""
    F = torch.from_numpy(solid.F)
    elastic = (solid.material.energy_density(F) if solid.out_of_plane is None else
               solid.material.energy_density(F, torch.from_numpy(solid.out_of_plane))).numpy()
    return float(0.5 * (solid.mass * (solid.v ** 2).sum(axis=1)).sum() + (solid.volume * elastic).sum())
