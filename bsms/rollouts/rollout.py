"""Autoregressive rollouts of a learned simulator, and their metrics against the solver.

A rollout starts from frame 0 (positions and the initial velocity) and applies the model
step after step: v_{t+1} = v_t + dv, x_{t+1} = x_t + dt v_{t+1} for free nodes; clamped and
obstacle nodes follow their known motion (the trajectory's positions, moving obstacles
included, or rest), and the model sees the velocity of their coming step. On Eulerian
data (:mod:`bsms.fields`) the state is the node fields on the fixed mesh: each output field
is advanced by its predicted change or replaced by its predicted value, and the fields of
prescribed nodes (inflow, walls, airfoil) come from the data.

Metrics (:func:`rollout_metrics`; per Eulerian field :func:`field_metrics`) use the free body
nodes: the error of a step is the RMSE over those nodes of the position error vector,
sqrt(mean_i |x_i - x_i^true|^2) (m);
``rmse_1`` / ``rmse_50`` are the errors at steps 1 and 50, ``rmse_all`` the RMSE over all
steps and nodes. Relative values divide by the body size (the diagonal of the rest body's
bounding box). A rollout is unstable from the first step whose error exceeds
``bound`` x body size, or whose state is not finite.
"""

from __future__ import annotations

import math
import resource
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from bsms.data import Scenario
from bsms.level_graph import level_graph
from bsms.models.blocks import compiled_message_passing
from bsms.models.precision import network_dtype
from bsms.rollouts.memory import keep_freed_memory
from bsms.rollouts.motion import SKILL_KEYS
from bsms.rollouts.stride import strided_rollouts

__all__ = [
    "Rollout", "rollout", "rollouts", "eulerian_metrics", "rollout_metrics", "field_metrics", "summarize", "body_size",
    "peak_memory_mb", "DEFAULT_BOUND", "integrate",
]

DEFAULT_BOUND = 0.5  # relative error (of the body size) at which a rollout counts as unstable
# Independent frames (graph.from_rest) joined into one CPU call: up to this many graph nodes. Past
# it the activations leave the caches and a frame costs more: 2 press test trajectories (~1,300
# nodes each, latent 32, one thread) took 63 ms per frame at 40 frames per call, 30 ms at 4.
CPU_NODES_PER_CALL = 12_000
# ... unless every message pass is summed by the compiled loop (no per-edge activations): then a
# bigger call only spreads the per-call costs. pretrained/press2d through bsms.infer, three shapes
# of ~1,900 nodes: 9.2-10.3 ms per frame at 12,000 nodes per call, 7.1-7.5 at 48,000; its 8 test
# trajectories at once: the same at both.
CPU_NODES_PER_CALL_COMPILED = 48_000


