"""Compressible Euler on a regular grid: CSMPM's gas (thesis §3.2.3–3.2.5), without solids yet.

A step splits the Euler equations as Kwatra et al. (2009) do:

1. **Advection** of the conserved variables (rho, rho u, rho E) by the flow alone (thesis eqs.
   3.10–3.12): the flux u_n U along each axis, reconstructed by second-order WENO (two
   two-point stencils, Jiang–Shu weights) with local Lax–Friedrichs flux splitting whose speed is
   the largest |u_n| of the stencil, integrated by SSP-RK2 (Heun). No pressure enters, so
   the step's stability is set by the flow speed, not the sound speed.
2. **Pressure** (eqs. 3.21–3.22): p* from the equation of state of the advected state, then the
   SPD system  p / (rho c^2 dt^2) - div(grad p / rho_f) = p* / (rho c^2 dt^2) - div(u*_f) / dt
   on the cells (rho c^2 of the step's start, rho_f face averages, u*_f face velocities: the
   average of the two cells), solved by Jacobi-preconditioned CG.
3. **Correction**: face velocities u_f = u*_f - dt grad_f p / rho_f; cell momentum by the
   difference of face pressures (the mean of the two cells), energy by the face fluxes p_f u_f.

Every update is a difference of face fluxes, so mass and energy in a closed box are conserved
to round-off (walls: no flux; their faces carry only the wall's pressure force on momentum).

Boundaries per axis end: ``wall`` (reflective: ghost cells mirror the state with the normal
velocity negated; face velocity 0, zero pressure gradient), ``open`` (an outlet: ghost cells
extrapolate the edge cell; the face velocity is the edge cell's, the face pressure its
pressure; other outlets below) or ``inlet`` (ghost cells hold the grid's ``inflow`` state; its
velocity and pressure act at the face: the thesis' §3.2.9 with a prescribed supersonic inflow).

**Outlets** (§3.2.9; ``Grid.outlet``): ``extrapolate`` (the default above: zero pressure gradient,
the face velocity the edge cell's, so the outlet does not know the far field and a pressure
wave leaving through it partly reflects), ``attenuate`` (the thesis' attenuated ghost cells: with
``Grid.attenuation`` a and the far field's conserved state ``Grid.outflow``, the ghost cells k = 1, 2
away hold far + a^k (edge - far) and the face pressure is p_far + a (p_edge - p_far): the domain
relaxes towards the far field, a = 0 holds the face at p_far) or ``characteristic`` (no wave
enters from outside: the face pressure and outward velocity satisfy p_b - p_far = rho c (u_b -
u_far), the acoustic impedance of the edge cell, so a leaving pressure wave passes; where the
outflow is supersonic nothing enters and the face extrapolates). Both couple the face pressure
p_b to the edge cell's through the half cell between them, as the Robin condition
p_b = p_edge + f (target - p_edge), taken implicitly by the pressure solve:
2 f / (rho_edge dx^2) joins the edge cell's diagonal (the system stays SPD) and the face
velocity is corrected by that gradient. Measured in docs/csmpm.md.

Static solid cells (``Grid.solid``, a boolean mask) are walls inside the domain: no advective
flux crosses a face between gas and solid, a WENO stencil that reaches into a solid cell takes
the value of the gas cell next to it on the face's side (the thesis' "reflection only at the
evaluated interface"), their faces carry zero normal velocity into the pressure solve, and the
gas cell's own pressure pushes on them. Solid cells keep their state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator, cg

from .gas import GAMMA, pressure, sound_speed

__all__ = ["Grid", "BOUNDARIES", "advective_flux", "advect", "solve_pressure", "jacobi_cg", "project", "step",
           "time_step", "StepInfo", "OUTLETS", "outlet_ends", "outlet_terms", "correct_outlets"]

BOUNDARIES = ("wall", "open", "inlet")
OUTLETS = ("extrapolate", "attenuate", "characteristic")
EPSILON = 1e-6  # the WENO weights' guard against division by zero


@dataclass(frozen=True, eq=False)
class Grid:
    """A regular grid of cells: ``shape`` cells per axis, square cells of side ``dx``, per axis
    the (low, high) boundaries, each ``wall``, ``open`` or ``inlet``; ``inflow``: the conserved
    state (d + 2,) the inlets hold; ``solid``: a boolean mask of static solid cells (None: none);
    ``outlet``: how outlets treat the far field (:data:`OUTLETS`, module docstring), whose conserved
    state (d + 2,) ``outflow`` holds (needed but for ``extrapolate``); ``attenuation`` a (0 to 1)
    of the ``attenuate`` outlet."""

    shape: tuple[int, ...]
    dx: float
    boundaries: tuple[tuple[str, str], ...]
    inflow: np.ndarray | None = None
    solid: np.ndarray | None = None
    outlet: str = "extrapolate"
    attenuation: float = 1.0
    outflow: np.ndarray | None = None

    def __post_init__(self):
        if len(self.boundaries) != len(self.shape) or any(len(b) != 2 for b in self.boundaries):
            raise ValueError(f"boundaries must give (low, high) for each of the {len(self.shape)} axes, "
                             f"got {self.boundaries}")
        bad = [b for pair in self.boundaries for b in pair if b not in BOUNDARIES]
        if bad:
            raise ValueError(f"unknown boundary {bad[0]!r}; choose one of {', '.join(BOUNDARIES)}")
        if any(b == "inlet" for pair in self.boundaries for b in pair) and (
                self.inflow is None or np.shape(self.inflow) != (len(self.shape) + 2,)):
            raise ValueError(f"an inlet needs the inflow's conserved state ({len(self.shape) + 2} values), "
                             f"got {self.inflow!r}")
        if self.outlet not in OUTLETS:
            raise ValueError(f"unknown outlet {self.outlet!r}; choose one of {', '.join(OUTLETS)}")
        if not 0.0 <= self.attenuation <= 1.0:
            raise ValueError(f"attenuation must be from 0 (the far field held at outlets) to 1 (plain extrapolation), "
                             f"got {self.attenuation}")
        if self.outlet != "extrapolate" and (self.outflow is None or np.shape(self.outflow) != (len(self.shape) + 2,)):
            raise ValueError(f"a {self.outlet} outlet needs the far field's conserved state (outflow, "
                             f"{len(self.shape) + 2} values), got {self.outflow!r}")
        if self.solid is not None and np.shape(self.solid) != tuple(self.shape):
            raise ValueError(f"solid must be a mask of the {self.shape} cells, got shape {np.shape(self.solid)}")
        if min(self.shape) < 2 or not self.dx > 0:
            raise ValueError(f"a grid needs >= 2 cells per axis and dx > 0, got shape {self.shape}, dx {self.dx}")

    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def attenuated(self) -> bool:
        """Whether the outlets' ghost cells are attenuated towards the far field."""
        return self.outlet == "attenuate" and self.attenuation < 1.0


