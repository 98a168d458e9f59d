"""The MPM solver run again on a stored trajectory: at the data's own settings and cheaper ones.

``ground_truth`` re-runs the trajectory's generating config unchanged: it must reproduce the
stored trajectory, and its wall time is what a learned model's speed-up is measured against.
The cheaper settings -- a coarser background mesh, fewer particles (a coarser body mesh,
compared at the ground truth's nodes by interpolating its displacement), a larger time step
-- are the honest baseline a surrogate must beat on the speed-accuracy chart.
"""

from __future__ import annotations

import copy
import math
import time

import numpy as np
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

from bsms.data import NodeType
from bsms.rollout import body_size, rollout_metrics
from datagen import simulate
from datagen.mpm import SimulationError
from datagen.simulation import SOLVER_DEFAULTS

__all__ = ["SOLVER_SETTINGS", "setting_config", "interpolate_to", "run_solver", "frame_dt", "free_nodes"]

# name -> label (how the trajectory's generating config changes: setting_config)
SOLVER_SETTINGS = {
    "ground_truth": "solver, data settings (ground truth)",
    "coarse_mesh": "solver, background mesh 2x coarser",
    "fewer_particles": "solver, body mesh 1.5x coarser",
    "large_step": "solver, time step 2x larger",
}


def setting_config(base: dict, setting: str, frames: int) -> dict | None:
    """The generating config ``base`` changed for ``setting`` (None when the scene lacks the knob)."""
    config = copy.deepcopy(base)
    config["output"] = {**config.get("output", {}), "frames": frames, "step_diagnostics": False}
    params, solver = config.setdefault("params", {}), config.setdefault("solver", {})
    if setting == "coarse_mesh":
        if "mesh_size" not in params:
            return None
        params["mesh_size"] = 2.0 * params["mesh_size"]
    elif setting == "fewer_particles":
        if "body_size" not in params:
            return None
        params["body_size"] = 1.5 * params["body_size"]
    elif setting == "large_step":
        if solver.get("dt"):
            solver["dt"] = 2.0 * solver["dt"]
        else:
            solver["cfl"] = 2.0 * solver.get("cfl", SOLVER_DEFAULTS["cfl"])
    return config


def interpolate_to(truth_rest: np.ndarray, truth_body: np.ndarray, other_rest: np.ndarray,
                   other_body: np.ndarray, other_positions: np.ndarray) -> np.ndarray:
    """(T, N, d) positions of the ground truth's N rest nodes moved by another run's displacement.

    truth_rest (N, d) and truth_body (N,): the ground truth's rest nodes and their body ids;
    other_rest (M, d), other_body (M,), other_positions (T, M, d): the other run's. The field is
    piecewise linear on each body's rest nodes (the nearest node outside their hull).
    """
    displacement = other_positions - other_positions[:1]
    out = np.empty((len(other_positions), *truth_rest.shape))
    for body in np.unique(truth_body):
        mine, theirs = truth_body == body, other_body == body
        values = displacement[:, theirs].transpose(1, 0, 2).reshape(theirs.sum(), -1)
        moved = LinearNDInterpolator(other_rest[theirs], values)(truth_rest[mine])
        outside = ~np.isfinite(moved).all(axis=1)
        if outside.any():
            moved[outside] = NearestNDInterpolator(other_rest[theirs], values)(truth_rest[mine][outside])
        out[:, mine] = moved.reshape(mine.sum(), len(other_positions), -1).transpose(1, 0, 2)
    return out + truth_rest


def frame_dt(trajectory) -> float:
    """Time between the stored frames of a trajectory (s)."""
    return float(trajectory.times[1] - trajectory.times[0])


def free_nodes(trajectory) -> np.ndarray:
    """(N,) bool: the trajectory's free body nodes (the ones errors are measured on)."""
    n = trajectory.positions.shape[1]
    node_type = trajectory.node_type if trajectory.node_type is not None else np.zeros(n, int)
    return node_type == NodeType.FREE


def _failed(message: str, seconds: float, frames: int, trajectory) -> dict:
    return {"failed": message, "unstable_step": 1, "seconds_per_sim_second": seconds / (frames * frame_dt(trajectory)),
            "rmse_all": math.inf, "rmse_1": math.inf, "rmse_50": math.inf, "rel_all": math.inf,
            "error_curve": np.full(frames, np.inf)}


def run_solver(trajectory, setting: str, frames: int, bound: float) -> dict:
    """Metrics (:func:`bsms.rollout.rollout_metrics`) and timing of the solver at ``setting``
    over the first ``frames`` frames of ``trajectory``; {"skipped": why} without the knob."""
    config = setting_config(trajectory.config, setting, frames)
    if config is None:
        return {"skipped": f"the scene has no knob for {setting}"}
    start = time.perf_counter()
    try:
        other = simulate(config)
    except SimulationError as exc:
        return _failed(str(exc).splitlines()[0], time.perf_counter() - start, frames, trajectory)
    truth = trajectory.positions[: frames + 1]
    positions = other.positions
    if positions.shape[1:] != truth.shape[1:]:
        body = trajectory.body_id if trajectory.body_id is not None else np.zeros(len(truth[0]), int)
        other_body = other.body_id if other.body_id is not None else np.zeros(other.positions.shape[1], int)
        positions = interpolate_to(trajectory.mesh.nodes, body, other.mesh.nodes, other_body, positions)
    metrics = rollout_metrics(positions, truth, free_nodes(trajectory), body_size(trajectory.mesh.nodes), bound)
    metrics["seconds_per_sim_second"] = other.wall_time / (frames * frame_dt(trajectory))
    metrics["seconds_per_step"] = other.wall_time / frames
    if setting == "ground_truth":
        metrics["max_difference_from_stored"] = float(np.abs(other.positions - truth).max())
    return metrics
