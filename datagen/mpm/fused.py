"""Many eulerian substeps in one compiled call (``csrc/substeps.c``): :func:`advance`.

A small substep -- a press letter's 1,200 particles -- spends more time in the two hundred torch
operators and the Python between the compiled kernels than in the kernels themselves
(``benchmarks/substep_overhead.py``). :func:`advance` runs ``n`` substeps of
:func:`~datagen.mpm.step.eulerian_step` inside C instead: cell search, kernel, stress, P2G, the
mirror folds, the nodal update with gravity, damping, walls, clamps, colliders and mirror
ghosts, FLIP or PIC G2P, the F update and F-bar, returning to Python once per call.

It applies to the eulerian UMLS kernel with FLIP or PIC on the CPU in float64, elastic
materials (linear, Neo-Hookean, fixed corotated), and no grips; everything else (the A-ULMPM
reference modes, APIC, MUSL, plasticity, viscosity, grips, other kernels or devices) steps
through :func:`~datagen.mpm.step.step` as before, and so does any substep the compiled code
declines before changing the state: a particle lost from the mesh, a kernel with negative MLS
weights (replaced in torch by the closest non-negative one) or a non-finite result (torch then
raises :class:`~datagen.mpm.errors.SimulationError` with its advice). The torch step is the
reference: the tests hold every feature of the compiled substep to it at round-off, and node
sums use fixed particle blocks, so results do not depend on the thread count.
``BSMS_NATIVE=0`` turns it off with the other compiled code; ``BSMS_FUSED=0`` turns off only this
(every substep a Python step with the compiled kernels, as before it: for comparisons).
"""

from __future__ import annotations

import ctypes
import functools
import os
import weakref
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from datagen import compiled

from .boundary import Mirror, SeparatingSlip, Slip, Sticky
from .kernels import MeshTables
from .locate import BARYCENTRIC_TOL
from .materials import FixedCorotated, LinearElastic, NeoHookean
from .model import Model
from .nodal import MASS_FLOOR
from .state import State
from .step import step

__all__ = ["advance", "applies", "library"]

SOURCE = Path(__file__).with_name("csrc") / "substeps.c"
DEPENDS = (Path(__file__).with_name("csrc") / "umls.c",)
_MATERIALS = {LinearElastic: 0, NeoHookean: 1, FixedCorotated: 2}
_SHAPES = {"disk": 0, "sphere": 0, "box": 1, "wedge": 2}
_STATUS = {1: "a particle left the cells searched", 2: "negative MLS weights", 3: "a non-finite result",
           4: "out of memory", 5: "unsupported shapes"}
i64, f64, ptr = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p


class _Condition(ctypes.Structure):
    _fields_ = [("kind", i64), ("count", i64), ("nodes", ptr), ("normals", ptr), ("friction", f64), ("per", i64),
                ("sources", ptr), ("weights", ptr), ("wall_count", i64), ("wall", ptr)]


class _Collider(ctypes.Structure):
    _fields_ = [("shape", i64), ("size", f64 * 3), ("friction", f64), ("reach", f64), ("centre", ptr),
                ("velocity", ptr)]


class _Locator(ctypes.Structure):
    _fields_ = [("origin", ptr), ("corner", ptr), ("to_bary", ptr), ("spacing", f64), ("tol", f64), ("shape", ptr),
                ("strides", ptr), ("buckets", ptr), ("n_buckets", i64), ("per_bucket", i64)]


class _Plan(ctypes.Structure):
    _fields_ = [(name, i64) for name in ("P", "K", "d", "N", "transfer_pic", "fbar", "n_conditions", "n_colliders",
                                          "threads")] + [
        ("inv_h", f64), ("mass_floor", f64), ("damping", f64), ("gravity", f64 * 3), ("ring", ptr),
        ("adjacency", ptr), ("nodes", ptr), ("cells", ptr), ("bary_grad", ptr), ("mass", ptr), ("volume0", ptr),
        ("mu", ptr), ("lam", ptr), ("material", ptr), ("conditions", ptr), ("colliders", ptr), ("locator", _Locator)]


@functools.cache
def library() -> ctypes.CDLL | None:
    """The compiled substeps (built on first use), or None where they cannot be."""
    lib = compiled.build(SOURCE, "compiled substeps", "each substep runs through the Python step, several times "
                         "slower", depends=DEPENDS)
    if lib is None:
        return None
    lib.bsms_substeps.argtypes = [ctypes.POINTER(_Plan), i64, f64, ptr, ptr, ptr, ptr, ctypes.POINTER(f64),
                                  ctypes.POINTER(i64)]
    lib.bsms_substeps.restype = ctypes.c_int
    return lib