@dataclass(frozen=True)
class StepInfo:
    """What a step did: the time step, CG iterations of the pressure solve and its final
    relative residual."""

    dt: float
    cg_iterations: int
    residual: float


def _ghosts(state: np.ndarray, axis: int, grid: Grid) -> np.ndarray:
    """``state`` (k, *cells) padded by two ghost cells at both ends of ``axis``."""
    a, n = axis + 1, grid.shape[axis]
    parts = []
    # per end: the two cells next to it, the edge cell twice, and the ghosts' distances from the edge
    for side, pair, edge, distance in zip(grid.boundaries[axis], ([0, 1], [n - 2, n - 1]), ([0, 0], [n - 1, n - 1]),
                                          ([2, 1], [1, 2]), strict=True):
        if side == "wall":  # the two cells mirrored, their normal momentum negated
            ghost = np.flip(np.take(state, pair, axis=a), axis=a)
            ghost[1 + axis] *= -1.0
        elif side == "inlet":
            ghost = np.broadcast_to(np.reshape(grid.inflow, (-1,) + (1,) * (state.ndim - 1)),
                                    np.take(state, pair, axis=a).shape)
        else:  # open: the edge cell extrapolated, attenuated towards the far field
            ghost = np.take(state, edge, axis=a)
            if grid.attenuated:
                far = np.reshape(grid.outflow, (-1,) + (1,) * (state.ndim - 1))
                shape = [1] * state.ndim
                shape[a] = 2
                ghost = far + np.reshape(grid.attenuation ** np.array(distance, float), shape) * (ghost - far)
        parts.append(ghost)
    return np.concatenate([parts[0], state, parts[1]], axis=a)


