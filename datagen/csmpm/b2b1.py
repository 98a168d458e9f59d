"""The gas's pressure projection with B2B1 shape functions (thesis §3.2.6–3.2.7, eqs. 3.25–3.26).

:mod:`~datagen.csmpm.euler` projects with B1B0 (one normal velocity per face, one pressure per
cell: Kwatra's MAC layout, which lumping turns into the five-point system). B2B1 takes the
thesis' 1D and 2D benchmark discretization instead:

* **velocity**: quadratic B-splines N2 centred on the cells, where the conserved variables are,
  so the nodal velocities before the solve are u*_i = (rho u)_i / rho_i and the lumped masses
  m_i = rho_i dx^d;
* **pressure**: linear B-splines N1 (hats) on the cell corners, each truncated to the domain;
* **walls** (the only boundary this projection takes): the velocity basis is folded at each
  wall by mirror ghost nodes, with the wall-normal component odd (phi_i = N2_i - N2_ghost, zero
  on the wall: the slip condition 3.29 holds exactly) and the tangential ones even
  (N2_i + N2_ghost, a partition of unity).

With G_a[i, k] = integral phi_i d_a N1_k (the weak gradient; by the folding, integral
div(u) N1_k = -sum_i G[i, k] u_i exactly) and the lumped compressibility S_k = integral N1_k /
(rho c^2) (rho c^2 of the step's start, constant per cell), eliminating the velocities
(eq. 3.35) leaves the SPD system of eq. 3.37 without interface blocks:

    (S / dt^2 + sum_a G_a^T M^-1 G_a) p = S p* / dt^2 + sum_a G_a^T u*_a / dt,

p* the equation of state's pressure of the advected cells, taken constant per cell. All
operators are tensor products of 1D matrices (exact Gauss quadrature on each cell), so the
system is applied without being assembled: Jacobi-preconditioned CG.

After the solve the cells' momentum takes the weak gradient (eq. 3.35):
(rho u)_i -= dt (G p)_i / dx^d. The energy takes the work of the faces, as Kwatra's update does:
each face's pressure is the bilinear pressure at its centre, its normal velocity the corrected
quadratic field's there (zero on walls). Mass and energy in a closed box are therefore conserved
to round-off, as with B1B0.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator

from . import euler
from .gas import GAMMA, pressure, sound_speed

__all__ = ["SCHEMES", "check_grid", "axis_matrices", "Operators", "project", "step"]

SCHEMES = ("B1B0", "B2B1")
"""The gas's velocity/pressure orders (thesis §3.2.6): B1B0 (:func:`datagen.csmpm.euler.project`)
and B2B1 (this module)."""
_GAUSS_POINTS, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(3)  # exact to degree 5 on each cell


def check_grid(grid: euler.Grid) -> None:
    """ValueError unless ``grid`` is a closed box (walls on every side, no static solids): the
    boundaries the B2B1 projection takes."""
    others = sorted({b for pair in grid.boundaries for b in pair} - {"wall"})
    if others or grid.solid is not None:
        what = f"{' and '.join(others)} boundaries" if others else "static solid cells"
        raise ValueError(f"the B2B1 projection takes closed boxes (walls on every side) only, got {what}; "
                         "use the scheme B1B0")


def _quadratic(t: np.ndarray) -> np.ndarray:
    a = np.abs(t)
    return np.where(a < 0.5, 0.75 - a ** 2, np.where(a < 1.5, 0.5 * (1.5 - a) ** 2, 0.0))


@functools.lru_cache(maxsize=32)
def axis_matrices(n: int, dx: float, odd: bool) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Along one axis of ``n`` cells of side ``dx``, walls at both ends: (P, D), both (n, n + 1),
    P[i, k] = integral phi_i N1_k and D[i, k] = integral phi_i N1_k' over the axis, phi_i the
    cell-centred quadratic B-spline folded at the walls (``odd``: the wall-normal component, zero
    on the walls; else even), N1_k the hat on corner k. Exact (3-point Gauss on each cell)."""
    rows, cols, p_values, d_values = [], [], [], []
    cells = np.arange(n)
    for xi, weight in zip(_GAUSS_POINTS, _GAUSS_WEIGHTS, strict=True):
        s = cells + 0.5 * (xi + 1.0)  # the point in cell units, cell c covering [c, c + 1]
        w = 0.5 * dx * weight
        for offset in (-1, 0, 1):
            node = cells + offset
            phi = _quadratic(s - (node + 0.5))
            sign = np.where((node < 0) | (node >= n), -1.0 if odd else 1.0, 1.0)
            folded = np.where(node < 0, -1 - node, np.where(node >= n, 2 * n - 1 - node, node))  # the mirrored node
            for corner, hat, slope in ((cells, cells + 1 - s, -1.0 / dx), (cells + 1, s - cells, 1.0 / dx)):
                rows.append(folded)
                cols.append(corner)
                p_values.append(w * sign * phi * hat)
                d_values.append(w * sign * phi * slope)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    shape = (n, n + 1)
    P = sp.csr_matrix((np.concatenate(p_values), (rows, cols)), shape=shape)
    D = sp.csr_matrix((np.concatenate(d_values), (rows, cols)), shape=shape)
    P.sum_duplicates()
    D.sum_duplicates()
    return P, D


