"""``step(model, state, dt) -> state``: one explicit MPM step (UMLS Algorithm 1).

In eulerian mode (s = n, the plain UMLS solver) the kernel is computed at the current positions
and the step is P2G -> nodal update -> G2P (:func:`eulerian_step`); the A-ULMPM total and
adaptive modes reuse the kernel of a reference configuration
(:func:`~datagen.mpm.reference.reference_step`).
"""

from __future__ import annotations

from dataclasses import replace

from .errors import check_finite, lost_particles
from .inelastic import post_process
from .kernels import KernelResult
from .model import Model
from .nodal import move_grips, nodal_update
from .reference import reference_step
from .state import State
from .transfers import SLOT_TRANSFERS, kernel_and_p2g

__all__ = ["step", "eulerian_step", "cfl_time_step"]


def step(model: Model, state: State, dt: float, kernel: KernelResult | None = None) -> State:
    """Advance by dt. kernel: a precomputed kernel at state.x (eulerian mode; else computed).

    Raises SimulationError naming the step if particles are outside the background or the
    new state is not finite. In the total/adaptive modes ``kernel`` is ignored: the cached
    kernel of the reference configuration (state.reference) is used and rebuilt when due.
    """
    if model.reference != "eulerian":
        return reference_step(model, state, dt)
    return eulerian_step(model, state, dt, kernel)


def eulerian_step(model: Model, state: State, dt: float, kernel: KernelResult | None = None) -> State:
    """UMLS Algorithm 1 with the kernel at the current positions (s = n)."""
    p2g, g2p = SLOT_TRANSFERS[model.transfer]
    # line 1, the kernel; lines 2-3, P2G: [m_i, p_i, f_int_i] (in one pass where compiled)
    k, sums = kernel_and_p2g(model, state) if kernel is None else (kernel, None)
    if k.n_lost:
        raise lost_particles(model, state, k, dt)
    if sums is None:
        sums = p2g(model, state, k)
    grid = nodal_update(model, state, k, sums, dt)  # lines 4-6: gravity, v~_i, boundary conditions
    new = move_grips(model, state, g2p(model, state, k, grid, dt), dt)  # lines 7-9: v_p, x_p, F_p
    new = post_process(model, state, new, k)  # F-bar, plastic return map
    check_finite(model, state, new, dt)
    cell = k.cell if k.cell is not None else state.cell
    return replace(new, cell=cell, time=state.time + dt, step=state.step + 1)


def cfl_time_step(model: Model, state: State, cfl: float) -> float:
    """dt = cfl * h / (c + max |v_p|), c the largest dilatational wave speed."""
    speed = model.wave_speed + float(state.v.norm(dim=1).max())
    return cfl * model.h_cfl / speed