def _weno(minus, centre, plus) -> np.ndarray:
    """Second-order WENO value at the face between ``centre`` and ``plus``, upwind from
    ``minus``'s side: stencils (minus, centre) and (centre, plus), linear weights 1/3, 2/3."""
    q0, q1 = 1.5 * centre - 0.5 * minus, 0.5 * (centre + plus)
    a0 = (1.0 / 3.0) / (EPSILON + (centre - minus) ** 2) ** 2
    a1 = (2.0 / 3.0) / (EPSILON + (plus - centre) ** 2) ** 2
    return (a0 * q0 + a1 * q1) / (a0 + a1)


def advective_flux(state: np.ndarray, axis: int, grid: Grid, passable: np.ndarray | None = None) -> np.ndarray:
    """(k, ..., n + 1, ...) WENO-LLF fluxes u_n U through the faces normal to ``axis`` (face j
    between cells j - 1 and j; walls carry none). ``passable``: the faces' open fractions (n + 1
    along ``axis``), each face's flux scaled by it (the thesis' blend of a passable flux with a
    reflective one, which carries none); without it faces next to solid cells carry none."""
    padded = _ghosts(state, axis, grid)
    a, n = axis + 1, grid.shape[axis]
    velocity = padded[1 + axis] / padded[0]
    flux = velocity * padded

    def shifted(array, k):  # the stencil's k-th cell of every face: padded cells k .. k + n
        index = [slice(None)] * array.ndim
        index[array.ndim - grid.dim + axis] = slice(k, k + n + 1)
        return array[tuple(index)]

    cells = [shifted(padded, k) for k in range(4)]
    fluxes = [shifted(flux, k) for k in range(4)]
    speeds = [shifted(velocity, k) for k in range(4)]
    blocked = None
    if grid.solid is not None:  # a stencil cell inside a solid takes its face-side gas neighbour's value
        solid = np.pad(grid.solid, [(2, 2) if b == axis else (0, 0) for b in range(grid.dim)])
        inside = [shifted(solid, k) for k in range(4)]
        for outer, inner in ((0, 1), (3, 2)):
            cells[outer] = np.where(inside[outer], cells[inner], cells[outer])
            fluxes[outer] = np.where(inside[outer], fluxes[inner], fluxes[outer])
            speeds[outer] = np.where(inside[outer], speeds[inner], speeds[outer])
        blocked = inside[1] | inside[2]
    speed = np.max(np.abs(np.stack(speeds)), axis=0)
    plus = [0.5 * (fluxes[k] + speed * cells[k]) for k in range(3)]
    minus = [0.5 * (fluxes[k] - speed * cells[k]) for k in (3, 2, 1)]
    faces = _weno(*plus) + _weno(*minus)
    for end, side in zip((0, n), grid.boundaries[axis], strict=True):
        if side == "wall":
            index = [slice(None)] * faces.ndim
            index[a] = end
            faces[tuple(index)] = 0.0
    if passable is not None:
        faces *= passable
    elif blocked is not None:
        faces[:, blocked] = 0.0
    return faces


def _difference(faces: np.ndarray, axis: int, grid: Grid) -> np.ndarray:
    """Per cell, the face value above minus the one below along ``axis`` (n + 1 faces), over dx."""
    a, n = faces.ndim - grid.dim + axis, grid.shape[axis]
    return (np.take(faces, np.arange(1, n + 1), axis=a) - np.take(faces, np.arange(n), axis=a)) / grid.dx


def _divergence(faces: list[np.ndarray], grid: Grid) -> np.ndarray:
    """Cell sums of face values (one array per axis, n + 1 faces along it) out minus in, over dx."""
    return sum(_difference(f, axis, grid) for axis, f in enumerate(faces))


def _rate(state: np.ndarray, grid: Grid, passable) -> np.ndarray:
    return -_divergence([advective_flux(state, axis, grid, None if passable is None else passable[axis])
                         for axis in range(grid.dim)], grid)


def advect(state: np.ndarray, grid: Grid, dt: float, passable: list[np.ndarray] | None = None) -> np.ndarray:
    """The state after advection by the flow over dt (SSP-RK2); ``passable``: per axis the faces'
    open fractions (:func:`advective_flux`)."""
    first = state + dt * _rate(state, grid, passable)
    return 0.5 * (state + first + dt * _rate(first, grid, passable))


