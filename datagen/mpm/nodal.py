"""The nodal update of every engine (UMLS Algorithm 1 lines 4-6): P2G sums -> nodal velocities
before and after the update, with gravity, damping, walls, colliders, mirror ghosts and grips.

The slot path (:mod:`~datagen.mpm.transfers`) and the fixed operators
(:mod:`~datagen.mpm.operators`) both hand their P2G sums [m, p, f_int] to :func:`nodal_update`,
so they apply the same boundary conditions in the same order.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import torch

from .boundary import Mirror, apply_conditions, apply_mirrors, fold_mirrors
from .kernels import KernelResult
from .model import Grip, Model
from .state import Reference, State

__all__ = ["Nodal", "MASS_FLOOR", "nodal_update", "index_conditions", "constrain", "move_grips"]

MASS_FLOOR = 1e-10  # nodes lighter than this fraction of the mean particle mass are treated as empty


@dataclass(frozen=True)
class Nodal:
    """Node fields of one step: mass (N,); velocity before (v) and after (v_new) the update, (d, N)."""

    mass: torch.Tensor
    v: torch.Tensor
    v_new: torch.Tensor


def nodal_update(model: Model, state: State, k: KernelResult, sums: torch.Tensor, dt: float) -> Nodal:
    """Nodal velocities before and after the update, constrained (UMLS eq. 13, Alg. 1 l. 4-6).

    sums: (1+2d, N) the P2G sums [m, p, f_int], modified in place: the sums of mirror ghosts are
    first folded onto the nodes they mirror (:func:`~datagen.mpm.boundary.fold_mirrors`), and the
    ghosts' velocity before the update is mirrored as well as after it, so that FLIP's increment
    v_new - v is the odd extension of the physical nodes' increment. Then gravity, damping, the
    boundary conditions and colliders (:func:`constrain`, on the nodes that carry mass) and the
    held grips. k: the kernel of the P2G sums; dt: the step (s).
    """
    d = model.dim
    by_index = index_conditions(model, state)
    sums = fold_mirrors(sums, by_index, [1.0] + [-1.0] * (2 * d))  # mass even about a wall, p and f odd
    mass, momentum, force = sums[0], sums[1:1 + d], sums[1 + d:]
    active = mass > MASS_FLOOR * state.mass.mean()
    safe = torch.where(active, mass, torch.ones_like(mass))
    v = apply_mirrors(torch.where(active, momentum / safe, 0.0), by_index)
    accel = force / safe + model.gravity[:, None]  # gravity: f_ext = m_i g (UMLS eq. 11)
    v_new = torch.where(active, v + dt * accel, 0.0)  # UMLS eq. 13
    if model.damping:
        v_new = v_new / (1.0 + model.damping * dt)
    v_new = _hold_grips(model, state, k, constrain(model, state, v_new, dt, active))
    return Nodal(mass=torch.where(active, mass, 0.0), v=v, v_new=v_new)


def index_conditions(model: Model, state: State) -> tuple:
    """The conditions applied by node index: all of them in eulerian mode (or without wall
    planes), else the pinned ones (the walls act on moved node positions there)."""
    return model.conditions if state.reference is None or model.wall_planes is None else model.pinned


def constrain(model: Model, state: State, v: torch.Tensor, dt: float,
              active: torch.Tensor | None = None) -> torch.Tensor:
    """Boundary conditions on nodal velocities v (d, N), in place: by node index in eulerian
    mode; on the moved node positions (wall planes) plus the pinned nodes otherwise.

    With colliders (:mod:`~datagen.mpm.colliders`) the order is: walls and clamps, then the
    colliders (at state.time, moving over [t, t + dt]) on the ``active`` nodes ((N,) bool, the
    nodes that carry mass; None: all), then the mirror ghosts, which copy the final velocities
    of the nodes they mirror. dt: the step (s).
    """
    ref = state.reference
    by_plane = ref is not None and bool(model.wall_planes)
    if by_plane and ref.drift >= ref.wall_gap:  # only nodes in the kernel's support carry velocity
        nodes, members = _wall_members(model, ref)
        for j, hit in enumerate(members.any(1).tolist()):
            if hit:
                model.wall_planes[j].apply_to(v, nodes[members[j]])
    conditions = index_conditions(model, state)
    if not model.colliders:
        return apply_conditions(v, conditions)
    v = apply_conditions(v, [c for c in conditions if not isinstance(c, Mirror)])
    v = _apply_colliders(model, state, v, dt, active)
    return apply_conditions(v, [c for c in conditions if isinstance(c, Mirror)])


def _apply_colliders(model: Model, state: State, v: torch.Tensor, dt: float,
                     active: torch.Tensor | None) -> torch.Tensor:
    """Every collider's contact on the nodal velocities v (d, N), in place: at the background
    nodes' positions in eulerian mode, at their moved positions (state.reference.nodes) otherwise."""
    q = model.node_positions.T if state.reference is None else state.reference.nodes  # (d, N)
    if active is None:
        for collider in model.colliders:
            collider.apply(v, q, state.time, dt)
        return v
    ids = active.nonzero()[:, 0]
    sub, q = v[:, ids], q[:, ids]
    for collider in model.colliders:
        collider.apply(sub, q, state.time, dt)
    v[:, ids] = sub
    return v


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


# ----------------------------------------------------------------------------- grips
def _held_grips(model: Model, state: State) -> Iterator[tuple[Grip, torch.Tensor]]:
    """(grip, velocity (d,)) of every grip held at state.time."""
    for grip in model.grips:
        velocity = grip.velocity(state.time)
        if velocity is not None:
            yield grip, torch.as_tensor(velocity, dtype=state.x.dtype, device=state.x.device)


def _hold_grips(model: Model, state: State, k: KernelResult, v_new: torch.Tensor) -> torch.Tensor:
    """Every node a held grip's particles touch takes the grip velocity (v_new: (d, N), in place)."""
    for grip, velocity in _held_grips(model, state):
        index = k.index[grip.ids]
        v_new[:, torch.unique(index[index >= 0])] = velocity[:, None]
    return v_new


def move_grips(model: Model, state: State, new: State, dt: float) -> State:
    """Held grip particles of ``new`` (the step's result from ``state``) move exactly with their grip."""
    held = list(_held_grips(model, state))
    if not held:
        return new
    x, v = new.x.clone(), new.v.clone()
    for grip, velocity in held:
        v[grip.ids] = velocity
        x[grip.ids] = state.x[grip.ids] + dt * velocity
    return replace(new, x=x, v=v)