def _along(matrix, array: np.ndarray, axis: int) -> np.ndarray:
    """``matrix`` applied along ``axis`` of ``array``."""
    moved = np.moveaxis(array, axis, 0)
    out = matrix @ moved.reshape(moved.shape[0], -1)
    return np.moveaxis(np.asarray(out).reshape((matrix.shape[0],) + moved.shape[1:]), 0, axis)


class Operators:
    """The B2B1 operators of a closed-box grid (module docstring): the weak gradients G_a (corners
    to cells) and their transposes, applied axis by axis."""

    def __init__(self, grid: euler.Grid):
        check_grid(grid)
        self.grid = grid
        self.corners = tuple(n + 1 for n in grid.shape)
        # per component a, per axis b: the 1D matrix (D where b == a, else P), odd along a
        self.factors = [[axis_matrices(n, grid.dx, b == a)[1 if b == a else 0] for b, n in enumerate(grid.shape)]
                        for a in range(grid.dim)]

    def gradient(self, p: np.ndarray, component: int) -> np.ndarray:
        """(G_a p) on the cells, ``p`` on the corners."""
        out = p
        for axis, matrix in enumerate(self.factors[component]):
            out = _along(matrix, out, axis)
        return out

    def gradient_transpose(self, values: np.ndarray, component: int) -> np.ndarray:
        """(G_a^T values) on the corners, ``values`` on the cells."""
        out = values
        for axis, matrix in enumerate(self.factors[component]):
            out = _along(matrix.T, out, axis)
        return out

    def gradient_diagonal(self, inverse_mass: np.ndarray) -> np.ndarray:
        """The diagonal of sum_a G_a^T diag(inverse_mass) G_a on the corners."""
        out = np.zeros(self.corners)
        for a in range(self.grid.dim):
            squared = inverse_mass
            for axis, matrix in enumerate(self.factors[a]):
                squared = _along(matrix.multiply(matrix).T, squared, axis)
            out += squared
        return out

    def corner_sum(self, cells: np.ndarray) -> np.ndarray:
        """integral N1_k f over the domain for f constant per cell (the lumped S and S p*)."""
        share = self.grid.dx ** self.grid.dim / 2 ** self.grid.dim
        out = np.zeros(self.corners)
        for offset in np.ndindex(*(2,) * self.grid.dim):
            out[tuple(slice(o, o + n) for o, n in zip(offset, self.grid.shape, strict=True))] += share * cells
        return out

    def matrix(self, inverse_mass: np.ndarray, compressibility: np.ndarray, dt: float) -> LinearOperator:
        """The system's operator p -> S p / dt^2 + sum_a G_a^T M^-1 G_a p on flat corner arrays."""
        size = int(np.prod(self.corners))

        def apply(flat):
            p = flat.reshape(self.corners)
            out = compressibility * p / dt ** 2
            for a in range(self.grid.dim):
                out = out + self.gradient_transpose(inverse_mass * self.gradient(p, a), a)
            return out.ravel()

        return LinearOperator((size, size), matvec=apply, dtype=np.float64)


