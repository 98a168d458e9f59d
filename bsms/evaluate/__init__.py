"""Evaluate trained runs against the solver: ``python -m bsms.evaluate RUN_DIR [--compare RUN ...]``.

On a split of the run's dataset (default: test, shapes never seen in training; ``final``: the
held-out split, once per published model) every learned model is rolled out from frame 0 of
every trajectory, and the MPM solver is run again (:mod:`bsms.rollouts.solver_runs`) at the data's own
settings -- the ground truth: its re-run must reproduce the stored trajectory -- and at cheaper
settings, mass scaling among them where the drive is quasi-static (on past x3000 while the most
scaled run is still more accurate than the model). A model with the elastic input
(``graph.elastic``) gets a row for that input alone (the physics-only answer,
:func:`bsms.rollouts.learned_rollouts.physics_rollouts`). Every method becomes one point (wall seconds per
simulated second end to end, rollout RMSE) of the speed-accuracy chart, timed in this same run on
this same machine and the same CPU threads (the solver runs get the evaluation's thread count as
solver.threads). ``speedup`` is end to end for a new mesh (the learned side's per-mesh setup
included; :mod:`bsms.rollouts.learned_rollouts`), ``speedup_throughput`` the batched figure with the
setup amortised, ``latency_ms`` one frame per call. Every row names the rows that dominate it
(:mod:`bsms.evaluate.pareto`: at least as fast and as accurate, strictly better in one); the chart draws
the Pareto front.

Datasets converted from other sources (DeepMind's, the BSMS-GNN authors') have no scene for the
solver to re-run: evaluate them with ``--no-solver`` (config: ``evaluate.solver: []``); their
Eulerian fields are measured per field (RMSE of velocity, density, pressure; :mod:`bsms.fields`).

Writes ``RUN_DIR/report.md`` and ``RUN_DIR/evaluation/``: metrics.json, speed_accuracy.csv
and .md, speed_accuracy.png, error_vs_step.png, training_curve.png, rollout_<k>.gif and an
XDMF time series of the first rollout.
"""

from __future__ import annotations

import argparse
import copy
import json
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from bsms.checkpoint import CheckpointError
from bsms.config import ConfigError
from bsms.evaluate import pareto
from bsms.evaluate.report import GROUND_TRUTH, columns, ground_truth_row, heading, rest, write_report, write_tables
from bsms.fields import eulerian_state, spec_of, world_positions
from bsms.rollouts import viz
from bsms.rollouts.learned_rollouts import PHYSICS_LABEL, end_to_end, learned_rollouts, physics_rollouts
from bsms.rollouts.rollout import peak_memory_mb, summarize
from bsms.rollouts.solver_runs import frame_dt, mass_scaling_factor, next_mass_scaling, run_solver, setting_label
from bsms.run import EvaluateConfig, convert_fix, dataset_folder, load_model, resolve_device, saved_options, split_files
from datagen.atomic import atomic_path
from datagen.compiled import cpu_summary
from datagen.config import output_folder
from datagen.dataset import DatasetError, load

__all__ = ["evaluate", "main"]


@dataclass
class _Results:
    """What one evaluation measured: per-trajectory metrics per learned model and per solver
    setting (by label), peak memory per model, the pictures drawn, and the summary rows."""

    learned: dict[str, list[dict]]
    solver: dict[str, list[dict]]
    physics: list[dict] = field(default_factory=list)
    memory: dict[str, float] = field(default_factory=dict)
    pictures: list[Path] = field(default_factory=list)
    rows: list[dict] = field(default_factory=list)


# ----------------------------------------------------------------------------- learned models
def _frames(trajectory, options: EvaluateConfig) -> int:
    available = len(trajectory.times) - 1
    return available if options.steps is None else min(options.steps, available)


