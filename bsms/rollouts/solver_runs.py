"""The MPM solver run again on a stored trajectory: at the data's own settings and cheaper ones.

``ground_truth`` re-runs the trajectory's generating config unchanged: it must reproduce the
stored trajectory, and its wall time is what a learned model's speed-up is measured against.
The cheaper settings -- A-ULMPM's adaptive reference configuration (the fast solver a user
would run instead), a coarser background mesh, fewer particles (a coarser body mesh, compared
at the ground truth's nodes by interpolating its displacement), a larger time step up to the
largest one the solver survives, and, where the scene's drive is quasi-static (its module says
``QUASI_STATIC``), mass scaling as an engineer runs such a load explicitly (inertia x S, weight
and loads unchanged: density x S, gravity / S; the damping ratios kept: velocity decay rates /
sqrt(S), :data:`DAMPING_RATES`; the stable time step grows by sqrt(S)) -- are the honest baseline a
surrogate must beat on the speed-accuracy chart.

Every run is timed end to end (``solver_s``: from the config to the last frame, its setup
included, the settling pre-roll before frame 0 apart as ``preroll_s``), the footing of a learned
model's end-to-end speed-up (:mod:`bsms.rollouts.learned_rollouts`).
"""

from __future__ import annotations

import copy
import math
import re
import time

import numpy as np
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

from bsms.data import NodeType
from bsms.fields import eulerian_state, spec_of
from bsms.rollouts.memory import keep_freed_memory
from bsms.rollouts.motion import skill
from bsms.rollouts.rollout import body_size, eulerian_metrics, rollout_metrics
from datagen import simulate
from datagen.config import ConfigError
from datagen.mpm import SimulationError
from datagen.scenes import get_scene
from datagen.simulation import SOLVER_DEFAULTS

__all__ = ["SOLVER_SETTINGS", "STABILITY_FACTORS", "MASS_SCALING", "DAMPING_RATES", "setting_config", "setting_label",
           "is_setting", "mass_scaling_factor", "next_mass_scaling", "interpolate_to", "run_solver", "largest_stable",
           "stability_limit", "frame_dt", "free_nodes"]

# name -> label (how the trajectory's generating config changes: setting_config)
SOLVER_SETTINGS = {
    "ground_truth": "solver, data settings (ground truth)",
    "adaptive": "solver, adaptive reference (A-ULMPM)",
    "coarse_mesh_1.5": "solver, background mesh 1.5x coarser",
    "coarse_mesh": "solver, background mesh 2x coarser",
    "adaptive_coarse_mesh": "solver, adaptive reference, background mesh 2x coarser",
    "total": "solver, total reference (A-ULMPM, one kernel)",
    "fewer_particles": "solver, body mesh 1.5x coarser",
    "large_step": "solver, time step 2x larger",
    "stability_limit": "solver, largest stable time step",
    "mass_scaling_10": "solver, mass scaling x10",
    "mass_scaling_100": "solver, mass scaling x100",
    "mass_scaling_1000": "solver, mass scaling x1000",
    "mass_scaling_3000": "solver, mass scaling x3000",
}
# mass_scaling_S for any whole S >= 2 is a setting too (bsms.evaluate goes on past 3000 while the
# solver stays more accurate than the model: next_mass_scaling)
MASS_SCALING = re.compile(r"mass_scaling_([1-9][0-9]*)")
# the scene's velocity decay rates (mass-proportional damping, 1/s) that mass scaling divides by
# sqrt(S): the scaled body's frequencies are sqrt(S) lower, so the same damping ratio (the same
# fraction of critical) needs a sqrt(S) smaller rate. On three press_stiff_960 final trajectories
# vs_rest at x100 / x1000: rates kept 0.07, 0.58, 0.27 / 0.33, 0.71, 0.63; / S 0.04, 0.48, 0.08 /
# 0.14, 1.17, 0.37; / sqrt(S) 0.03, 0.32, 0.06 / 0.11, 0.86, 0.30 (docs/surrogate_vs_solver.md).
DAMPING_RATES = ("damping", "settle_damping")
# the reference configuration of the settings that change it
_REFERENCE = {"adaptive": "adaptive", "adaptive_coarse_mesh": "adaptive", "total": "total"}
# background mesh coarsening (params.mesh_size x factor) of the settings that have one
_MESH_FACTOR = {"coarse_mesh_1.5": 1.5, "coarse_mesh": 2.0, "adaptive_coarse_mesh": 2.0}
# stability_limit: the time step x these factors of the data's, tried in order until a run fails
# or goes unstable (at most this many solver runs per trajectory)
STABILITY_FACTORS = (2.0, 4.0, 8.0, 16.0)


