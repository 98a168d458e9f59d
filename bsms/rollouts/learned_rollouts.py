"""Learned rollouts on stored trajectories, scored against them: what ``bsms.evaluate`` reports
per trajectory and what training validates on when ``train.validation`` is ``rollout``.

Speed is measured three ways (:func:`end_to_end`), the first the headline:

- end to end (``seconds``, ``setup_s`` + ``learned_s``): a user's wall time for a new mesh, from
  the mesh and scene to the last frame -- the scenario built with no cache (hierarchy,
  factorisations, outlines, graph building) and the mesh rolled out alone as ``bsms.infer``
  rolls it out (a from-rest model with a known drive predicts many frames per call);
- latency (``latency_ms``): one frame per call, each from the last, as a controller or an
  interactive user calls it;
- throughput (``seconds_per_step`` of :func:`learned_rollouts`): many meshes in one batch,
  frames batched, the per-mesh setup amortised (not counted).

:func:`physics_rollouts` scores the physics-only input of a model -- the linear-elastic contact
answer of ``graph.elastic`` alone, every frame the rest shape plus that answer -- timed end to end
the same way: the trivial answer that input gives for free.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from bsms.data import GraphOptions, Scenario
from bsms.fields import eulerian_state, initial_velocity, world_positions
from bsms.rollouts.motion import skill
from bsms.rollouts.rollout import DEFAULT_BOUND, body_size, eulerian_metrics, rollout_metrics, rollouts
from bsms.rollouts.solver_runs import free_nodes

__all__ = ["learned_rollouts", "end_to_end", "physics_rollouts", "PHYSICS_LABEL"]

PHYSICS_LABEL = "physics only: linear-elastic contact answer (graph.elastic)"


def learned_rollouts(model, graph: GraphOptions, trajectories, cache_dir, frames: list[int],
                     bound: float = DEFAULT_BOUND, device="cpu", scenarios=None) -> list[tuple[dict, object]]:
    """(metrics, :class:`~bsms.rollouts.rollout.Rollout`) of ``model`` on each of ``trajectories``, rolled
    out from frame 0 for ``frames`` steps each as one batch; graphs built by ``graph``, their
    hierarchies cached in ``cache_dir``. Metrics: :func:`~bsms.rollouts.rollout.rollout_metrics` (with
    ``bound``, the relative error that marks a rollout unstable) and the skill measures of
    :func:`bsms.rollouts.motion.skill` (``rest_rel_all``, ``vs_rest``, rigid and deformation parts) for
    Lagrangian data, :func:`~bsms.rollouts.rollout.eulerian_metrics` for Eulerian data; timing in
    both. ``scenarios``: the trajectories' scenarios if already built with ``graph`` (e.g. a
    dataset's), else built here."""
    spec = model.spec
    if scenarios is None:
        scenarios = [Scenario.from_trajectory(t, graph, cache_dir, spec=spec) for t in trajectories]
    truths = _truths(spec, trajectories, frames)
    results = _roll(model, scenarios, trajectories, truths, frames, device, max(frames))
    out = []
    for scenario, trajectory, n, result, truth in zip(scenarios, trajectories, frames, results, truths, strict=True):
        if spec.is_lagrangian:
            metrics = _scored(result.positions[:, : scenario.n_body], truth[: n + 1], trajectory, bound)
        else:
            metrics = eulerian_metrics(spec, result.states, truth, free_nodes(trajectory), bound)
        metrics["seconds_per_step"] = result.seconds_per_step
        metrics["seconds_per_sim_second"] = result.seconds_per_step / scenario.frame_dt
        metrics["graph_nodes_ratio"] = float(np.mean(result.graph_nodes[:, 0])) / scenario.n_body
        out.append((metrics, result))
    return out


def _scored(predicted: np.ndarray, truth: np.ndarray, trajectory, bound: float) -> dict:
    """A Lagrangian rollout's errors on the trajectory's free body nodes and its skill against rest."""
    free, size = free_nodes(trajectory), body_size(trajectory.mesh.nodes)
    metrics = rollout_metrics(predicted, truth, free, size, bound)
    metrics.update(skill(predicted, truth, free, size, metrics["rel_all"]))
    return metrics


def _truths(spec, trajectories, frames: list[int]) -> list[np.ndarray]:
    """Per trajectory the stored frames a rollout is scored on (and whose kinematic rows drive it)."""
    if spec.is_lagrangian:
        return [world_positions(spec, t) for t in trajectories]
    return [eulerian_state(spec, t)[: n + 1] for t, n in zip(trajectories, frames, strict=True)]


def _roll(model, scenarios, trajectories, truths, frames: list[int], device, frames_per_call: int, warmup: int = 1):
    """:func:`~bsms.rollouts.rollout.rollouts` of ``model`` from frame 0 of each trajectory, driven by its
    stored kinematic motion, ``frames_per_call`` frames per call where they are independent."""
    spec = model.spec
    if spec.is_lagrangian:
        known = [s.positions(w[: n + 1], None if t.obstacle_positions is None else t.obstacle_positions[: n + 1])
                 for s, w, n, t in zip(scenarios, truths, frames, trajectories, strict=True)]
        initial = [s.full(initial_velocity(spec, t, w)[None], 0.0)[0]
                   for s, t, w in zip(scenarios, trajectories, truths, strict=True)]
        return rollouts(model, scenarios, [k[0] for k in known], initial, frames, known, device=device,
                        frames_per_call=frames_per_call, warmup=warmup)
    return rollouts(model, scenarios, [s.rest_pos for s in scenarios], [np.zeros_like(s.rest_pos) for s in scenarios],
                    frames, device=device, initial_states=[truth[0] for truth in truths], known_states=truths,
                    warmup=warmup)