def applies(model: Model, state: State) -> bool:
    """Whether :func:`advance` runs this model's substeps compiled (module docstring)."""
    return (os.environ.get("BSMS_FUSED", "1") != "0" and model.reference == "eulerian" and state.reference is None
            and model.kernel == "umls" and model.transfer in ("flip", "pic")
            and isinstance(model.background, MeshTables)
            and not (model.grips or model.plastic or model.viscous or state.velocity_gradient is not None)
            and all(type(m) in _MATERIALS for m, _ in model.materials)
            and all(type(c) in (Sticky, Slip, SeparatingSlip, Mirror) for c in model.conditions)
            and state.x.device.type == "cpu" and state.x.dtype == torch.float64
            and model.node_positions.dtype == torch.float64 and model.dim in (2, 3) and library() is not None)


class _Compiled:
    """A model's tables in the layout of ``csrc/substeps.c`` (the tensors kept alive with it)."""

    def __init__(self, model: Model, n_particles: int):
        tables, dev = model.background, torch.device("cpu")
        keep = self.keep = []

        def address(t: torch.Tensor, dtype=None) -> int:
            t = t.to(device=dev, dtype=dtype or t.dtype).contiguous()
            keep.append(t)
            return t.data_ptr()

        plan = self.plan = _Plan()
        plan.P, plan.K, plan.d, plan.N = n_particles, tables.ring.shape[1], model.dim, model.n_nodes
        plan.transfer_pic, plan.fbar = int(model.transfer == "pic"), int(model.fbar)
        plan.inv_h, plan.damping = 1.0 / tables.h, float(model.damping)
        for a, g in enumerate(model.gravity.tolist()):
            plan.gravity[a] = g
        # nodes and cells renumbered along a Z-order curve inside the plan (module docstring)
        nodes = model.node_positions.cpu()
        node_order = _z_order(nodes.numpy())
        cell_order = _z_order(nodes[tables.cells.cpu()].mean(1).numpy())
        self.node_rank, self.cell_rank = _ranks(node_order), _ranks(cell_order)
        self.cell_order = cell_order
        node_id = lambda ids: _relabel(self.node_rank, ids)  # noqa: E731
        plan.ring = address(node_id(tables.ring.cpu()[cell_order]))
        plan.adjacency = address(tables.ring_adjacency.cpu()[cell_order], torch.uint8)
        plan.nodes = address(nodes[node_order])
        plan.cells = address(node_id(tables.cells.cpu()[cell_order]))
        plan.bary_grad = address(tables.bary_grad.cpu()[cell_order], torch.float64)
        mu, lam = torch.empty(n_particles, dtype=torch.float64), torch.empty(n_particles, dtype=torch.float64)
        kind = torch.empty(n_particles, dtype=torch.int8)
        for material, ids in model.materials:
            sel = slice(None) if ids is None else ids.cpu()
            mu[sel], lam[sel], kind[sel] = material.mu, material.lam, _MATERIALS[type(material)]
        plan.mu, plan.lam, plan.material = address(mu), address(lam), address(kind)
        self.conditions = self._conditions(model, address, lambda t: address(node_id(t.cpu().to(torch.int64))))
        plan.conditions, plan.n_conditions = ctypes.addressof(self.conditions), len(self.conditions)
        self.colliders = (_Collider * max(1, len(model.colliders)))()
        for slot, collider in zip(self.colliders, model.colliders, strict=False):
            slot.shape, slot.friction, slot.reach = _SHAPES[collider.shape], collider.friction, collider._reach()
            for a, s in enumerate(collider.size):
                slot.size[a] = s
        plan.colliders, plan.n_colliders = ctypes.addressof(self.colliders), len(model.colliders)
        loc = tables.locator
        plan.locator = _Locator(address(loc.origin), address(loc.corner.cpu()[cell_order]),
                                address(loc.to_bary.cpu()[cell_order]), loc.spacing, BARYCENTRIC_TOL,
                                address(loc.shape), address(loc.strides),
                                address(_relabel(self.cell_rank, loc.buckets.cpu())),  # same order per bucket
                                loc.buckets.shape[0], loc.buckets.shape[1])

    @staticmethod
    def _conditions(model: Model, address, node_ids):
        """The conditions in the order :func:`~datagen.mpm.nodal.constrain` applies them; the
        colliders (kind 4) after the walls and clamps and before the mirror ghosts. address(t,
        dtype): a kept tensor's address; node_ids(t): the address of node ids in the plan's numbering."""
        order = list(model.conditions)
        if model.colliders:
            order = [c for c in order if not isinstance(c, Mirror)] + ["colliders"] + \
                    [c for c in order if isinstance(c, Mirror)]
        out = (_Condition * max(1, len(order)))()
        for slot, c in zip(out, order, strict=False):
            if c == "colliders":
                slot.kind = 4
                continue
            slot.kind = {Sticky: 0, Slip: 1, SeparatingSlip: 2, Mirror: 3}[type(c)]
            slot.nodes = node_ids(c.ghosts if isinstance(c, Mirror) else c.nodes)
            slot.count = len(c.ghosts if isinstance(c, Mirror) else c.nodes)
            if isinstance(c, (Slip, SeparatingSlip)):
                slot.normals = address(c.normals.T, torch.float64)
                slot.friction = getattr(c, "friction", 0.0)
            if isinstance(c, Mirror):
                slot.per, slot.sources = c.sources.shape[1], node_ids(c.sources)
                slot.weights = address(c.weights, torch.float64)
                if c.wall is not None:
                    slot.wall_count, slot.wall = len(c.wall), node_ids(c.wall)
        return out


