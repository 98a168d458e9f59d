"""Learned rollouts on stored trajectories, scored against them: what ``bsms.evaluate`` reports
per trajectory and what training validates on when ``train.validation`` is ``rollout``."""

from __future__ import annotations

import numpy as np

from bsms.data import GraphOptions, Scenario
from bsms.fields import eulerian_state, initial_velocity, world_positions
from bsms.motion import skill
from bsms.rollout import DEFAULT_BOUND, body_size, eulerian_metrics, rollout_metrics, rollouts
from bsms.solver_runs import free_nodes

__all__ = ["learned_rollouts"]


def learned_rollouts(model, graph: GraphOptions, trajectories, cache_dir, frames: list[int],
                     bound: float = DEFAULT_BOUND, device="cpu", scenarios=None) -> list[tuple[dict, object]]:
    """(metrics, :class:`~bsms.rollout.Rollout`) of ``model`` on each of ``trajectories``, rolled
    out from frame 0 for ``frames`` steps each as one batch; graphs built by ``graph``, their
    hierarchies cached in ``cache_dir``. Metrics: :func:`~bsms.rollout.rollout_metrics` (with
    ``bound``, the relative error that marks a rollout unstable) and the skill measures of
    :func:`bsms.motion.skill` (``rest_rel_all``, ``vs_rest``, rigid and deformation parts) for
    Lagrangian data, :func:`~bsms.rollout.eulerian_metrics` for Eulerian data; timing in both. ``scenarios``: the
    trajectories' scenarios if already built with ``graph`` (e.g. a dataset's), else built here."""
    spec = model.spec
    if scenarios is None:
        scenarios = [Scenario.from_trajectory(t, graph, cache_dir, spec=spec) for t in trajectories]
    if spec.is_lagrangian:
        truths = [world_positions(spec, t) for t in trajectories]
        known = [s.positions(w[: n + 1], None if t.obstacle_positions is None else t.obstacle_positions[: n + 1])
                 for s, w, n, t in zip(scenarios, truths, frames, trajectories, strict=True)]
        initial = [s.full(initial_velocity(spec, t, w)[None], 0.0)[0]
                   for s, t, w in zip(scenarios, trajectories, truths, strict=True)]
        results = rollouts(model, scenarios, [k[0] for k in known], initial, frames, known, device=device,
                           frames_per_call=max(frames))  # independent frames (graph.from_rest): all at once
    else:
        truths = [eulerian_state(spec, t)[: n + 1] for t, n in zip(trajectories, frames, strict=True)]
        results = rollouts(model, scenarios, [s.rest_pos for s in scenarios],
                           [np.zeros_like(s.rest_pos) for s in scenarios], frames, device=device,
                           initial_states=[truth[0] for truth in truths], known_states=truths)
    out = []
    for scenario, trajectory, n, result, truth in zip(scenarios, trajectories, frames, results, truths, strict=True):
        if spec.is_lagrangian:
            free, size = free_nodes(trajectory), body_size(trajectory.mesh.nodes)
            predicted = result.positions[:, : scenario.n_body]
            metrics = rollout_metrics(predicted, truth[: n + 1], free, size, bound)
            metrics.update(skill(predicted, truth[: n + 1], free, size, metrics["rel_all"]))
        else:
            metrics = eulerian_metrics(spec, result.states, truth, free_nodes(trajectory), bound)
        metrics["seconds_per_step"] = result.seconds_per_step
        metrics["seconds_per_sim_second"] = result.seconds_per_step / scenario.frame_dt
        metrics["graph_nodes_ratio"] = float(np.mean(result.graph_nodes[:, 0])) / scenario.n_body
        out.append((metrics, result))
    return out