def _pairs(array: np.ndarray, axis: int, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """The (n - 1) cells below and above each interior face along ``axis`` (last axes: the grid's)."""
    a, n = array.ndim - grid.dim + axis, grid.shape[axis]
    return np.take(array, np.arange(n - 1), axis=a), np.take(array, np.arange(1, n), axis=a)


def _solid_sides(axis: int, grid: Grid):
    """(below, above) solid masks of the interior faces along ``axis``, or None without solids."""
    return None if grid.solid is None else _pairs(grid.solid, axis, grid)


def _faces(cells: np.ndarray, axis: int, grid: Grid, kind: str) -> np.ndarray:
    """(n + 1 along ``axis``) face values of a cell field of the grid's shape: ``velocity`` (the
    normal velocity, cells' u_axis): the mean of the two cells, 0 at walls and solid faces, the
    edge cell's at outlets, the inflow's at inlets; ``pressure``: the mean of two gas cells,
    the gas cell's own at a solid face, the edge cell's at walls and outlets (other outlets than
    ``extrapolate``: :func:`correct_outlets`), the inflow's at inlets."""
    below, above = _pairs(cells, axis, grid)
    inner = 0.5 * (below + above)
    sides = _solid_sides(axis, grid)
    if sides is not None:
        if kind == "velocity":
            inner = np.where(sides[0] | sides[1], 0.0, inner)
        else:
            inner = np.where(sides[0], above, np.where(sides[1], below, inner))
    ends = []
    for index, side in zip((0, grid.shape[axis] - 1), grid.boundaries[axis], strict=True):
        end = np.take(cells, [index], axis=axis)
        if side == "wall" and kind == "velocity":
            end = np.zeros_like(end)
        elif side == "inlet":
            inflow = np.asarray(grid.inflow, np.float64)
            end = np.full_like(end, inflow[1 + axis] / inflow[0] if kind == "velocity" else pressure(inflow))
        ends.append(end)
    return np.concatenate([ends[0], inner, ends[1]], axis=axis)


@dataclass(frozen=True, eq=False)
class OutletEnd:
    """One outlet end of an axis whose face pressure p_b = p_edge + factor (target - p_edge) (module
    docstring): the edge cell's index, the face's, the outward sign, and per face ``factor``,
    ``target``, ``k`` = 2 dt / (rho_edge dx), how p_b - p_edge changes the outward velocity, and
    ``weight`` = 2 factor / (rho_edge dx^2), its term in the edge cell's row of the system."""

    axis: int
    index: int
    face: int
    outward: float
    factor: np.ndarray
    target: np.ndarray
    k: np.ndarray
    weight: np.ndarray


def outlet_ends(state: np.ndarray, u_faces: list[np.ndarray], grid: Grid, dt: float,
                gamma: float = GAMMA) -> list[OutletEnd]:
    """The outlets of ``grid`` that couple to the far field (``attenuate``, ``characteristic``), from
    the advected ``state`` and the face velocities u* (per axis, n + 1 faces) before the solve."""
    if grid.outlet == "extrapolate":
        return []
    far = np.asarray(grid.outflow, np.float64)
    p_far, ends = pressure(far, gamma), []
    for axis in range(grid.dim):
        n = grid.shape[axis]
        for index, face, outward, side in zip((0, n - 1), (0, n), (-1.0, 1.0), grid.boundaries[axis], strict=True):
            if side != "open":
                continue
            edge = np.take(state, [index], axis=axis + 1)
            k = 2.0 * dt / (edge[0] * grid.dx)
            if grid.outlet == "attenuate":
                factor, target = np.full_like(k, 1.0 - grid.attenuation), np.full_like(k, p_far)
            else:  # characteristic: p_b - p_far = Z (u_b - u_far) outward, u_b = u* - k (p_b - p_edge)
                c = sound_speed(edge[0], pressure(edge, gamma), gamma)
                impedance = edge[0] * c
                u_star = outward * np.take(u_faces[axis], [face], axis=axis)
                # a supersonic outflow has no incoming characteristic: plain extrapolation there
                factor = np.where(u_star >= c, 0.0, 1.0 / (1.0 + impedance * k))
                target = p_far + impedance * (u_star - outward * far[1 + axis] / far[0])
            weight = 2.0 * factor / (edge[0] * grid.dx ** 2)
            ends.append(OutletEnd(axis, index, face, outward, factor, target, k, weight))
    return ends


def outlet_terms(ends: list[OutletEnd], grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """(diagonal, right-hand side) additions, flat over the cells, of the ``ends``
    (:func:`outlet_ends`) to the pressure system: each end's weight on its edge cells, times its
    target on the right."""
    diagonal, rhs = np.zeros(grid.shape), np.zeros(grid.shape)
    for end in ends:
        where = [slice(None)] * grid.dim
        where[end.axis] = slice(end.index, end.index + 1)
        diagonal[tuple(where)] += end.weight
        rhs[tuple(where)] += end.weight * end.target
    return diagonal.ravel(), rhs.ravel()


def correct_outlets(u_faces: np.ndarray, p_faces: np.ndarray, p: np.ndarray, ends: list[OutletEnd],
                    axis: int) -> None:
    """The ``ends`` of ``axis``: their face pressure p_b = p_edge + f (target - p_edge) into
    ``p_faces`` and their face velocity corrected outward by -k (p_b - p_edge), in place."""
    for end in ends:
        if end.axis != axis:
            continue
        where = [slice(None)] * p.ndim
        where[axis] = slice(end.face, end.face + 1)
        edge = np.take(p, [end.index], axis=axis)
        jump = end.factor * (end.target - edge)  # p_b - p_edge
        p_faces[tuple(where)] = edge + jump
        u_faces[tuple(where)] -= end.outward * end.k * jump


def _face_coefficients(density: np.ndarray, grid: Grid) -> list[np.ndarray]:
    """Per axis, 1 / rho_f on the interior faces (rho_f the mean of the two cells), 0 on faces
    next to a solid cell: how a pressure difference across each face moves it."""
    out = []
    for axis in range(grid.dim):
        below, above = _pairs(density, axis, grid)
        coefficient = 2.0 / (below + above)
        sides = _solid_sides(axis, grid)
        out.append(coefficient if sides is None else np.where(sides[0] | sides[1], 0.0, coefficient))
    return out


def _laplacian(coefficients: list[np.ndarray], grid: Grid) -> sp.csr_matrix:
    """The matrix of -div(c_f grad p) over the cells, ``coefficients`` c_f per axis on the interior
    faces (1 / rho_f for the gas; 0 where faces carry no gradient: domain boundaries, static
    solids); symmetric positive semi-definite."""
    size = int(np.prod(grid.shape))
    ids = np.arange(size).reshape(grid.shape)
    rows, cols, values = [], [], []
    for axis, coefficient in enumerate(coefficients):
        left, right = (i.ravel() for i in _pairs(ids, axis, grid))
        w = coefficient.ravel() / grid.dx ** 2
        rows += [left, right, left, right]
        cols += [left, right, right, left]
        values += [w, w, -w, -w]
    matrix = sp.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))
    matrix.eliminate_zeros()
    return matrix