def _z_order(points: np.ndarray) -> torch.Tensor:
    """The permutation (int64) that sorts points (n, d) along a Z-order (Morton) curve: each
    coordinate quantised to 21 bits over the points' box, the bits interleaved, ties by index."""
    lo, hi = points.min(0), points.max(0)
    q = ((points - lo) / np.where(hi > lo, hi - lo, 1.0) * (2**21 - 1)).astype(np.uint64)
    key = np.zeros(len(points), dtype=np.uint64)
    d = points.shape[1]
    for bit in range(21):
        for a in range(d):
            key |= ((q[:, a] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(bit * d + a)
    return torch.from_numpy(np.argsort(key, kind="stable"))


def _ranks(order: torch.Tensor) -> torch.Tensor:
    """The inverse permutation of ``order``: rank[order[i]] = i."""
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(order))
    return rank


def _relabel(rank: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """ids (any shape, -1 = none) in the renumbering ``rank`` (old id -> new id)."""
    return torch.where(ids >= 0, rank[ids.clamp(min=0)], ids)


_plans: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _compiled(model: Model, n_particles: int) -> _Compiled:
    plan = _plans.get(model)
    if plan is None or plan.plan.P != n_particles:
        plan = _plans[model] = _Compiled(model, n_particles)
    return plan


def _collider_paths(model: Model, time: float, dt: float, steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per collider: its centre at each substep's start (steps + 1, d) and its mean velocity over
    each substep (steps, d), at the times the Python step would see (t <- t + dt, one at a time)."""
    times = np.add.accumulate(np.concatenate([[time], np.full(steps, dt)]))
    out = []
    for collider in model.colliders:
        path = collider.path
        centre = np.stack([np.interp(times, path.times, path.points[:, k]) for k in range(path.dim)], 1)
        velocity = (centre[1:] - centre[:-1]) / (times[1:] - times[:-1])[:, None]
        out.append((np.ascontiguousarray(centre), np.ascontiguousarray(velocity)))
    return out


def advance(model: Model, state: State, dt: float, steps: int) -> State:
    """``steps`` substeps of ``dt`` from ``state``: the state ``step`` would reach, in as few
    compiled calls as the substeps allow (module docstring); step by step where it does not apply."""
    if steps <= 0 or not applies(model, state):
        for _ in range(steps):
            state = step(model, state, dt)
        return state
    lib, left = library(), steps
    while left > 0:
        compiled_plan = _compiled(model, len(state.x))
        plan = compiled_plan.plan
        paths = _collider_paths(model, state.time, dt, left)
        for slot, (centre, velocity) in zip(compiled_plan.colliders, paths, strict=False):
            slot.centre, slot.velocity = centre.ctypes.data, velocity.ctypes.data
        mass, volume0 = state.mass.contiguous(), state.volume0.contiguous()
        plan.mass, plan.volume0 = mass.data_ptr(), volume0.data_ptr()
        plan.mass_floor, plan.threads = float(MASS_FLOOR * mass.mean()), torch.get_num_threads()
        x, v, F = (t.clone(memory_format=torch.contiguous_format) for t in (state.x, state.v, state.F))
        cell = _relabel(compiled_plan.cell_rank, state.cell).contiguous()
        time, done = f64(state.time), i64(0)
        code = lib.bsms_substeps(ctypes.byref(plan), left, dt, x.data_ptr(), v.data_ptr(), F.data_ptr(),
                                 cell.data_ptr(), ctypes.byref(time), ctypes.byref(done))
        if code in (4, 5):
            raise RuntimeError(f"compiled substeps: {_STATUS[code]} ({len(state.x)} particles, {model.n_nodes} nodes)")
        if done.value:
            cell = _relabel(compiled_plan.cell_order, cell)  # back to the mesh's numbering
            state = replace(state, x=x, v=v, F=F, cell=cell, time=time.value, step=state.step + done.value)
        left -= done.value
        if code != 0 and left > 0:  # this substep in torch: it replaces the kernel or raises
            state = step(model, state, dt)
            left -= 1
    return state