def setting_config(base: dict, setting: str, frames: int, dt: float | None = None) -> dict | None:
    """The generating config ``base`` changed for ``setting`` (None when the scene lacks the knob,
    or for ``adaptive*`` / ``total`` when the data already used that reference configuration).

    ``dt``: the time step (s) to try, for ``stability_limit`` only (required there).
    """
    if not is_setting(setting):
        raise ValueError(f"unknown solver setting {setting!r}; choose from {', '.join(SOLVER_SETTINGS)} "
                         "(or mass_scaling_S for a whole S >= 2)")
    config = copy.deepcopy(base)
    config["output"] = {**config.get("output", {}), "frames": frames, "step_diagnostics": False}
    params, solver = config.setdefault("params", {}), config.setdefault("solver", {})
    reference = _REFERENCE.get(setting)
    if reference is not None:
        if solver.get("reference", SOLVER_DEFAULTS["reference"]) == reference:
            return None
        solver["reference"] = reference
    if setting in _MESH_FACTOR:
        if "mesh_size" not in params:
            return None
        params["mesh_size"] = _MESH_FACTOR[setting] * params["mesh_size"]
    elif setting == "fewer_particles":
        if "body_size" not in params:
            return None
        params["body_size"] = 1.5 * params["body_size"]
        if params.get("min_nodes"):  # a node floor (press scene) is coarsened alike: 1.5^2 fewer nodes
            params["min_nodes"] = max(1, round(params["min_nodes"] / 2.25))
    elif setting == "large_step":
        if solver.get("dt"):
            solver["dt"] = 2.0 * solver["dt"]
        else:
            solver["cfl"] = 2.0 * solver.get("cfl", SOLVER_DEFAULTS["cfl"])
    elif setting == "stability_limit":
        if dt is None:
            raise ValueError("setting 'stability_limit' needs the time step to try (dt)")
        solver["dt"] = float(dt)
    elif mass_scaling_factor(setting) is not None:
        if not _quasi_static(config) or "density" not in params:
            return None
        scale = mass_scaling_factor(setting)
        params["density"] = float(params["density"]) * scale
        defaults = getattr(get_scene(config["scene"]), "DEFAULTS", {})
        params["gravity"] = float(params.get("gravity", defaults.get("gravity", 0.0))) / scale
        for key in DAMPING_RATES:  # velocity decay rates (1/s): / sqrt(S) keeps each damping ratio
            if params.get(key, defaults.get(key)):
                params[key] = float(params.get(key, defaults.get(key))) / math.sqrt(scale)
    return config


def is_setting(name: str) -> bool:
    """Whether ``name`` is a solver setting: a key of :data:`SOLVER_SETTINGS` or ``mass_scaling_S``."""
    return name in SOLVER_SETTINGS or mass_scaling_factor(name) is not None


def mass_scaling_factor(setting: str) -> int | None:
    """S of a ``mass_scaling_S`` setting (a whole number >= 2), else None."""
    match = MASS_SCALING.fullmatch(str(setting))
    return int(match.group(1)) if match and int(match.group(1)) >= 2 else None


def next_mass_scaling(setting: str) -> str:
    """The mass scaling after ``setting`` on the 1-3-10 ladder: 3000 -> 10000 -> 30000 -> 100000."""
    scale = mass_scaling_factor(setting)
    if scale is None:
        raise ValueError(f"{setting!r} is no mass_scaling_S setting")
    decade = 10 ** int(math.floor(math.log10(scale)))
    return f"mass_scaling_{3 * decade if scale < 3 * decade else 10 * decade}"


def _quasi_static(config: dict) -> bool:
    """Whether the scene of a generating config drives its body quasi-statically (mass scaling applies)."""
    try:
        return bool(getattr(get_scene(config.get("scene")), "QUASI_STATIC", False))
    except ConfigError:  # a gas scene (datagen.csmpm) or none: no mass to scale
        return False


