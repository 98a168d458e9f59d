"""Runs that cannot continue: particles lost from the background or a non-finite state,
reported as :class:`SimulationError` with the step, the time and a time step to try."""

from __future__ import annotations

import torch

from .kernels import KernelResult
from .locate import LocateStatus
from .model import Model
from .state import State

__all__ = ["SimulationError", "lost_particles", "check_finite"]


class SimulationError(RuntimeError):
    """A run that cannot continue: particles lost or a non-finite state."""


def lost_particles(model: Model, state: State, k: KernelResult, dt: float) -> SimulationError:
    """The error for a kernel k at state.x with particles outside the background."""
    lost = k.status != LocateStatus.INSIDE
    nonfinite = int((k.status == LocateStatus.NONFINITE).sum())
    background = "grid" if model.kernel == "bspline" else "mesh"
    what = f"{int(lost.sum())} of {len(lost)} particles left the {background}"
    if nonfinite:
        what += f" ({nonfinite} with non-finite positions)"
    return SimulationError(_advice(model, state, dt, what))


def check_finite(model: Model, state: State, new: State, dt: float) -> None:
    """Raise SimulationError if the step from ``state`` gave a non-finite ``new`` state."""
    if not bool(torch.isfinite(new.x.sum() + new.v.sum() + new.F.sum())):
        raise SimulationError(_advice(model, state, dt, "the state became non-finite (NaN or inf)"))


def _advice(model: Model, state: State, dt: float, what: str) -> str:
    finite_v = state.v[torch.isfinite(state.v).all(dim=1)]
    vmax = float(finite_v.norm(dim=1).max()) if len(finite_v) else 0.0
    suggest = min(0.5 * dt, 0.3 * model.h_cfl / (model.wave_speed + vmax))
    return (f"step {state.step} (t = {state.time:.6g}): {what}; the run is unstable or leaves the "
            f"domain at dt = {dt:.3g}. Try dt <= {suggest:.3g} (solver.dt, or a smaller solver.cfl), "
            "or enlarge the domain")
