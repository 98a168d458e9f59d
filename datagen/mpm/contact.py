"""The force the boundary conditions exert on the material, for diagnostics (e.g. the contact
force on a container)."""

from __future__ import annotations

from dataclasses import replace

import torch

from .model import Model, compute_kernel
from .nodal import nodal_update
from .state import State
from .transfers import SLOT_TRANSFERS

__all__ = ["wall_force"]


def wall_force(model: Model, state: State, dt: float) -> torch.Tensor:
    """(d,) the total force the walls and clamps exert on the material at ``state``, over a step dt:
    sum_i m_i (v_i constrained - v_i free) / dt, from one P2G and two nodal updates (with and
    without the boundary conditions). Uses the reference kernel in the total/adaptive modes."""
    ref = state.reference
    k = ref.kernel if ref is not None and ref.kernel is not None else compute_kernel(model, state.x, state.cell)
    sums = SLOT_TRANSFERS[model.transfer][0](model, state, k)
    free_model = replace(model, conditions=(), wall_planes=None, pinned=(), grips=())
    free = nodal_update(free_model, state, k, sums.clone(), dt)
    held = nodal_update(model, state, k, sums, dt)
    return (held.mass * (held.v_new - free.v_new)).sum(1) / dt
