"""Many substeps in one compiled call (``csrc/substeps.c``): :func:`advance`.

A small substep -- a press letter's 1,200 particles -- spends more time in the two hundred torch
operators and the Python between the compiled kernels than in the kernels themselves
(``benchmarks/substep_overhead.py``). :func:`advance` runs ``n`` substeps inside C instead and
returns to Python once per call:

- **eulerian** (:func:`~datagen.mpm.step.eulerian_step`): cell search, kernel (with the closest
  non-negative kernel where MLS weights go negative), stress, P2G, the mirror folds, the nodal
  update with gravity, damping, walls, clamps, colliders and mirror ghosts, FLIP or PIC G2P, the
  F update and F-bar. Inside its plan the background's nodes and cells are renumbered along a
  Z-order curve for memory locality, keeping every slot and hash-bucket order, so the results
  are bitwise those of the mesh's own numbering.
- **A-ULMPM total and adaptive** (:func:`~datagen.mpm.reference.reference_step`) between updates
  of the reference configuration: P2G with the reference kernel and the stress tau (F^{sn})^-T,
  the nodal update with the wall planes on the moved nodes, the pinned conditions and the
  colliders, G2P with F^{sn} += dt grad_s v and F = F^{sn} F^{0s}, F-bar, the moved nodes and
  their drift, and the adaptive mode's strain and contact triggers. A substep that makes an
  update due ends the call; the rebuild (a new kernel, clusters, gaps) runs in Python.

It applies to the UMLS kernel with FLIP or PIC on the CPU in float64, elastic materials (linear,
Neo-Hookean, fixed corotated) and no grips; everything else (APIC, MUSL, plasticity, viscosity,
grips, the linear and B-spline kernels, other devices) steps through
:func:`~datagen.mpm.step.step` as before, and so does any substep the compiled code declines
before changing the state (a particle lost from the mesh, a non-finite result): the Python step
then raises :class:`~datagen.mpm.errors.SimulationError` with its advice. The Python step is the
reference: the tests hold every feature of the compiled substeps to it at round-off, and node
sums use fixed particle blocks, so results do not depend on the thread count.
**Precision.** ``Model.precision="float32"`` (``solver.precision: float32``) runs a second build of
the same source (``-DBSMS_REAL=float``, csrc/umls.c's ``real``): the kernel's slots, the stress
coefficients, the node sums' block copies, the G2P fields and the arithmetic over them in single
precision; the particle state (x, v, F), the mesh, the cell search and the node velocities stay
float64, so positions and deformation gradients accumulate their small per-substep increments
without float32's rounding (at 0.1 m a float32 position resolves 7e-9 m, about the displacement of a
substep). Steps outside the compiled substeps run in float64. Errors against float64: docs/solver.md.
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

from . import linalg
from .boundary import Mirror, SeparatingSlip, Slip, Sticky
from .kernels import MeshTables
from .locate import BARYCENTRIC_TOL
from .materials import FixedCorotated, LinearElastic, NeoHookean
from .model import Model
from .nodal import MASS_FLOOR, index_conditions
from .state import State
from .step import step

__all__ = ["advance", "applies", "library"]

SOURCE = Path(__file__).with_name("csrc") / "substeps.c"
DEPENDS = tuple(Path(__file__).with_name("csrc") / name for name in ("umls.c", "nodes.h", "reference.h"))
_MATERIALS = {LinearElastic: 0, NeoHookean: 1, FixedCorotated: 2}
_SHAPES = {"disk": 0, "sphere": 0, "box": 1, "wedge": 2}
_PLANES = {"sticky": 0, "slip": 1, "separating": 2}
_STATUS = {4: "out of memory", 5: "unsupported shapes"}  # the C codes that end a call with an error (csrc/nodes.h)
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


class _Reference(ctypes.Structure):
    _fields_ = [("index", ptr), ("weight", ptr), ("grad", ptr), ("support", ptr), ("rest", ptr), ("wall_gap", f64),
                ("epsilon", f64), ("fraction", f64), ("contact", f64), ("adaptive", i64), ("n_planes", i64),
                ("n_clusters", i64), ("planes_due", i64), ("plane_kind", ptr), ("cluster", ptr),
                ("plane_friction", ptr), ("normal", ptr), ("offset", ptr), ("low", ptr), ("high", ptr),
                ("tangents", ptr), ("lower", ptr), ("upper", ptr), ("gaps", ptr)]


# each Model.precision: its build's preprocessor definitions and the dtype of the slots it reads
_BUILDS = {"float64": ((), torch.float64), "float32": (("-DBSMS_REAL=float",), torch.float32)}


@functools.cache
def library(precision: str = "float64") -> ctypes.CDLL | None:
    """The compiled substeps (built on first use), or None where they cannot be. precision: the
    kernel's and the transfers' arithmetic (:attr:`Model.precision`), a build of its own."""
    lib = compiled.build(SOURCE, "compiled substeps", "each substep runs through the Python step, several times "
                         "slower", depends=DEPENDS, defines=_BUILDS[precision][0])
    if lib is None:
        return None
    lib.bsms_substeps.argtypes = [ctypes.POINTER(_Plan), i64, f64, ptr, ptr, ptr, ptr, ctypes.POINTER(f64),
                                  ctypes.POINTER(i64)]
    lib.bsms_substeps.restype = ctypes.c_int
    lib.bsms_reference_substeps.argtypes = [ctypes.POINTER(_Plan), ctypes.POINTER(_Reference), i64, f64] + \
        [ptr] * 6 + [ctypes.POINTER(f64)] * 2 + [ctypes.POINTER(i64)]
    lib.bsms_reference_substeps.restype = ctypes.c_int
    return lib


def applies(model: Model, state: State) -> bool:
    """Whether :func:`advance` runs this model's substeps compiled (module docstring)."""
    return (os.environ.get("BSMS_FUSED", "1") != "0" and (model.reference != "eulerian" or state.reference is None)
            and model.kernel == "umls" and model.transfer in ("flip", "pic")
            and isinstance(model.background, MeshTables)
            and not (model.grips or model.plastic or model.viscous or state.velocity_gradient is not None)
            and all(type(m) in _MATERIALS for m, _ in model.materials)
            and all(type(c) in (Sticky, Slip, SeparatingSlip, Mirror) for c in (*model.conditions, *model.pinned))
            and all(w.kind in _PLANES for w in model.wall_planes or ())
            and state.x.device.type == "cpu" and state.x.dtype == torch.float64
            and model.node_positions.dtype == torch.float64 and model.dim in (2, 3)
            and library(model.precision) is not None)