def _pictures(out: Path, k: int, trajectory, result, frames: int, spec) -> Path:
    """GIF of rollout ``k`` (and, for the first, its XDMF time series); Eulerian data: the fixed
    mesh coloured by the error of the first output field, and every field in the XDMF."""
    body = result.positions[:, : trajectory.mesh.n_nodes]
    obstacles, colour, data = None, None, {}
    if trajectory.obstacle_nodes is not None and len(trajectory.obstacle_nodes):
        moving = trajectory.obstacle_positions
        obstacles = (trajectory.obstacle_nodes if moving is None else moving[: len(body)], trajectory.obstacle_facets)
    if spec.is_lagrangian:
        truth = world_positions(spec, trajectory)[: frames + 1]
        data["error"] = np.linalg.norm(body - truth[: len(body)], axis=-1)
    else:
        truth = trajectory.positions[: frames + 1]
        states = eulerian_state(spec, trajectory)[: len(result.states)]
        for f in spec.state_fields:
            cols = spec.columns(f.name)
            data[f.name] = result.states[..., cols]
            data[f"{f.name}_error"] = np.linalg.norm(result.states[..., cols] - states[..., cols], axis=-1)
        main = spec.outputs[0].name
        colour = (data[f"{main}_error"], f"{main} error")
    gif = viz.rollout_gif(trajectory.mesh.cells, body, out / f"rollout_{k}.gif", truth=truth, obstacles=obstacles,
                          frame_dt=frame_dt(trajectory), colour=colour)
    if k == 0:
        viz.write_xdmf(out / "rollout_0.xdmf", trajectory.mesh.cells, body, trajectory.times[: len(body)], data)
    return gif


def _methods(model, config, compare, which: str = "best") -> list[tuple[str, object, object]]:
    """(label, model, config) of the run and of every run to compare (checkpoint ``which``), labels distinct."""
    methods = [(config.name, model, config)]
    for other in compare:
        other_model, other_config, _ = load_model(other, which)
        methods.append((other_config.name, other_model, other_config))
    labels = [m[0] for m in methods]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"runs to compare must have different names, got {labels}")
    return methods


def _roll_out(results: _Results, methods, trajectories, cache_dir: Path, options: EvaluateConfig, out: Path,
              progress: bool) -> None:
    """Learned rollouts first, so that the process's peak memory (CPU) is theirs, not the solver's;
    ``options.batch`` trajectories at a time, as one batch."""
    device = resolve_device(options.device, "evaluate.device")
    starts = range(0, len(trajectories), options.batch)
    for first in tqdm(starts, desc="rollout batches", unit="batch", disable=not progress):
        batch = trajectories[first: first + options.batch]
        frames = [_frames(trajectory, options) for trajectory in batch]
        for label, model, config in methods:
            scored = learned_rollouts(model, config.graph, batch, cache_dir, frames, options.bound, device)
            for k, (metrics, result) in enumerate(scored, start=first):
                results.learned[label].append(metrics)
                if label == methods[0][0] and k < options.gifs:
                    results.pictures.append(_pictures(out, k, trajectories[k], result, frames[k - first],
                                                      model.spec))
            results.memory[label] = peak_memory_mb(device)
    for label, model, config in methods:  # each mesh as a new one, alone: end to end and one frame per call
        for metrics, trajectory in zip(results.learned[label], trajectories, strict=True):
            n = _frames(trajectory, options)
            _end_to_end(metrics, end_to_end(model, config.graph, trajectory, n, device), n * frame_dt(trajectory))
    _, model, config = methods[0]
    if model.spec.is_lagrangian:
        results.physics = physics_rollouts(config.graph, trajectories, [_frames(t, options) for t in trajectories],
                                           options.bound)


def _end_to_end(metrics: dict, timed: dict, simulated: float) -> None:
    """A learned rollout's metrics with its end-to-end timing (:func:`bsms.rollouts.learned_rollouts.end_to_end`)
    over ``simulated`` seconds: ``seconds_per_sim_second`` becomes end to end, the batched figure
    ``throughput_seconds_per_sim_second``."""
    metrics["throughput_seconds_per_sim_second"] = metrics["seconds_per_sim_second"]
    metrics.update(timed)
    metrics["seconds_per_sim_second"] = timed["seconds"] / simulated


def _run_solvers(results: _Results, trajectories, options: EvaluateConfig, progress: bool) -> None:
    """Every solver setting on every trajectory, on the threads the learned models were timed on;
    results.solver keyed by each setting's label (:func:`bsms.rollouts.solver_runs.setting_label`)."""
    done = [_solver_runs(trajectory, options) for trajectory in
            tqdm(trajectories, desc="solver runs", unit="traj", disable=not progress or not options.solver)]
    _collect_solver(results, done, options.solver)
    while (setting := _more_mass_scaling(results)) is not None:
        extra = [_solver_runs(trajectory, options, [setting]) for trajectory in trajectories]
        _collect_solver(results, extra, [setting])