def solve_pressure(coefficients: list[np.ndarray], diagonal: np.ndarray, rhs: np.ndarray, p_star: np.ndarray,
                   grid: Grid, dt: float, rtol: float = 1e-10) -> tuple[np.ndarray, int, float]:
    """The cells' pressures of the system -div(c_f grad p) + diag p = rhs (face coefficients c_f,
    :func:`_laplacian`; ``diagonal`` and ``rhs`` flat), static solid cells held at p* (their rows
    replaced by p = p*), by Jacobi-preconditioned CG from p*. -> (p, CG iterations, relative
    residual); RuntimeError when CG does not converge."""
    if grid.solid is not None:
        solid = grid.solid.ravel()
        diagonal, rhs = np.where(solid, 1.0, diagonal), np.where(solid, p_star.ravel(), rhs)
    matrix = (_laplacian(coefficients, grid) + sp.diags(diagonal)).tocsr()
    solution, iterations, residual = jacobi_cg(matrix, matrix.diagonal(), rhs, p_star.ravel(), dt, rtol)
    return solution.reshape(grid.shape), iterations, residual


def jacobi_cg(matrix, diagonal: np.ndarray, rhs: np.ndarray, start: np.ndarray, dt: float, rtol: float = 1e-10,
              what: str = "the pressure solve") -> tuple[np.ndarray, int, float]:
    """Jacobi-preconditioned CG on an SPD ``matrix`` (sparse or a LinearOperator) with the flat
    ``diagonal`` of it, from ``start``: (solution, iterations, relative residual); RuntimeError
    naming ``what`` and dt when it does not converge."""
    inverse, iterations = 1.0 / diagonal, [0]

    def count(_):
        iterations[0] += 1

    solution, failed = cg(matrix, rhs, x0=start, rtol=rtol, atol=0.0, maxiter=10 * rhs.size,
                          M=LinearOperator(matrix.shape, lambda v: inverse * v), callback=count)
    if failed:
        raise RuntimeError(f"{what} did not converge in {failed} CG iterations (dt {dt:g})")
    residual = float(np.linalg.norm(matrix @ solution - rhs) / max(np.linalg.norm(rhs), 1e-300))
    return solution, iterations[0], residual