def peak_memory_mb(device: torch.device | str = "cpu") -> float:
    """Peak memory so far: CUDA allocations on a GPU, the process's peak resident set on CPU."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10


@dataclass
class Rollout:
    """positions, velocities: (T, N, d) of all scenario nodes, frame 0 included; step_seconds:
    wall time of each model step (graph building, contacts and the network; (T-1,)), for a
    rollout of a batch its share of the batch's step (the step's time over the rollouts in it);
    finite: whether the whole rollout stayed finite (it stops at the first non-finite step);
    graph_nodes: (T-1, L) node count of each level of each step's graph (body and obstacle nodes
    in reach); states: (T, N, k) Eulerian node fields (:mod:`bsms.fields`), None for Lagrangian data."""

    positions: np.ndarray
    velocities: np.ndarray
    step_seconds: np.ndarray
    finite: bool = True
    extra: dict = field(default_factory=dict)
    graph_nodes: np.ndarray = field(default_factory=lambda: np.zeros((0, 1), np.int64))
    states: np.ndarray | None = None

    @property
    def seconds_per_step(self) -> float:
        return float(np.mean(self.step_seconds)) if len(self.step_seconds) else float("nan")


def integrate(position, velocity, change, dt: float):
    """The learned step of free nodes: (x + dt v', v') with v' = v + dv, for numpy arrays or torch
    tensors (multi-step training, :mod:`bsms.training.unroll`, integrates its own predictions with it)."""
    velocity = velocity + change
    return position + dt * velocity, velocity


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@dataclass
class _Track:
    """One rollout of a batch while it runs: its scenario, state per frame and what it measured."""

    scenario: Scenario
    positions: np.ndarray
    velocities: np.ndarray
    known: np.ndarray | None
    steps: int
    seconds: list = field(default_factory=list)
    graph_nodes: list = field(default_factory=list)
    finite: bool = True
    spec: object = None
    states: np.ndarray | None = None
    known_states: np.ndarray | None = None

    def running(self, t: int) -> bool:
        return self.finite and t < self.steps

    def frame(self, t: int):
        """The graph arrays of frame t (Eulerian: the spec's input fields on the fixed mesh).
        Lagrangian: kinematic nodes get the velocity of their coming step, as in training
        (:func:`~bsms.data.frame_velocities`): (known x_{t+1} - x_t) / dt, 0 without known positions."""
        if self.states is not None:
            fields = self.spec.input_values(self.states[t])
            return self.scenario.frame(self.positions[t], self.velocities[t], fields=fields)
        return self.scenario.frame(*self.state(t))

    def frames(self, ts: list[int]) -> list:
        """:meth:`frame` of each of ``ts``; a Lagrangian track's in one call of
        :meth:`Scenario.frames` (the elastic answers of all of them in one solve)."""
        if self.states is not None:
            return [self.frame(t) for t in ts]
        return self.scenario.frames([self.state(t) for t in ts])

    def state(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(positions, velocities) frame t's graph is built from (Lagrangian, see :meth:`frame`)."""
        velocity, kinematic = self._base(t), self.scenario.kinematic
        if kinematic.any():
            velocity = velocity.copy()
            velocity[kinematic] = 0.0 if self.known is None else \
                (self.known[t + 1][kinematic] - self.positions[t][kinematic]) / self.scenario.frame_dt
        return self._origin(t), velocity

    def _origin(self, t: int) -> np.ndarray:
        """Where frame t's graph puts the nodes and its step starts from: frame t, or the rest
        shape on free nodes of a model that predicts from rest (``graph.from_rest``)."""
        if not self.scenario.options.from_rest:
            return self.positions[t]
        return np.where(self.scenario.kinematic[:, None], self.positions[t], self.scenario.rest_pos)

    def _base(self, t: int) -> np.ndarray:
        """The velocities frame t's step starts from: the state's, or 0 on free nodes of a
        quasi-static model (``graph.quasi_static``: the output is their whole velocity) or of
        one that predicts from rest (``graph.from_rest``)."""
        options = self.scenario.options
        if not (options.quasi_static or options.from_rest):
            return self.velocities[t]
        return np.where(self.scenario.kinematic[:, None], self.velocities[t], 0.0)

    def advance(self, t: int, change: np.ndarray) -> None:
        """Frame t + 1 from frame t and the model's output (N, node_out) of every scenario node:
        the velocity change (Lagrangian) or the spec's outputs (Eulerian)."""
        if self.states is not None:
            self._advance_fields(t, change)
            return
        kinematic, dt = self.scenario.kinematic, self.scenario.frame_dt
        position, velocity = integrate(self._origin(t), self._base(t), change, dt)
        if self.scenario.options.from_rest:  # the output was the displacement from rest: the frame's velocity
            velocity = (position - self.positions[t]) / dt
        if self.known is not None:
            position[kinematic] = self.known[t + 1][kinematic]
            velocity[kinematic] = (self.known[t + 1][kinematic] - self.positions[t][kinematic]) / dt
        else:
            position[kinematic], velocity[kinematic] = self.positions[t][kinematic], 0.0
        self.positions[t + 1], self.velocities[t + 1] = position, velocity
        if not (np.isfinite(position).all() and np.isfinite(velocity).all()):
            self.finite = False
            self.steps = t + 1

    def _advance_fields(self, t: int, output: np.ndarray) -> None:
        state = self.spec.advance(self.states[t], output)
        kinematic = self.scenario.kinematic
        state[kinematic] = (self.states[t] if self.known_states is None else self.known_states[t + 1])[kinematic]
        self.states[t + 1] = state
        self.positions[t + 1], self.velocities[t + 1] = self.positions[t], self.velocities[t]
        if not np.isfinite(state).all():
            self.finite = False
            self.steps = t + 1

    def result(self) -> Rollout:
        n = self.steps + 1
        levels = self.scenario.levels.n_levels
        return Rollout(self.positions[:n], self.velocities[:n], np.asarray(self.seconds), self.finite,
                       graph_nodes=np.array(self.graph_nodes, np.int64).reshape(len(self.graph_nodes), levels),
                       states=None if self.states is None else self.states[:n])


def _track(scenario: Scenario, x0: np.ndarray, v0: np.ndarray, steps: int, known, spec=None, s0=None,
           known_states=None) -> _Track:
    for name, series in (("known_positions", known), ("known_states", known_states)):
        if series is not None and len(series) < steps + 1:
            raise ValueError(f"{name} has {len(series)} frames; a rollout of {steps} steps needs {steps + 1}")
    positions = np.empty((steps + 1, *np.shape(x0)))
    velocities = np.empty_like(positions)
    positions[0], velocities[0] = x0, v0
    states = None
    if s0 is not None:
        states = np.empty((steps + 1, *np.shape(s0)))
        states[0] = s0
    return _Track(scenario, positions, velocities, known, int(steps), spec=spec, states=states,
                  known_states=known_states)


def _frames(jobs: list[tuple[_Track, int]]) -> list:
    """The graph arrays of each job's frame, in order, each track's frames built together
    (:meth:`_Track.frames`)."""
    out, by_track = [None] * len(jobs), {}
    for i, (track, _) in enumerate(jobs):
        by_track.setdefault(id(track), []).append(i)
    for indices in by_track.values():
        track = jobs[indices[0]][0]
        for i, frame in zip(indices, track.frames([jobs[i][1] for i in indices]), strict=True):
            out[i] = frame
    return out


def _changes(model, jobs: list[tuple[_Track, int]], device: torch.device, precision: str) -> list[np.ndarray]:
    """One model call on the graphs of ``jobs`` ((track, frame) pairs) as one batch -> per job the
    (N_k, d) velocity changes of every scenario node (zero on nodes outside the frame's graph)."""
    frames = _frames(jobs)
    change = model.velocity_change(level_graph(frames).to(device), precision=precision).double().cpu().numpy()
    out, start = [], 0
    for (k, t), frame in zip(jobs, frames, strict=True):
        full = np.zeros((len(k.positions[t]), change.shape[1]))
        full[frame.nodes["scenario_nodes"]] = change[start: start + frame.n_nodes]
        start += frame.n_nodes
        k.graph_nodes.append([len(level.nodes) for level in frame.levels])
        out.append(full)
    return out


def _step(model, jobs: list[tuple[_Track, int]], device: torch.device, precision: str) -> None:
    """One model call on ``jobs`` (:func:`_changes`), each job's frame then advanced in order and
    timed at its share of the call; a track that went non-finite at an earlier frame of the same
    call stops there."""
    start = time.perf_counter()
    changes = _changes(model, jobs, device, precision)
    _synchronize(device)
    share = (time.perf_counter() - start) / len(jobs)
    for (k, t), change in zip(jobs, changes, strict=True):
        if k.running(t):
            k.seconds.append(share)
            k.advance(t, change)


def _independent(tracks: list[_Track]) -> bool:
    """Whether every frame of these rollouts can be predicted at once: a model that predicts each
    frame from the rest shape and the drive (``graph.from_rest``), with the drive known ahead."""
    return all(k.states is None and k.scenario.options.from_rest and (k.known is not None or
                                                                     not k.scenario.kinematic.any())
               for k in tracks)


def _all_frames(model, tracks: list[_Track], device: torch.device, precision: str, frames_per_call: int,
                progress: bool) -> None:
    """The rollouts of independent frames (:func:`_independent`): up to ``frames_per_call`` frames
    of every track joined into one model call (:func:`_step`), on a CPU no more than fit
    :data:`CPU_NODES_PER_CALL` graph nodes (:data:`CPU_NODES_PER_CALL_COMPILED` for a model whose
    message passes are all compiled, :func:`~bsms.models.blocks.compiled_message_passing`; at
    least one frame)."""
    for k in tracks:  # the drive of every frame, before any is predicted
        if k.known is not None:
            k.positions[1:, k.scenario.kinematic] = k.known[1: k.steps + 1][:, k.scenario.kinematic]
        else:
            k.positions[1:, k.scenario.kinematic] = k.positions[0][k.scenario.kinematic]
    longest = max(k.steps for k in tracks)
    if device.type == "cpu":  # a call's tensors beyond the caches' size cost more per frame
        nodes = sum(len(k.positions[0]) for k in tracks)
        compiled = compiled_message_passing(model, network_dtype(precision, device, getattr(model, "latent", None)))
        budget = CPU_NODES_PER_CALL_COMPILED if compiled else CPU_NODES_PER_CALL
        frames_per_call = max(1, min(frames_per_call, budget // nodes))
    for t0 in tqdm(range(0, longest, frames_per_call), desc="rollout", unit="call", disable=not progress):
        jobs = [(k, t) for t in range(t0, min(t0 + frames_per_call, longest)) for k in tracks if k.running(t)]
        if not jobs:
            break
        _step(model, jobs, device, precision)


@torch.no_grad()
def rollouts(model, scenarios: list[Scenario], initial_positions: list, initial_velocities: list, steps,
             known_positions: list | None = None, device="cpu", progress: bool = False,
             warmup: int = 1, precision: str = "auto", initial_states: list | None = None,
             known_states: list | None = None, frames_per_call: int = 1) -> list[Rollout]:
    """Roll ``model`` out on several scenarios at once: every step is one model call on their
    graphs joined into one (:func:`~bsms.level_graph.level_graph`), and each rollout equals its
    rollout alone to float32 round-off. Arguments as :func:`rollout`, one per scenario
    (``steps``: an int or one per scenario; ``known_positions``: None, or one array or None per
    scenario). A rollout that ends (its steps, or a non-finite state) leaves the batch; the
    others go on. Each rollout's ``step_seconds`` are its share of the batch's steps.

    frames_per_call: for a model whose frames do not depend on each other (``graph.from_rest``,
    with the drive known: ``known_positions`` or no kinematic nodes), this many frames of every
    scenario go into one model call (a whole known drive predicted in a few calls); each
    frame's time is its share of its call. Other models step one frame per call whatever it says.

    A model of Eulerian data (``model.spec``, :mod:`bsms.fields`) needs ``initial_states``: one
    (N, k) state of the spec's fields per scenario; ``known_states``: None, or one (>= steps + 1,
    N, k) array (or None) per scenario whose rows of prescribed nodes give their fields.
    """
    n = len(scenarios)
    steps = [steps] * n if np.ndim(steps) == 0 else list(steps)
    known_positions = [None] * n if known_positions is None else list(known_positions)
    if not n or not len(initial_positions) == len(initial_velocities) == len(steps) == len(known_positions) == n:
        raise ValueError(f"give one initial state, step count and known_positions (or None) per scenario; got "
                         f"{n} scenarios, {len(initial_positions)} initial positions, {len(initial_velocities)} "
                         f"initial velocities, {len(steps)} step counts, {len(known_positions)} known_positions")
    options = {"device": device, "progress": progress, "warmup": warmup, "precision": precision,
               "initial_states": initial_states, "known_states": known_states, "frames_per_call": frames_per_call}
    stride = int(getattr(model, "frame_stride", 1))
    if stride > 1:  # a step of k frames (train.frame_stride): run at k dt, every frame given back
        return strided_rollouts(_rolled, model, scenarios, initial_positions, initial_velocities, steps,
                                known_positions, stride, **options)
    return _rolled(model, scenarios, initial_positions, initial_velocities, steps, known_positions, **options)


def _rolled(model, scenarios, initial_positions, initial_velocities, steps: list, known_positions: list,
            device, progress: bool, warmup: int, precision: str, initial_states, known_states,
            frames_per_call: int) -> list[Rollout]:
    """:func:`rollouts` of one model step per row of its scenarios (its arguments checked)."""
    device = torch.device(device)
    network_dtype(precision, device)  # a bad precision fails before any work
    keep_freed_memory()  # each call's arrays reused, not paged in anew (bsms.rollouts.memory)
    model = model.to(device).eval()
    n = len(scenarios)
    spec = getattr(model, "spec", None)
    eulerian = spec is not None and not spec.is_lagrangian
    if eulerian and (initial_states is None or len(initial_states) != n):
        raise ValueError(f"the model learned Eulerian fields ({spec.describe()}); give one initial state per scenario")
    initial_states = list(initial_states) if eulerian else [None] * n
    known_states = [None] * n if known_states is None else list(known_states)
    tracks = [_track(*args, spec, s0, ks) for *args, s0, ks in zip(
        scenarios, initial_positions, initial_velocities, steps, known_positions, initial_states, known_states,
        strict=True)]
    if frames_per_call < 1:
        raise ValueError(f"frames_per_call must be >= 1, got {frames_per_call}")
    for _ in range(warmup):
        _changes(model, [(k, 0) for k in tracks], device, precision)
        for k in tracks:
            k.graph_nodes.clear()
    if frames_per_call > 1 and _independent(tracks):
        _all_frames(model, tracks, device, precision, frames_per_call, progress)
        return [k.result() for k in tracks]
    for t in tqdm(range(max(steps)), desc="rollout", unit="step", disable=not progress):
        running = [k for k in tracks if k.running(t)]
        if not running:
            break
        _step(model, [(k, t) for k in running], device, precision)
    return [k.result() for k in tracks]


def rollout(model, scenario: Scenario, initial_positions: np.ndarray, initial_velocity: np.ndarray, steps: int,
            known_positions: np.ndarray | None = None, device="cpu", progress: bool = False,
            warmup: int = 1, precision: str = "auto", initial_state: np.ndarray | None = None,
            known_state: np.ndarray | None = None, frames_per_call: int = 1) -> Rollout:
    """Roll ``model`` out for ``steps`` steps from frame 0.

    initial_positions, initial_velocity: (N, d) of all scenario nodes at frame 0.
    known_positions: (>= steps + 1, N, d) positions whose kinematic (clamped, obstacle) rows
        prescribe those nodes' motion; None keeps kinematic nodes where they start.
    warmup: untimed model calls on the first state before the timed steps (one-off start-up
        costs such as allocator growth and kernel selection are not per-step costs).
    precision: the core network's number format, ``auto`` (bfloat16 where the hardware has
        it), ``bf16`` or ``f32`` (:mod:`bsms.models.precision`).
    initial_state, known_state: Eulerian data: the (N, k) state of frame 0 and the (>= steps + 1,
        N, k) states whose rows of prescribed nodes give their fields (:func:`rollouts`).
    frames_per_call: frames predicted in one model call where they do not depend on each other
        (``graph.from_rest`` with the drive known; :func:`rollouts`).
    """
    return rollouts(model, [scenario], [initial_positions], [initial_velocity], [steps], [known_positions],
                    device=device, progress=progress, warmup=warmup, precision=precision,
                    initial_states=None if initial_state is None else [initial_state], known_states=[known_state],
                    frames_per_call=frames_per_call)[0]


def body_size(rest_positions: np.ndarray) -> float:
    """Diagonal of the bounding box of the rest body (the length errors are relative to)."""
    return float(np.linalg.norm(rest_positions.max(axis=0) - rest_positions.min(axis=0)))


def rollout_metrics(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray, size: float,
                    bound: float = DEFAULT_BOUND) -> dict:
    """Errors of one rollout. predicted: (T_p, N, d), truth: (T, N, d) with T >= T_p, both from
    frame 0; mask: (N,) nodes that count (free body nodes); size: body size (m).

    -> error_curve (T-1,) per-step RMSE (m; inf after a non-finite step), rmse_1, rmse_50,
    rmse_all (m; nan where the rollout is shorter), the same relative to ``size``
    (``rel_*``), and ``unstable_step`` (first step, from 1, beyond ``bound`` x size or not
    finite; None when stable).
    """
    steps = truth.shape[0] - 1
    curve = np.full(steps, np.inf)
    reached = min(predicted.shape[0], truth.shape[0]) - 1
    error = predicted[1: reached + 1][:, mask] - truth[1: reached + 1][:, mask]
    with np.errstate(invalid="ignore", over="ignore"):
        curve[:reached] = np.sqrt(np.mean(np.sum(error**2, axis=-1), axis=-1))
    curve[~np.isfinite(curve)] = np.inf
    bad = np.flatnonzero(~(curve <= bound * size))
    with np.errstate(invalid="ignore", over="ignore"):
        rmse_all = float(np.sqrt(np.mean(curve**2))) if steps else float("nan")
    out = {
        "error_curve": curve, "rmse_1": float(curve[0]) if steps >= 1 else float("nan"),
        "rmse_50": float(curve[49]) if steps >= 50 else float("nan"), "rmse_all": rmse_all,
        "unstable_step": int(bad[0]) + 1 if len(bad) else None, "steps": steps, "body_size": size,
    }
    for key in ("rmse_1", "rmse_50", "rmse_all"):
        out[f"rel_{key[5:]}"] = out[key] / size
    return out


def field_metrics(spec, predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray,
                  bound: float = DEFAULT_BOUND) -> dict:
    """Errors of an Eulerian rollout per field of ``spec`` (:mod:`bsms.fields`): predicted
    (T_p, N, k) and truth (T, N, k) states -> {field: :func:`rollout_metrics`}, each relative
    to (and unstable beyond ``bound`` times) the field's scale, the RMS over the free nodes and
    frames of the true field's magnitude."""
    out = {}
    for f in spec.state_fields:
        cols = spec.columns(f.name)
        scale = float(np.sqrt(np.mean(np.sum(truth[:, mask, cols] ** 2, axis=-1)))) if mask.any() else 0.0
        out[f.name] = rollout_metrics(predicted[..., cols], truth[..., cols], mask, scale or 1.0, bound)
        out[f.name]["scale"] = out[f.name].pop("body_size")
    return out


def eulerian_metrics(spec, predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray,
                     bound: float = DEFAULT_BOUND) -> dict:
    """An Eulerian rollout's metrics: its first output field's :func:`field_metrics` (every
    field's under ``fields``) beside persistence, the trivial answer of a fixed mesh -- the first
    frame held for ever: ``rest_rel_all`` its relative RMSE over all steps and ``vs_rest`` the
    rollout's over it (the at-rest yardstick of Lagrangian data)."""
    name = spec.outputs[0].name
    fields = field_metrics(spec, predicted, truth, mask, bound)
    persisting = field_metrics(spec, np.repeat(truth[:1], len(truth), axis=0), truth, mask, bound)[name]
    main = fields[name]
    rest = persisting["rel_all"]
    return {**main, "body_size": main["scale"], "field": name, "fields": fields, "rest_rel_all": rest,
            "vs_rest": main["rel_all"] / rest if rest > 0 else math.inf}


def summarize(metrics: list[dict]) -> dict:
    """Mean and std over trajectories of each scalar metric; count of unstable rollouts; for
    Eulerian rollouts the same per field (``fields``)."""
    out = {"trajectories": len(metrics), "unstable": sum(m["unstable_step"] is not None for m in metrics)}
    for key in ("rmse_1", "rmse_50", "rmse_all", "rel_1", "rel_50", "rel_all", "seconds_per_step",
                "seconds_per_sim_second", "throughput_seconds_per_sim_second", "seconds", "setup_s", "learned_s",
                "latency_ms", "solver_s", "preroll_s", "graph_nodes_ratio", "scale", *SKILL_KEYS):
        values = np.array([m[key] for m in metrics if key in m], dtype=float)
        if len(values):
            out[key] = float(np.mean(values))
            out[f"{key}_std"] = float(np.std(values))
    steps = [m["unstable_step"] for m in metrics if m["unstable_step"] is not None]
    out["first_unstable_step"] = min(steps) if steps else None
    if metrics and "fields" in metrics[0]:
        out["field"] = metrics[0].get("field")
        out["fields"] = {name: summarize([m["fields"][name] for m in metrics]) for name in metrics[0]["fields"]}
    return out