def _solver_runs(trajectory, options: EvaluateConfig, settings=None) -> dict:
    """setting -> metrics of every solver setting (default: ``options.solver``) on one trajectory
    (in order: later settings reuse earlier ones, :func:`bsms.rollouts.solver_runs.run_solver`)."""
    done = {}
    for setting in options.solver if settings is None else settings:
        done[setting] = run_solver(trajectory, setting, _frames(trajectory, options), options.bound,
                                   threads=torch.get_num_threads(), done=done)
    return done


def _collect_solver(results: _Results, done: list[dict], settings) -> None:
    runs = {setting: [d[setting] for d in done] for setting in settings}
    results.solver.update({setting_label(setting, metrics): metrics for setting, metrics in runs.items()})


# mass scaling goes on past the settings asked for while its most scaled run is more accurate than
# the model, up to this factor
MASS_SCALING_LIMIT = 1_000_000


def _more_mass_scaling(results: _Results) -> str | None:
    """The next mass scaling to run (:func:`bsms.rollouts.solver_runs.next_mass_scaling`) while the most
    scaled run so far is stable and more accurate (mean RMSE over the whole rollout) than the
    first learned model; None when it is not, or no mass scaling ran (skipped: no quasi-static drive)."""
    scaled = [(mass_scaling_factor(runs[0].get("setting")), runs) for runs in results.solver.values()
              if runs and mass_scaling_factor(runs[0].get("setting")) is not None
              and not any("skipped" in r for r in runs)]
    model = next(iter(results.learned.values()), None)
    if not scaled or not model:
        return None
    scale, runs = max(scaled, key=lambda item: item[0])
    error = float(np.mean([r["rel_all"] for r in runs]))
    stable = all("failed" not in r and r.get("unstable_step") is None for r in runs)
    if not stable or error >= float(np.mean([m["rel_all"] for m in model])):
        return None
    following = next_mass_scaling(f"mass_scaling_{scale}")
    return following if mass_scaling_factor(following) <= MASS_SCALING_LIMIT else None


# ----------------------------------------------------------------------------- worker pool
def _in_pool(results: _Results, runs, files, cache_dir: Path, options: EvaluateConfig, out: Path,
             progress: bool) -> None:
    """The learned rollouts (one job) and each trajectory's solver runs (one job each) in a pool
    of ``options.workers`` processes on ``options.threads`` threads each (spawned: no state shared)."""
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(options.workers, mp_context=context, initializer=_worker_threads,
                             initargs=(options.threads,)) as pool:
        learned = pool.submit(_learned_job, [str(r) for r in runs], [str(f) for f in files], str(cache_dir),
                              options, str(out))
        jobs = [pool.submit(_solver_job, str(f), options) for f in files] if options.solver else []
        done = [job.result() for job in tqdm(jobs, desc="solver runs", unit="traj", disable=not progress)]
        results.learned, results.memory, results.pictures, results.physics = learned.result()
        _collect_solver(results, done, options.solver)
        while (setting := _more_mass_scaling(results)) is not None:
            extra = [job.result() for job in [pool.submit(_solver_job, str(f), options, [setting]) for f in files]]
            _collect_solver(results, extra, [setting])


def _worker_threads(threads: int | None) -> None:
    if threads is not None:
        torch.set_num_threads(threads)


def _learned_job(runs: list[str], files: list[str], cache_dir: str, options: EvaluateConfig, out: str):
    model, config, _ = load_model(Path(runs[0]), options.checkpoint)
    methods = _methods(model, config, [Path(r) for r in runs[1:]], options.checkpoint)
    results = _Results({label: [] for label, _, _ in methods}, {})
    _roll_out(results, methods, [load(f) for f in files], Path(cache_dir), options, Path(out), False)
    return results.learned, results.memory, results.pictures, results.physics


def _solver_job(file: str, options: EvaluateConfig, settings=None) -> dict:
    return _solver_runs(load(file), options, settings)