class _Compiled:
    """A model's tables in the layout of ``csrc/substeps.c`` (the tensors kept alive with it)."""

    def __init__(self, model: Model, state: State):
        n_particles = len(state.x)
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
        nodes = model.node_positions.cpu()
        if model.reference == "eulerian":  # nodes and cells renumbered along a Z-order curve (module docstring)
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
            loc = tables.locator
            plan.locator = _Locator(address(loc.origin), address(loc.corner.cpu()[cell_order]),
                                    address(loc.to_bary.cpu()[cell_order]), loc.spacing, BARYCENTRIC_TOL,
                                    address(loc.shape), address(loc.strides),
                                    address(_relabel(self.cell_rank, loc.buckets.cpu())),  # same order per bucket
                                    loc.buckets.shape[0], loc.buckets.shape[1])
        else:  # A-ULMPM: the reference kernel comes from Python in the mesh's numbering
            node_id = lambda ids: ids  # noqa: E731
            plan.nodes = address(nodes)
        mu, lam = torch.empty(n_particles, dtype=torch.float64), torch.empty(n_particles, dtype=torch.float64)
        kind = torch.empty(n_particles, dtype=torch.int8)
        for material, ids in model.materials:
            sel = slice(None) if ids is None else ids.cpu()
            mu[sel], lam[sel], kind[sel] = material.mu, material.lam, _MATERIALS[type(material)]
        plan.mu, plan.lam, plan.material = address(mu), address(lam), address(kind)
        self.conditions = self._conditions(model, index_conditions(model, state), address,
                                           lambda t: address(node_id(t.cpu().to(torch.int64))))
        plan.conditions, plan.n_conditions = ctypes.addressof(self.conditions), len(self.conditions)
        self.colliders = (_Collider * max(1, len(model.colliders)))()
        for slot, collider in zip(self.colliders, model.colliders, strict=False):
            slot.shape, slot.friction, slot.reach = _SHAPES[collider.shape], collider.friction, collider._reach()
            for a, s in enumerate(collider.size):
                slot.size[a] = s
        plan.colliders, plan.n_colliders = ctypes.addressof(self.colliders), len(model.colliders)

    @staticmethod
    def _conditions(model: Model, conditions: tuple, address, node_ids):
        """The index ``conditions`` in the order :func:`~datagen.mpm.nodal.constrain` applies them;
        the colliders (kind 4) after the walls and clamps and before the mirror ghosts. address(t,
        dtype): a kept tensor's address; node_ids(t): the address of node ids in the plan's numbering."""
        order = list(conditions)
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


def _compiled(model: Model, state: State) -> _Compiled:
    """The model's plan for ``state``'s particles (built once per model; the reference modes build
    theirs once a reference exists, so that the index conditions are the pinned ones)."""
    plan = _plans.get(model)
    if plan is None or plan.plan.P != len(state.x):
        plan = _plans[model] = _Compiled(model, state)
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
    left = steps
    while left > 0:
        ref = state.reference
        if model.reference != "eulerian" and (ref is None or ref.kernel is None or ref.stale):
            state = step(model, state, dt)  # (re)builds the reference configuration
            left -= 1
            continue
        call = _eulerian_call if model.reference == "eulerian" else _reference_call
        state, done, code = call(model, state, dt, left)
        left -= done
        if code in (1, 3) and left > 0:  # this substep in torch: it raises with its advice
            state = step(model, state, dt)
            left -= 1
    return state