def project(advected: np.ndarray, before: np.ndarray, grid: Grid, dt: float, gamma: float = GAMMA,
            rtol: float = 1e-10) -> tuple[np.ndarray, int, float]:
    """The state after the pressure solve and correction (module docstring, steps 2-3) of the
    ``advected`` state; rho c^2 from ``before`` (the step's start). Returns (state, CG
    iterations, relative residual). Solid cells keep their state (their pressure row: p = p*)."""
    rho = advected[0]
    p_star = pressure(advected, gamma)
    stiffness = before[0] * sound_speed(before[0], pressure(before, gamma), gamma) ** 2  # rho c^2
    velocity = advected[1:-1] / rho
    u_faces = [_faces(velocity[axis], axis, grid, "velocity") for axis in range(grid.dim)]
    diagonal = (1.0 / (stiffness * dt ** 2)).ravel()
    rhs = diagonal * p_star.ravel() - _divergence(u_faces, grid).ravel() / dt
    ends = outlet_ends(advected, u_faces, grid, dt, gamma)
    outlet_diagonal, outlet_rhs = outlet_terms(ends, grid)
    p, iterations, residual = solve_pressure(_face_coefficients(rho, grid), diagonal + outlet_diagonal,
                                             rhs + outlet_rhs, p_star, grid, dt, rtol)
    out = advected.copy()
    energy_flux = []
    for axis, coefficient in enumerate(_face_coefficients(rho, grid)):
        below, above = _pairs(p, axis, grid)
        u_f = u_faces[axis].copy()
        inner = [slice(None)] * grid.dim
        inner[axis] = slice(1, grid.shape[axis])
        u_f[tuple(inner)] -= dt * coefficient * (above - below) / grid.dx
        p_f = _faces(p, axis, grid, "pressure")
        correct_outlets(u_f, p_f, p, ends, axis)
        out[1 + axis] -= dt * _difference(p_f, axis, grid)
        energy_flux.append(p_f * u_f)
    out[-1] -= dt * _divergence(energy_flux, grid)
    if grid.solid is not None:
        out[:, grid.solid] = advected[:, grid.solid]
    return out, iterations, residual


def time_step(state: np.ndarray, grid: Grid, cfl: float = 0.5, acoustic: float = 0.0, gamma: float = GAMMA) -> float:
    """cfl dx / max over cells and axes of (|u_n| + acoustic c): with ``acoustic`` 0 the flow
    speed alone limits the step (the semi-implicit pressure is stable at any sound speed);
    infinite where nothing moves and ``acoustic`` is 0 (the caller caps it)."""
    rho, momentum = state[0], state[1:-1]
    speed = np.max(np.abs(momentum) / rho, axis=0)
    if acoustic > 0:
        speed = speed + acoustic * sound_speed(rho, pressure(state, gamma), gamma)
    fastest = float(speed.max() if grid.solid is None else np.max(speed, where=~grid.solid, initial=0.0))
    return cfl * grid.dx / fastest if fastest > 0 else float("inf")


def step(state: np.ndarray, grid: Grid, dt: float, gamma: float = GAMMA) -> tuple[np.ndarray, StepInfo]:
    """One step of dt: advection, then the pressure solve and correction."""
    new, iterations, residual = project(advect(state, grid, dt), state, grid, dt, gamma)
    return new, StepInfo(dt, iterations, residual)