# ----------------------------------------------------------------------------- summary
def _summary_rows(results: _Results) -> list[dict]:
    """One row per learned model, then per solver setting that ran; speed-ups vs the ground truth."""
    rows = [{"label": label, "kind": "learned", **summarize(metrics), "peak_memory_mb": results.memory[label]}
            for label, metrics in results.learned.items()]
    if results.physics:
        rows.append({"label": PHYSICS_LABEL, "kind": "physics", **summarize(results.physics)})
    for label, runs in results.solver.items():
        used = [r for r in runs if "skipped" not in r]
        if not used:
            continue
        row = {"label": label, "kind": "solver", "setting": used[0]["setting"], **summarize(used)}
        failed = [r["failed"] for r in used if "failed" in r]
        if failed:
            row["failed"] = failed[0]
        factors = [r["dt_factor"] for r in used if "dt_factor" in r]
        if factors:  # the time step over the data's (the smallest over trajectories)
            row["dt_factor"] = min(factors)
        if "max_difference_from_stored" in used[0]:
            row["max_difference_from_stored"] = max(r["max_difference_from_stored"] for r in used)
        rows.append(row)
    truth = ground_truth_row(rows)
    for row in rows:
        if truth is not None and row.get("seconds_per_sim_second"):
            row["speedup"] = truth["seconds_per_sim_second"] / row["seconds_per_sim_second"]
        if truth is not None and row.get("throughput_seconds_per_sim_second"):
            row["speedup_throughput"] = truth["seconds_per_sim_second"] / row["throughput_seconds_per_sim_second"]
    pareto.mark_rows(rows, reference=GROUND_TRUTH)
    return rows


def _charts(out: Path, results: _Results, frame_interval: float, bound: float) -> None:
    truth = ground_truth_row(results.rows)
    points = [{"label": r["label"], "kind": "ground_truth" if r is truth else r["kind"],
               "seconds_per_sim_second": r["seconds_per_sim_second"], "error": pareto.row_point(r, GROUND_TRUTH)[1],
               "unstable": r["unstable"] or bool(r.get("failed")), "dominated": bool(r["dominated_by"]),
               "front": r["pareto_front"]} for r in results.rows]
    field_name = next((r["field"] for r in results.rows if r.get("field")), None)
    scale = f"{field_name} scale" if field_name else "body size"
    viz.speed_accuracy_chart(points, out / "speed_accuracy.png", ylabel=f"rollout RMSE / {scale} (whole rollout)",
                             rest=rest(results.rows))
    curves = {label: [m["error_curve"] for m in metrics] for label, metrics in results.learned.items()}
    curves.update({label: [r["error_curve"] for r in runs if "error_curve" in r]
                   for label, runs in results.solver.items()
                   if label != GROUND_TRUTH and any("error_curve" in r for r in runs)})
    sizes = [m["body_size"] for m in next(iter(results.learned.values()))]
    viz.error_curves(curves, frame_interval, out / "error_vs_step.png", bound=bound * float(np.mean(sizes)))


def _training_curve(run_dir: Path, out: Path) -> Path | None:
    if not (run_dir / "metrics.csv").is_file():
        return None
    try:
        return viz.training_curve(run_dir / "metrics.csv", out / "training_curve.png")
    except ValueError:  # no step logged yet
        return None


# ----------------------------------------------------------------------------- evaluate
def evaluate(run_dir, compare=(), options: EvaluateConfig | None = None, progress: bool = True) -> dict:
    """Evaluate ``run_dir`` (and the ``compare`` runs on the same trajectories); write the report.

    Returns {"rows": one summary row per method, "report": path of report.md}.
    """
    run_dir = Path(run_dir)
    options = options or saved_options(run_dir)
    model, config, state = load_model(run_dir, options.checkpoint if options else "best")
    options = options or config.evaluate
    threads = torch.get_num_threads()
    if options.threads is not None:
        torch.set_num_threads(options.threads)
    try:
        return _evaluate(run_dir, model, config, state, compare, options, progress)
    finally:
        torch.set_num_threads(threads)


