"""The A-ULMPM reference-configuration step (A-ULMPM §3.4, §5, App. B): the total and adaptive
modes of ``Model.reference``.

- ``total`` (s = 0): the kernel of the initial positions is kept for the whole run.
- ``adaptive``: the kernel of configuration s is kept until an update is triggered, by the
  A-ULMPM eq. 33 criterion (:func:`strain_criterion`) or by the contact trigger (below).
- ``eulerian`` (s = n) is the plain UMLS step, :func:`~datagen.mpm.step.eulerian_step`.

Between updates particles carry F^{0s} and F^{sn} (:class:`~datagen.mpm.state.Reference`),
F = F^{sn} F^{0s} (A-ULMPM eq. 32); the nodal force is f_i = -sum_p V_p^0 P(F_p) (F_p^{0s})^T
grad_s w_ip (A-ULMPM App. B eq. 44), computed as tau_p (F_p^{sn})^-T grad_s w_ip with
tau = P F^T; F^{sn} <- F^{sn} + dt grad_s v_p (A-ULMPM eqs. 45-47). The background nodes move
with their velocities, q_i <- q_i + dt v_i, and walls act on those moved positions
(:class:`~datagen.mpm.model.WallPlane`). An update sets F^{0s} <- F, F^{sn} <- I and rebuilds
the kernel at the particles' current positions in the undeformed background. Between updates
FLIP, PIC and APIC transfer by fixed sparse operators (:mod:`~datagen.mpm.operators`), MUSL by
the slot path; both hand their sums to the one nodal update (:mod:`~datagen.mpm.nodal`).

Contact trigger (``contact_margin``, adaptive only). Between updates two bodies only interact
through background nodes they share at s, so bodies that approach each other would pass
through one another. At each update the active nodes are split into clusters (connected through
shared particles) and the gap between every pair of clusters is measured. Between updates
D_c = max |q_i - q_i^s| over the nodes of cluster c bounds how far it moved; an update is
forced when D_a + D_b >= gap_ab - contact_margin * h for some pair (h the background cell
size). A single body in free rigid motion has one cluster and never triggers; walls and
colliders (:mod:`~datagen.mpm.colliders`) need no trigger because they act on the moved node
positions.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from . import linalg
from .errors import check_finite, lost_particles
from .inelastic import post_process
from .kernels import KernelResult
from .model import Model, compute_kernel
from .nodal import move_grips, nodal_update
from .operators import build_operators, flip_increment, operator_g2p, operator_p2g
from .slots import apic_inertia
from .state import Reference, State
from .stress import force_stress
from .transfers import SLOT_TRANSFERS

__all__ = ["reference_step", "strain_criterion", "kernel_rebuilds"]

_CLUSTER_WEIGHT = 0.05  # particles join the clusters of nodes they weigh at least this much


def kernel_rebuilds(state: State) -> int | None:
    """Kernels computed so far in a total/adaptive run (None for eulerian states: one per step)."""
    return None if state.reference is None else state.reference.rebuilds


def strain_criterion(Fsn: torch.Tensor, epsilon: float, fraction: float) -> bool:
    """The A-ULMPM eq. 33 update criterion: mark the particles whose volume changed since the
    reference configuration by delta J_p = |det F_p^{s,n+1} - 1| >= epsilon, and update when
    the marked fraction of all particles reaches ``fraction`` (the paper's eta).

    Fsn: (P, d, d) F^{s,n+1}, in either memory layout.
    """
    delta_J = (linalg.component_det(linalg.components(Fsn)) - 1.0).abs()
    return float((delta_J >= epsilon).to(Fsn.dtype).mean()) >= fraction


def reference_step(model: Model, state: State, dt: float) -> State:
    """One step in the total/adaptive modes: (re)build the reference when due, P2G -> nodal
    update -> G2P with its kernel, move the background nodes, then check the update triggers."""
    ref = state.reference
    if ref is None or ref.kernel is None or ref.stale:
        state = _rebuild(model, state, dt, contact=ref is not None and ref.stale == "contact")
    k = state.reference.kernel
    if state.reference.operators is not None:
        new, v_nodes = _operator_transfer(model, state, k, dt)
    else:
        p2g, g2p = SLOT_TRANSFERS[model.transfer]
        grid = nodal_update(model, state, k, p2g(model, state, k), dt)
        new, v_nodes = g2p(model, state, k, grid, dt), grid.v_new
    new = post_process(model, state, move_grips(model, state, new, dt), k)  # F-bar, plastic return map
    check_finite(model, state, new, dt)
    speed = float(v_nodes.abs().max()) * math.sqrt(model.dim) if v_nodes.numel() else 0.0  # >= max_i |v_i|
    ref = replace(new.reference, nodes=state.reference.nodes + dt * v_nodes, drift=new.reference.drift + dt * speed)
    if model.reference == "adaptive":
        ref = replace(ref, stale=_update_due(model, ref))
    return replace(new, reference=ref, time=state.time + dt, step=state.step + 1)


def _update_due(model: Model, ref: Reference) -> str:
    """Why the next step must rebuild the reference: "strain" (A-ULMPM eq. 33), "contact", or ""."""
    if strain_criterion(ref.Fsn, model.epsilon, model.fraction):
        return "strain"
    return "contact" if _contact_due(model, ref) else ""


def _operator_transfer(model: Model, state: State, k: KernelResult, dt: float) -> tuple[State, torch.Tensor]:
    """P2G -> nodal update -> G2P by the fixed operators (FLIP, PIC or APIC; A-ULMPM App. B
    eqs. 44-47). Returns the new state (without the grips' prescribed motion) and the
    constrained new nodal velocities (d, N)."""
    ref, d = state.reference, model.dim
    ops = ref.operators
    stress = linalg.components(force_stress(model, state))  # (d, d, P) tau (F^{sn})^-T, contiguous
    grid = nodal_update(model, state, k, operator_p2g(ops, state.v, stress, state.affine), dt)
    out = operator_g2p(ops, grid.v_new, len(state.x))  # (a, J, P)
    x = state.x + dt * out[:, 0].T
    v = state.v + flip_increment(ops, grid.v_new - grid.v) if model.transfer == "flip" else out[:, 0].T.contiguous()
    Fsn = linalg.components(ref.Fsn)
    grad_v = out[:, 1:1 + d]  # (a, b, P): d v_a / d X^s_b
    Fsn_new = torch.add(Fsn, grad_v, alpha=dt)  # A-ULMPM eqs. 45-47
    fields = {"x": x, "v": v, "F": linalg.matrices(linalg.component_mm(Fsn_new, linalg.components(ref.F0s))),
              "reference": replace(ref, Fsn=linalg.matrices(Fsn_new))}
    if model.transfer == "apic":  # B_p = sum_i w_ip v_i (x_i - x_p)^T
        fields["affine"] = linalg.matrices(out[:, 1 + d:])
    if model.viscous:  # grad_x v = grad_s v (F^{sn})^-1
        fields["velocity_gradient"] = linalg.matrices(linalg.component_mm(grad_v, linalg.component_inv(Fsn)))
    return replace(state, **fields), grid.v_new


# ----------------------------------------------------------------------------- reference updates
def _rebuild(model: Model, state: State, dt: float, contact: bool = False) -> State:
    """Make the current configuration the reference: F^{0s} <- F, F^{sn} <- I, new kernel."""
    k = compute_kernel(model, state.x, state.cell)
    if k.n_lost:
        raise lost_particles(model, state, k, dt)
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
        kernel=k, F0s=linalg.matrices(linalg.components(state.F).contiguous()), Fsn=linalg.matrices(eye),
        nodes=model.node_positions.T.clone(), active=_support(model, k),
        rebuilds=(old.rebuilds if old is not None else 0) + 1,
        contact_rebuilds=(old.contact_rebuilds if old is not None else 0) + int(contact),
        cluster=cluster, gaps=gaps,
        operators=build_operators(model.transfer, k, state.mass, state.volume0, model.n_nodes),
    )
    ref = replace(ref, wall_gap=_wall_gap(model, ref))
    cell = k.cell if k.cell is not None else state.cell
    return replace(state, reference=ref, affine=affine, cell=cell)


def _apic_to_new_reference(state: State, old: Reference, k: KernelResult) -> torch.Tensor:
    """B such that B D_new^-1 = B_old D_old^-1 (F^{sn})^-1: the same velocity gradient, now
    measured in the new configuration (D = sum w r r^T, the APIC inertia)."""
    C = state.affine @ linalg.inv(apic_inertia(old.kernel))
    return C @ linalg.inv(old.Fsn) @ apic_inertia(k)


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


# ----------------------------------------------------------------------------- contact trigger
def _clusters(model: Model, k: KernelResult) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Clusters of active nodes (connected through shared particles) and their gaps at s.

    A particle links only the nodes it weighs >= _CLUSTER_WEIGHT: the far, faint ring nodes
    two bodies may share cells apart carry no real contact, and must not merge their clusters.
    Gaps are exact up to ``reach = (contact_margin + 4) h``; farther pairs get ``reach``,
    a lower bound, so the trigger stays conservative.
    """
    n_nodes, device = model.n_nodes, model.node_positions.device
    index = k.index.cpu().numpy()
    rows, cols = np.nonzero((index >= 0) & (k.weight.abs().cpu().numpy() >= _CLUSTER_WEIGHT))
    nodes = index[rows, cols]
    n_p = index.shape[0]
    graph = sp.coo_matrix((np.ones(len(nodes)), (rows, n_p + nodes)), shape=(n_p + n_nodes,) * 2)
    _, labels = connected_components(graph, directed=False)
    active = np.unique(nodes)
    if not len(active):
        return torch.full((n_nodes,), -1, device=device), None
    _, cluster_of_active = np.unique(labels[n_p + active], return_inverse=True)
    cluster = np.full(n_nodes, -1, dtype=np.int64)
    cluster[active] = cluster_of_active
    gaps = _cluster_gaps(model, model.node_positions.cpu().numpy()[active], cluster_of_active)
    return torch.as_tensor(cluster, device=device), torch.as_tensor(gaps, dtype=model.node_positions.dtype,
                                                                    device=device)


def _cluster_gaps(model: Model, points: np.ndarray, cluster: np.ndarray) -> np.ndarray:
    """(C, C) the smallest distance between nodes at ``points`` (m, d) of clusters ``cluster`` (m,),
    capped at reach = (contact_margin + 4) h; inf on the diagonal."""
    n_clusters = int(cluster.max()) + 1
    reach = (model.contact_margin + 4.0) * model.cell_size
    gaps = np.full((n_clusters, n_clusters), reach)
    np.fill_diagonal(gaps, np.inf)
    if n_clusters > 1:
        pairs = cKDTree(points).query_pairs(reach, output_type="ndarray")
        a, b = cluster[pairs[:, 0]], cluster[pairs[:, 1]]
        apart = a != b
        dist = np.linalg.norm(points[pairs[apart, 0]] - points[pairs[apart, 1]], axis=1)
        np.minimum.at(gaps, (a[apart], b[apart]), dist)
        np.minimum.at(gaps, (b[apart], a[apart]), dist)
    return gaps


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