def _independent_frames(model, graph: GraphOptions) -> bool:
    """Whether the model predicts each frame without the one before (``graph.from_rest``)."""
    return bool(model.spec.is_lagrangian and graph.from_rest)


def end_to_end(model, graph: GraphOptions, trajectory, frames: int, device="cpu") -> dict:
    """A user's wall time for ``trajectory``'s mesh as a new one (module docstring): ``setup_s``
    (the scenario from the trajectory with no cache: hierarchy, factorisations, outlines),
    ``learned_s`` (the mesh rolled out alone from frame 0, as ``bsms.infer`` does, no untimed
    warm-up), ``seconds`` (their sum) and ``latency_ms`` (one frame per call, each from the last:
    the mean step after a warm-up call)."""
    spec = model.spec
    truths = _truths(spec, [trajectory], [frames])
    start = time.perf_counter()
    scenario = Scenario.from_trajectory(trajectory, graph, None, spec=spec)
    setup = time.perf_counter() - start
    start = time.perf_counter()
    alone = _roll(model, [scenario], [trajectory], truths, [frames], device, frames, warmup=0)[0]
    learned = time.perf_counter() - start
    latency = alone
    if frames > 1 and _independent_frames(model, graph):
        latency = _roll(model, [scenario], [trajectory], truths, [frames], device, 1)[0]
    return {"setup_s": setup, "learned_s": learned, "seconds": setup + learned,
            "latency_ms": 1e3 * latency.seconds_per_step}


def physics_rollouts(graph: GraphOptions, trajectories, frames: list[int], bound: float = DEFAULT_BOUND) -> list[dict]:
    """The physics-only input of a model with ``graph.elastic`` as a method of its own: frame t + 1
    is the rest shape plus the linear-elastic contact answer the model is given at frame t (its
    penetration input, its hold, its load), on every trajectory, scored and timed end to end like
    a learned model (:func:`end_to_end`: the scenario built with no cache, then every frame's
    answer in one solve; ``latency_ms``: one frame per solve). [] where ``graph`` has no elastic input."""
    if not graph.elastic:
        return []
    options = dataclasses.replace(graph, levels=1, from_rest=True, clearance=False)  # what the answer needs
    out = []
    for trajectory, n in zip(trajectories, frames, strict=True):
        truth = trajectory.positions[: n + 1]
        start = time.perf_counter()
        scenario = Scenario.from_trajectory(trajectory, options, None)
        setup = time.perf_counter() - start
        start = time.perf_counter()
        states = _physics_states(scenario, trajectory, n)
        predicted = _physics_answers(scenario, states)
        learned = time.perf_counter() - start
        start = time.perf_counter()
        for state in states:
            _physics_answers(scenario, [state])
        per_frame = (time.perf_counter() - start) / max(1, n)
        metrics = _scored(np.concatenate([truth[:1], predicted]), truth, trajectory, bound)
        metrics.update(setup_s=setup, learned_s=learned, seconds=setup + learned, latency_ms=1e3 * per_frame,
                       seconds_per_step=learned / max(1, n),
                       seconds_per_sim_second=(setup + learned) / (n * scenario.frame_dt))
        out.append(metrics)
    return out


def _physics_states(scenario: Scenario, trajectory, frames: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (positions, velocities) of every scenario node the answer to frames 1..``frames`` starts
    from, as a from-rest model's rollout builds them: the body at rest (clamped nodes as stored),
    the obstacles where they are, kinematic nodes moving to their next stored place."""
    n_body = scenario.n_body
    rest = scenario.rest_pos[:n_body]
    obstacles = trajectory.obstacle_positions
    body = np.where(scenario.kinematic[:n_body, None], trajectory.positions[: frames + 1], rest)
    pos = scenario.positions(body, None if obstacles is None else obstacles[: frames + 1])
    velocity = np.where(scenario.kinematic[:, None], (pos[1:] - pos[:-1]) / scenario.frame_dt, 0.0)
    return list(zip(pos[:-1], velocity, strict=True))


def _physics_answers(scenario: Scenario, states) -> np.ndarray:
    """(T, N_body, d) the rest shape plus the elastic answer of each state (one solve for all),
    the kinematic body nodes where their step takes them."""
    answers = np.stack(scenario.elastic_answers(states)[1])[:, : scenario.n_body]
    n_body = scenario.n_body
    moved = np.stack([pos[:n_body] + scenario.frame_dt * velocity[:n_body] for pos, velocity in states])
    free = ~scenario.kinematic[:n_body, None]
    return np.where(free, scenario.rest_pos[:n_body] + answers, moved)

