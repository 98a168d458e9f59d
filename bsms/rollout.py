"""Autoregressive rollouts of a learned simulator, and their metrics against the solver.

A rollout starts from frame 0 (positions and the initial velocity) and applies the model
step after step: v_{t+1} = v_t + dv, x_{t+1} = x_t + dt v_{t+1} for free nodes; clamped and
obstacle nodes follow their known motion (the trajectory's positions, or rest).

Metrics (:func:`rollout_metrics`) use the free body nodes: the error of a step is the RMSE
over those nodes of the position error vector, sqrt(mean_i |x_i - x_i^true|^2) (m);
``rmse_1`` / ``rmse_50`` are the errors at steps 1 and 50, ``rmse_all`` the RMSE over all
steps and nodes. Relative values divide by the body size (the diagonal of the rest body's
bounding box). A rollout is unstable from the first step whose error exceeds
``bound`` x body size, or whose state is not finite.
"""

from __future__ import annotations

import resource
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from bsms.data import NodeType, Scenario

__all__ = ["Rollout", "rollout", "rollout_metrics", "summarize", "body_size", "peak_memory_mb", "DEFAULT_BOUND"]

DEFAULT_BOUND = 0.5  # relative error (of the body size) at which a rollout counts as unstable


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
    wall time of each model step (graph building, contacts and the network; (T-1,)); finite:
    whether the whole rollout stayed finite (it stops at the first non-finite step)."""

    positions: np.ndarray
    velocities: np.ndarray
    step_seconds: np.ndarray
    finite: bool = True
    extra: dict = field(default_factory=dict)

    @property
    def seconds_per_step(self) -> float:
        return float(np.mean(self.step_seconds)) if len(self.step_seconds) else float("nan")


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def rollout(model, scenario: Scenario, initial_positions: np.ndarray, initial_velocity: np.ndarray, steps: int,
            known_positions: np.ndarray | None = None, device="cpu", progress: bool = False,
            warmup: int = 1) -> Rollout:
    """Roll ``model`` out for ``steps`` steps from frame 0.

    initial_positions, initial_velocity: (N, d) of all scenario nodes at frame 0.
    known_positions: (>= steps + 1, N, d) positions whose kinematic (clamped, obstacle) rows
        prescribe those nodes' motion; None keeps kinematic nodes where they start.
    warmup: untimed model calls on the first state before the timed steps (one-off start-up
        costs such as allocator growth and kernel selection are not per-step costs).
    """
    device = torch.device(device)
    model = model.to(device).eval()
    kinematic = scenario.node_type != NodeType.FREE
    if known_positions is not None and len(known_positions) < steps + 1:
        raise ValueError(f"known_positions has {len(known_positions)} frames; a rollout of {steps} steps needs "
                         f"{steps + 1}")
    dt = scenario.frame_dt
    positions = np.empty((steps + 1, *initial_positions.shape))
    velocities = np.empty_like(positions)
    positions[0], velocities[0] = initial_positions, initial_velocity
    seconds = []
    finite = True
    for _ in range(warmup):
        model.velocity_change(scenario.graph(positions[0], velocities[0]).to(device))
    for t in tqdm(range(steps), desc="rollout", unit="step", disable=not progress):
        start = time.perf_counter()
        graph = scenario.graph(positions[t], velocities[t]).to(device)
        change = model.velocity_change(graph).double().cpu().numpy()
        _synchronize(device)
        seconds.append(time.perf_counter() - start)
        velocity = velocities[t] + change
        position = positions[t] + dt * velocity
        if known_positions is not None:
            position[kinematic] = known_positions[t + 1][kinematic]
            velocity[kinematic] = (known_positions[t + 1][kinematic] - positions[t][kinematic]) / dt
        else:
            position[kinematic], velocity[kinematic] = positions[t][kinematic], 0.0
        positions[t + 1], velocities[t + 1] = position, velocity
        if not (np.isfinite(position).all() and np.isfinite(velocity).all()):
            finite = False
            positions, velocities = positions[: t + 2], velocities[: t + 2]
            break
    return Rollout(positions, velocities, np.asarray(seconds), finite)


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


def summarize(metrics: list[dict]) -> dict:
    """Mean and std over trajectories of each scalar metric; count of unstable rollouts."""
    out = {"trajectories": len(metrics), "unstable": sum(m["unstable_step"] is not None for m in metrics)}
    for key in ("rmse_1", "rmse_50", "rmse_all", "rel_1", "rel_50", "rel_all", "seconds_per_step",
                "seconds_per_sim_second"):
        values = np.array([m[key] for m in metrics if key in m], dtype=float)
        if len(values):
            out[key] = float(np.mean(values))
            out[f"{key}_std"] = float(np.std(values))
    steps = [m["unstable_step"] for m in metrics if m["unstable_step"] is not None]
    out["first_unstable_step"] = min(steps) if steps else None
    return out