def setting_label(setting: str, runs: list[dict]) -> str:
    """The chart's and report's label of ``setting`` after its ``runs``: for ``stability_limit``
    with the time step factor reached (a range when trajectories differ)."""
    label = SOLVER_SETTINGS.get(setting) or f"solver, mass scaling x{mass_scaling_factor(setting)}"
    factors = [r["dt_factor"] for r in runs if setting == "stability_limit" and "dt_factor" in r]
    if not factors:
        return label
    low, high = min(factors), max(factors)
    return f"{label} ({low:.3g}x)" if f"{low:.3g}" == f"{high:.3g}" else f"{label} ({low:.3g}x-{high:.3g}x)"


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
    return {"failed": message, "unstable_step": 1, "seconds": seconds, "solver_s": seconds,
            "seconds_per_sim_second": seconds / (frames * frame_dt(trajectory)),
            "rmse_all": math.inf, "rmse_1": math.inf, "rmse_50": math.inf, "rel_all": math.inf,
            "vs_rest": math.inf, "rigid_rel_all": math.inf, "deform_rel_all": math.inf,
            "error_curve": np.full(frames, np.inf)}


def run_solver(trajectory, setting: str, frames: int, bound: float, threads: int | None = None,
               done: dict | None = None) -> dict:
    """Metrics (:func:`bsms.rollouts.rollout.rollout_metrics`) and timing of the solver at ``setting``
    over the first ``frames`` frames of ``trajectory``; {"skipped": why} without the knob.

    threads: torch CPU threads of the run (solver.threads; None: the data config's). done: the
    metrics of this trajectory's runs at other settings (name -> metrics), which
    ``stability_limit`` reuses (:func:`stability_limit`). Every result names its ``setting``;
    a run also gives its time step (``dt``, ``dt_factor``: over the data's, ``substeps``).
    """
    keep_freed_memory()  # the footing of the learned rollouts it is timed against (bsms.rollouts.memory)
    if setting == "stability_limit":
        metrics = stability_limit(trajectory, frames, bound, threads, done)
    else:
        config = setting_config(trajectory.config, setting, frames)
        if config is None:
            used = trajectory.config.get("solver", {}).get("reference")
            metrics = {"skipped": f"the data already used the {used} reference configuration"
                       if used == _REFERENCE.get(setting) else
                       "the scene's drive is not quasi-static: mass scaling would change its physics"
                       if mass_scaling_factor(setting) is not None and not _quasi_static(trajectory.config) else
                       f"the scene has no knob for {setting}"}
        else:
            metrics = _measure(trajectory, config, frames, bound, threads, ground_truth=setting == "ground_truth")
    return {**metrics, "setting": setting}


def _measure(trajectory, config: dict, frames: int, bound: float, threads: int | None,
             ground_truth: bool = False) -> dict:
    """Run ``config`` and measure it against ``trajectory`` (failed: infinite errors)."""
    if threads is not None:
        config = {**config, "solver": {**config["solver"], "threads": int(threads)}}
    start = time.perf_counter()
    try:
        other = simulate(config)
    except SimulationError as exc:
        return _failed(str(exc).splitlines()[0], time.perf_counter() - start, frames, trajectory)
    except ConfigError as exc:  # e.g. a doubled solver.cfl above 1
        return {"skipped": str(exc).splitlines()[0]}
    spec = spec_of(trajectory) if (trajectory.config or {}).get("field_spec") else None
    if spec is not None and not spec.is_lagrangian:  # Eulerian data (a fixed mesh): the fields, on the same cells
        if other.mesh.n_nodes != trajectory.mesh.n_nodes:
            return {"skipped": "an Eulerian run on another grid has no common nodes to compare on"}
        state, stored = eulerian_state(spec, other), eulerian_state(spec, trajectory)[: frames + 1]
        metrics = eulerian_metrics(spec, state, stored, free_nodes(trajectory), bound)
        return _timed(metrics, trajectory, other, frames, ground_truth, lambda: float(np.abs(state - stored).max()))
    truth = trajectory.positions[: frames + 1]
    positions = other.positions
    if positions.shape[1:] != truth.shape[1:]:
        body = trajectory.body_id if trajectory.body_id is not None else np.zeros(len(truth[0]), int)
        other_body = other.body_id if other.body_id is not None else np.zeros(other.positions.shape[1], int)
        positions = interpolate_to(trajectory.mesh.nodes, body, other.mesh.nodes, other_body, positions)
    free, size = free_nodes(trajectory), body_size(trajectory.mesh.nodes)
    metrics = rollout_metrics(positions, truth, free, size, bound)
    metrics.update(skill(positions, truth, free, size, metrics["rel_all"]))
    return _timed(metrics, trajectory, other, frames, ground_truth,
                  lambda: float(np.abs(other.positions - truth).max()))