def _evaluate(run_dir: Path, model, config, state, compare, options: EvaluateConfig, progress: bool) -> dict:
    folder, dataset_name = dataset_folder(run_dir, config)
    fix = None if config.dataset.kind == "mpm" else convert_fix(config.dataset.kind, folder, options.split)
    files = split_files(folder, options.split, fix)[: options.trajectories]
    methods = _methods(model, config, compare, options.checkpoint)
    trajectories = [load(path) for path in files]
    _check_data(methods, trajectories, files, options, config)
    out = run_dir / "evaluation"
    out.mkdir(parents=True, exist_ok=True)
    results = _Results({label: [] for label, _, _ in methods}, {})
    if options.workers > 1:
        _in_pool(results, (run_dir, *compare), files, folder / "hierarchies", options, out, progress)
    else:
        _roll_out(results, methods, trajectories, folder / "hierarchies", options, out, progress)
        _run_solvers(results, trajectories, options, progress)
    results.rows = _summary_rows(results)
    write_tables(out, results.rows, columns(model.spec))
    _charts(out, results, frame_dt(trajectories[0]), options.bound)
    training = _training_curve(run_dir, out)
    details = {"run": str(run_dir), "split": options.split, "cpu": cpu_summary(),
               "trajectories": [str(f) for f in files], "step": int(state["step"]), **_threads(trajectories),
               "rows": results.rows, "learned": results.learned, "physics": results.physics, "solver": results.solver}
    with atomic_path(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(details, indent=1, default=_json_default))
    lines = heading(config, state, options, len(files), dataset_name, model.spec)
    report = write_report(run_dir, lines, results.rows, results.learned, results.pictures, bool(options.solver),
                          options.bound, training, model.spec)
    return {"rows": results.rows, "report": report}


def _threads(trajectories) -> dict:
    """The CPU threads every point was timed on (learned rollouts and solver runs alike: the
    solver runs get solver.threads set to it), and the solver.threads the data was made with."""
    made = {t.config.get("solver", {}).get("threads") for t in trajectories}
    return {"threads": torch.get_num_threads(),
            "data_solver_threads": sorted(made, key=lambda t: (t is None, t or 0))}


def _check_data(methods, trajectories, files, options: EvaluateConfig, config) -> None:
    """Errors before any work: solver runs asked of data no solver made; a model whose field spec
    (:mod:`bsms.fields`) is not the data's."""
    if options.solver and (config.dataset.kind != "mpm" or any("scene" not in t.config for t in trajectories)):
        raise ConfigError(f"the trajectories of {Path(files[0]).parent.parent} were converted from another source "
                          f"(dataset.kind: {config.dataset.kind}), so there is no MPM scene for the solver to re-run; "
                          "evaluate with --no-solver (config: evaluate.solver: [])")
    for path, trajectory in zip(files, trajectories, strict=True):
        try:
            spec = spec_of(trajectory, f"trajectory file {path}")
        except ValueError as exc:
            raise DatasetError(str(exc)) from None
        for label, model, _ in methods:
            if spec != model.spec:
                raise DatasetError(f"run {label} learned {model.spec.describe()}, but trajectory file {path} holds "
                                   f"{spec.describe()}; evaluate a run on data like its own")


def _json_default(value):
    if isinstance(value, np.ndarray):
        return [None if not np.isfinite(v) else float(v) for v in value.ravel()]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return str(value)


def main(argv=None, prog: str = "python -m bsms.evaluate") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a run folder written by train.py (runs/<name>)")
    parser.add_argument("--compare", nargs="*", default=[], help="more run folders to put on the same chart")
    parser.add_argument("--split", default=None, help="dataset split (default: the run's evaluate.split)")
    parser.add_argument("--steps", type=int, default=None, help="rollout steps (default: all frames)")
    parser.add_argument("--trajectories", type=int, default=None, help="at most this many trajectories")
    parser.add_argument("--no-solver", action="store_true", help="skip the solver runs (learned models only)")
    parser.add_argument("--device", default=None, help="auto, cpu or cuda[:N]")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads of the learned models")
    parser.add_argument("--workers", type=int, default=None, help="processes to spread the work over")
    parser.add_argument("--solver", nargs="+", default=None, help="solver settings (default: the run's)")
    parser.add_argument("--checkpoint", choices=("best", "latest"), default=None,
                        help="checkpoint of every run (default: the run's evaluate.checkpoint, best)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        saved = saved_options(args.run_dir) or load_model(args.run_dir, args.checkpoint or "best")[1].evaluate
        options = copy.deepcopy(saved)
        if args.device is not None:
            resolve_device(args.device, "--device")
        output_folder(args.run_dir, "the run folder (the report is written there)")
        for key in ("split", "steps", "trajectories", "device", "threads", "workers", "solver", "checkpoint"):
            if getattr(args, key) is not None:
                setattr(options, key, getattr(args, key))
        if args.no_solver:
            options.solver = []
        options.validate("evaluate")
        result = evaluate(args.run_dir, args.compare, options, progress=not args.quiet)
    except (ConfigError, CheckpointError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(Path(result["report"]).read_text().split("## Speed")[0])
    print(f"report: {result['report']}")
    return 0