def _face_values(u: np.ndarray, p: np.ndarray, axis: int, grid: euler.Grid) -> tuple[np.ndarray, np.ndarray]:
    """On the faces normal to ``axis`` (n + 1 along it): the quadratic field ``u`` (the axis'
    component on the cells) and the bilinear pressure ``p`` (on the corners) at the face centres."""
    normal = np.zeros_like(u, shape=tuple(n + (b == axis) for b, n in enumerate(grid.shape)))
    inner = [slice(None)] * grid.dim
    inner[axis] = slice(1, grid.shape[axis])
    below, above = euler._pairs(u, axis, grid)
    normal[tuple(inner)] = 0.5 * (below + above)  # the walls' faces stay 0 (odd folding)
    for b in range(grid.dim):
        if b != axis:  # at a cell centre across: 1/8, 3/4, 1/8 of the even-folded neighbours
            padded = np.concatenate([np.take(normal, [0], b), normal, np.take(normal, [-1], b)], axis=b)
            n = grid.shape[b]
            normal = (0.125 * np.take(padded, np.arange(n), b) + 0.75 * np.take(padded, np.arange(1, n + 1), b)
                      + 0.125 * np.take(padded, np.arange(2, n + 2), b))
    face_p = p
    for b in range(grid.dim):
        if b != axis:  # the bilinear pressure at the face's centre: the mean of its corners
            n = grid.shape[b]
            face_p = 0.5 * (np.take(face_p, np.arange(n), b) + np.take(face_p, np.arange(1, n + 1), b))
    return normal, face_p


def project(advected: np.ndarray, before: np.ndarray, grid: euler.Grid, dt: float, gamma: float = GAMMA,
            rtol: float = 1e-10) -> tuple[np.ndarray, int, float]:
    """The B2B1 counterpart of :func:`datagen.csmpm.euler.project`: the ``advected`` state after the
    pressure solve and correction (module docstring), rho c^2 from ``before``. -> (state, CG
    iterations, relative residual); ValueError on grids other than closed boxes."""
    ops = Operators(grid)
    d, volume = grid.dim, grid.dx ** grid.dim
    rho = advected[0]
    velocity = advected[1:-1] / rho
    inverse_mass = 1.0 / (rho * volume)
    stiffness = before[0] * sound_speed(before[0], pressure(before, gamma), gamma) ** 2
    p_star = pressure(advected, gamma)
    compressibility = ops.corner_sum(1.0 / stiffness)
    rhs = ops.corner_sum(p_star / stiffness) / dt ** 2
    for a in range(d):
        rhs = rhs + ops.gradient_transpose(velocity[a], a) / dt
    diagonal = compressibility / dt ** 2 + ops.gradient_diagonal(inverse_mass)
    start = ops.corner_sum(p_star) / ops.corner_sum(np.ones(grid.shape))  # p* averaged onto the corners
    solution, iterations, residual = euler.jacobi_cg(ops.matrix(inverse_mass, compressibility, dt), diagonal.ravel(),
                                                     rhs.ravel(), start.ravel(), dt, rtol, "the B2B1 pressure solve")
    p = solution.reshape(ops.corners)
    out = advected.copy()
    energy_flux = []
    for a in range(d):
        out[1 + a] -= dt * ops.gradient(p, a) / volume
        u_face, p_face = _face_values(out[1 + a] / rho, p, a, grid)
        energy_flux.append(p_face * u_face)
    out[-1] -= dt * euler._divergence(energy_flux, grid)
    return out, iterations, residual


def step(state: np.ndarray, grid: euler.Grid, dt: float, gamma: float = GAMMA) -> tuple[np.ndarray, euler.StepInfo]:
    """One step of dt with the B2B1 projection: advection (as B1B0's), then :func:`project`."""
    new, iterations, residual = project(euler.advect(state, grid, dt), state, grid, dt, gamma)
    return new, euler.StepInfo(dt, iterations, residual)