def _timed(metrics: dict, trajectory, other, frames: int, ground_truth: bool, difference) -> dict:
    """``metrics`` with the run's timing and time step (and, for the ground truth, its largest
    difference from the stored trajectory: ``difference()``): ``solver_s`` end to end (setup and
    frames; the pre-roll apart, ``preroll_s``), ``seconds`` the same (every row's end-to-end
    time), per simulated second and per frame."""
    setup = float(other.setup_time or 0.0)
    metrics.update(solver_s=setup + other.wall_time, setup_s=setup, preroll_s=float(other.preroll_time or 0.0))
    metrics["seconds"] = metrics["solver_s"]
    metrics["seconds_per_sim_second"] = metrics["solver_s"] / (frames * frame_dt(trajectory))
    metrics["seconds_per_step"] = metrics["solver_s"] / frames
    metrics.update(dt=float(other.dt), dt_factor=float(other.dt / trajectory.dt), substeps=int(other.substeps))
    if ground_truth:
        metrics["max_difference_from_stored"] = difference()
    return metrics


def _stable(metrics: dict) -> bool:
    return "failed" not in metrics and "skipped" not in metrics and metrics.get("unstable_step") is None


def largest_stable(trial, factors=STABILITY_FACTORS) -> tuple[dict | None, list[dict]]:
    """The bounded search for the largest stable time step: ``trial(factor)`` -> metrics for each
    factor in order, stopping at the first run that failed, was skipped or went unstable, and
    after a run that takes one solver step per frame (``substeps`` 1: larger factors change
    nothing). -> (metrics of the last stable run, None when the first was not; one record per
    try: factor, stable, and the run's dt_factor, unstable_step, failed or skipped)."""
    best, tries = None, []
    for factor in factors:
        metrics = trial(factor)
        stable = _stable(metrics)
        tries.append({"factor": float(factor), "stable": stable,
                      **{k: metrics[k] for k in ("dt_factor", "unstable_step", "failed", "skipped") if k in metrics}})
        if not stable:
            break
        best = metrics
        if metrics.get("substeps") == 1:
            break
    return best, tries


def stability_limit(trajectory, frames: int, bound: float, threads: int | None = None, done: dict | None = None,
                    factors=STABILITY_FACTORS) -> dict:
    """The solver at the largest time step it survives on ``trajectory``: the data's time step x
    ``factors`` in turn (:func:`largest_stable`), at most ``len(factors)`` runs; the last stable
    run is the result, with ``search`` (the tries). A run is stable when the solver does not
    stop and the error stays within ``bound`` x body size (the evaluation's instability bound).

    done: runs of this trajectory already made (setting -> metrics): ``large_step`` is the
    first try when it took the same number of substeps as x2 (it does: ceil(ceil(x)/2) =
    ceil(x/2)); when even the first try fails, the limit is the data's own time step and the
    result is ``ground_truth``'s run (made here when not done).
    """
    done = done or {}
    doubled = done.get("large_step") or {}

    def trial(factor: float) -> dict:
        if factor == 2.0 and doubled.get("substeps") == math.ceil(trajectory.substeps / 2):
            return doubled
        config = setting_config(trajectory.config, "stability_limit", frames, dt=factor * trajectory.dt)
        return _measure(trajectory, config, frames, bound, threads)

    best, tries = largest_stable(trial, factors)
    if best is None:
        best = done.get("ground_truth") or _measure(
            trajectory, setting_config(trajectory.config, "ground_truth", frames), frames, bound, threads)
    best = {k: v for k, v in best.items() if k not in ("max_difference_from_stored", "setting")}
    return {**best, "search": tries}