def _prepared(model: Model, state: State, dt: float, steps: int) -> _Compiled:
    """The model's plan, set for ``steps`` substeps from ``state`` (collider paths, masses, threads)."""
    compiled_plan = _compiled(model, state)
    plan = compiled_plan.plan
    compiled_plan.paths = _collider_paths(model, state.time, dt, steps)  # kept alive with the plan
    for slot, (centre, velocity) in zip(compiled_plan.colliders, compiled_plan.paths, strict=False):
        slot.centre, slot.velocity = centre.ctypes.data, velocity.ctypes.data
    compiled_plan.particles = mass, volume0 = state.mass.contiguous(), state.volume0.contiguous()
    plan.mass, plan.volume0 = mass.data_ptr(), volume0.data_ptr()
    plan.mass_floor, plan.threads = float(MASS_FLOOR * mass.mean()), torch.get_num_threads()
    return compiled_plan


def _check(code: int, model: Model, state: State) -> None:
    if code in (4, 5):
        raise RuntimeError(f"compiled substeps: {_STATUS[code]} ({len(state.x)} particles, {model.n_nodes} nodes)")


def _eulerian_call(model: Model, state: State, dt: float, steps: int) -> tuple[State, int, int]:
    compiled_plan = _prepared(model, state, dt, steps)
    x, v, F = (t.clone(memory_format=torch.contiguous_format) for t in (state.x, state.v, state.F))
    cell = _relabel(compiled_plan.cell_rank, state.cell).contiguous()
    time, done = f64(state.time), i64(0)
    code = library(model.precision).bsms_substeps(ctypes.byref(compiled_plan.plan), steps, dt, x.data_ptr(),
                                                  v.data_ptr(), F.data_ptr(), cell.data_ptr(), ctypes.byref(time),
                                                  ctypes.byref(done))
    _check(code, model, state)
    if done.value:
        cell = _relabel(compiled_plan.cell_order, cell)  # back to the mesh's numbering
        state = replace(state, x=x, v=v, F=F, cell=cell, time=time.value, step=state.step + done.value)
    return state, done.value, code


def _reference_call(model: Model, state: State, dt: float, steps: int) -> tuple[State, int, int]:
    """A-ULMPM substeps on the current reference configuration until one makes an update due."""
    compiled_plan = _prepared(model, state, dt, steps)
    ref, keep = state.reference, []

    def address(t: torch.Tensor | None, dtype=None) -> int | None:
        if t is None:
            return None
        t = t.to(dtype=dtype or t.dtype).contiguous()
        keep.append(t)
        return t.data_ptr()

    k, real = ref.kernel, _BUILDS[model.precision][1]
    R = _Reference(address(k.index), address(k.weight, real), address(k.grad_axes, real),
                   address(ref.active, torch.uint8), address(model.node_positions), ref.wall_gap, model.epsilon,
                   model.fraction,
                   model.contact_margin * model.cell_size if model.contact_margin is not None else -1.0,
                   int(model.reference == "adaptive"), len(model.wall_planes or ()),
                   0 if ref.gaps is None else ref.gaps.shape[0], 0)
    R.cluster, R.gaps = address(ref.cluster, torch.int64), address(ref.gaps, torch.float64)
    if model.wall_planes:
        table = model._walls
        R.plane_kind = address(torch.tensor([_PLANES[w.kind] for w in model.wall_planes]))
        R.plane_friction = address(torch.tensor([float(w.friction) for w in model.wall_planes], dtype=torch.float64))
        for name in ("normal", "offset", "low", "high", "tangents", "lower", "upper"):
            setattr(R, name, address(table[name], torch.float64))
    x, v = (t.clone(memory_format=torch.contiguous_format) for t in (state.x, state.v))
    F, Fsn = (linalg.components(t).contiguous().clone() for t in (state.F, ref.Fsn))  # (d, d, P)
    F0s, q = address(linalg.components(ref.F0s)), ref.nodes.contiguous().clone()
    drift, time, done = f64(ref.drift), f64(state.time), i64(0)
    code = library(model.precision).bsms_reference_substeps(
        ctypes.byref(compiled_plan.plan), ctypes.byref(R), steps, dt, x.data_ptr(), v.data_ptr(), F.data_ptr(),
        Fsn.data_ptr(), F0s, q.data_ptr(), ctypes.byref(drift), ctypes.byref(time), ctypes.byref(done))
    _check(code, model, state)
    if done.value:
        ref = replace(ref, Fsn=linalg.matrices(Fsn), nodes=q, drift=drift.value,
                      stale={6: "strain", 7: "contact"}.get(code, ""))
        state = replace(state, x=x, v=v, F=linalg.matrices(F), reference=ref, time=time.value,
                        step=state.step + done.value)
    return state, done.value, code
