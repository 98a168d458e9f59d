"""Evaluate trained runs against the solver: ``python -m bsms.evaluate RUN_DIR [--compare RUN ...]``.

On a split of the run's dataset (default: test, shapes never seen in training) every learned
model is rolled out from frame 0 of every trajectory, and the MPM solver is run again at the
data's own settings (the reference: its re-run must reproduce the stored trajectory) and at
cheaper settings -- a coarser background mesh, fewer particles (a coarser body mesh, compared
at the reference points by interpolating its displacement), a larger time step. Every
learned model and every solver setting becomes one point (wall seconds per simulated second,
rollout RMSE) of the speed-accuracy chart, timed in this same run on this same machine.

Writes ``RUN_DIR/report.md`` and ``RUN_DIR/evaluation/``: metrics.json, speed_accuracy.csv
and .md, speed_accuracy.png, error_vs_step.png, training_curve.png, rollout_<k>.gif and an
XDMF time series of the first rollout.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bsms.checkpoint import load_model
from bsms.config import ConfigError
from bsms.data import NodeType, Scenario
from bsms.rollout import DEFAULT_BOUND, body_size, peak_memory_mb, rollout, rollout_metrics, summarize
from datagen.atomic import atomic_path

__all__ = ["EvaluateConfig", "SOLVER_SETTINGS", "evaluate", "main"]

# name -> (label, how the trajectory's generating config changes)
SOLVER_SETTINGS = {
    "reference": "solver (data settings)",
    "coarse_mesh": "solver, background mesh 2x coarser",
    "fewer_particles": "solver, body mesh 1.5x coarser",
    "large_step": "solver, time step 2x larger",
}


@dataclass
class EvaluateConfig:
    """The ``evaluate`` section of a training config (train.py evaluates after training).

    split: dataset split; trajectories: at most this many (null: all); steps: rollout steps
    (null: every frame of the trajectory); bound: relative error (of the body size) that
    marks a rollout unstable; solver: the solver settings to time and compare (``reference``
    first); gifs: rollout GIFs to draw; device: auto, cpu or cuda[:N]; threads: CPU threads
    of the learned models while timed (null: torch's default). The solver runs with the
    threads its dataset config gives (the family configs use 1), so the default of 1 times
    both alike; small graphs also run fastest on one thread.
    """

    enabled: bool = True
    split: str = "test"
    trajectories: int | None = None
    steps: int | None = None
    bound: float = DEFAULT_BOUND
    solver: list[str] = field(default_factory=lambda: list(SOLVER_SETTINGS))
    gifs: int = 2
    device: str = "auto"
    threads: int | None = 1

    def validate(self, prefix: str) -> None:
        if self.split not in ("train", "valid", "test"):
            raise ConfigError(f"config key '{prefix}.split' must be train, valid or test, got {self.split!r}")
        for key in ("trajectories", "steps"):
            value = getattr(self, key)
            if value is not None and value < 1:
                raise ConfigError(f"config key '{prefix}.{key}' must be >= 1 or null, got {value}")
        if self.bound <= 0:
            raise ConfigError(f"config key '{prefix}.bound' must be positive, got {self.bound}")
        unknown = [s for s in self.solver if s not in SOLVER_SETTINGS]
        if unknown:
            raise ConfigError(f"config key '{prefix}.solver' lists unknown setting {unknown[0]!r}; choose from "
                              f"{', '.join(SOLVER_SETTINGS)}")
        if self.threads is not None and self.threads < 1:
            raise ConfigError(f"config key '{prefix}.threads' must be >= 1 or null, got {self.threads}")
        if self.gifs < 0:
            raise ConfigError(f"config key '{prefix}.gifs' must be >= 0, got {self.gifs}")


# ----------------------------------------------------------------------------- solver settings
def _setting_config(base: dict, setting: str, frames: int) -> dict | None:
    """The generating config changed for ``setting`` (None when the scene lacks the knob)."""
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
            from datagen.simulation import SOLVER_DEFAULTS

            solver["cfl"] = 2.0 * solver.get("cfl", SOLVER_DEFAULTS["cfl"])
    return config


def _interpolate_to(reference_rest: np.ndarray, reference_body: np.ndarray, other_rest: np.ndarray,
                    other_body: np.ndarray, other_positions: np.ndarray) -> np.ndarray:
    """(T, N_ref, d) positions of the reference points moved by the other run's displacement
    field (piecewise linear on each body's rest nodes; nearest node outside their hull)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    displacement = other_positions - other_positions[:1]
    out = np.empty((len(other_positions), *reference_rest.shape))
    for body in np.unique(reference_body):
        ref, oth = reference_body == body, other_body == body
        values = displacement[:, oth].transpose(1, 0, 2).reshape(oth.sum(), -1)
        moved = LinearNDInterpolator(other_rest[oth], values)(reference_rest[ref])
        outside = ~np.isfinite(moved).all(axis=1)
        if outside.any():
            moved[outside] = NearestNDInterpolator(other_rest[oth], values)(reference_rest[ref][outside])
        out[:, ref] = moved.reshape(ref.sum(), len(other_positions), -1).transpose(1, 0, 2)
    return out + reference_rest


def _run_solver(trajectory, setting: str, frames: int, bound: float) -> dict:
    from datagen import simulate
    from datagen.mpm.solver import SimulationError

    config = _setting_config(trajectory.config, setting, frames)
    if config is None:
        return {"skipped": f"the scene has no knob for {setting}"}
    start = time.perf_counter()
    try:
        other = simulate(config)
    except SimulationError as exc:
        elapsed = time.perf_counter() - start
        return {"failed": str(exc).splitlines()[0], "unstable_step": 1,
                "seconds_per_sim_second": elapsed / (frames * _frame_dt(trajectory)), "rmse_all": math.inf,
                "rmse_1": math.inf, "rmse_50": math.inf, "rel_all": math.inf, "error_curve": np.full(frames, np.inf)}
    truth = trajectory.positions[: frames + 1]
    positions = other.positions
    if positions.shape[1:] != truth.shape[1:]:
        body = trajectory.body_id if trajectory.body_id is not None else np.zeros(len(truth[0]), int)
        other_body = other.body_id if other.body_id is not None else np.zeros(other.positions.shape[1], int)
        positions = _interpolate_to(trajectory.mesh.nodes, body, other.mesh.nodes, other_body, positions)
    mask = _free(trajectory)
    metrics = rollout_metrics(positions, truth, mask, body_size(trajectory.mesh.nodes), bound)
    metrics["seconds_per_sim_second"] = other.wall_time / (frames * _frame_dt(trajectory))
    metrics["seconds_per_step"] = other.wall_time / frames
    if setting == "reference":
        metrics["max_difference_from_stored"] = float(np.abs(other.positions - truth).max())
    return metrics


def _frame_dt(trajectory) -> float:
    return float(trajectory.times[1] - trajectory.times[0])


def _free(trajectory) -> np.ndarray:
    n = trajectory.positions.shape[1]
    node_type = trajectory.node_type if trajectory.node_type is not None else np.zeros(n, int)
    return node_type == NodeType.FREE


# ----------------------------------------------------------------------------- learned models
def _learned(model, config, trajectory, cache_dir, frames: int, bound: float, device) -> tuple[dict, object]:
    scenario = Scenario.from_trajectory(trajectory, config.graph, cache_dir)
    known = scenario.full(trajectory.positions[: frames + 1])
    initial_velocity = scenario.full(trajectory.velocities[:1], 0.0)[0]
    result = rollout(model, scenario, known[0], initial_velocity, frames, known, device=device)
    predicted = result.positions[:, : scenario.n_body]
    metrics = rollout_metrics(predicted, trajectory.positions[: frames + 1], _free(trajectory),
                              body_size(trajectory.mesh.nodes), bound)
    metrics["seconds_per_step"] = result.seconds_per_step
    metrics["seconds_per_sim_second"] = result.seconds_per_step / scenario.frame_dt
    return metrics, result


def _frames(trajectory, options: EvaluateConfig) -> int:
    available = len(trajectory.times) - 1
    return available if options.steps is None else min(options.steps, available)


def _pictures(out: Path, k: int, trajectory, result, frames: int, frame_dt: float) -> Path:
    """GIF of rollout ``k`` (and, for the first, its XDMF time series)."""
    from bsms import viz

    body = result.positions[:, : trajectory.mesh.n_nodes]
    obstacles = None
    if trajectory.obstacle_nodes is not None and len(trajectory.obstacle_nodes):
        obstacles = (trajectory.obstacle_nodes, trajectory.obstacle_facets)
    gif = viz.rollout_gif(trajectory.mesh.cells, body, out / f"rollout_{k}.gif",
                          truth=trajectory.positions[: frames + 1], obstacles=obstacles, frame_dt=frame_dt)
    if k == 0:
        error = np.linalg.norm(body - trajectory.positions[: len(body)], axis=-1)
        viz.write_xdmf(out / "rollout_0.xdmf", trajectory.mesh.cells, body, trajectory.times[: len(body)],
                       {"error": error})
    return gif


# ----------------------------------------------------------------------------- report
def _fmt(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        if math.isinf(value):
            return "inf"
        return f"{value:.{digits}g}"
    return str(value)


def _table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    lines = ["| " + " | ".join(title for _, title in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_fmt(row.get(key)) for key, _ in columns) + " |" for row in rows]
    return "\n".join(lines)


_COLUMNS = [
    ("label", "method"), ("kind", "kind"), ("rmse_1", "RMSE@1 (m)"), ("rmse_50", "RMSE@50 (m)"),
    ("rmse_all", "RMSE all (m)"), ("rmse_all_std", "± std"), ("rel_all", "RMSE all / body size"),
    ("unstable", "unstable rollouts"), ("first_unstable_step", "first unstable step"),
    ("seconds_per_step", "s per frame"), ("seconds_per_sim_second", "s per simulated s"),
    ("speedup", "speed-up vs solver"), ("peak_memory_mb", "peak memory (MB)"),
]


def _device(name: str):
    import torch

    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(name)


def evaluate(run_dir, compare=(), options: EvaluateConfig | None = None, progress: bool = True) -> dict:
    """Evaluate ``run_dir`` (and the ``compare`` runs on the same trajectories); write the report.

    Returns {"rows": one summary row per method, "report": path of report.md}.
    """
    import torch

    run_dir = Path(run_dir)
    model, config, state = load_model(run_dir)
    options = options or config.evaluate
    threads = torch.get_num_threads()
    if options.threads is not None:
        torch.set_num_threads(options.threads)
    try:
        return _evaluate(run_dir, model, config, state, compare, options, progress)
    finally:
        torch.set_num_threads(threads)


def _evaluate(run_dir: Path, model, config, state, compare, options: EvaluateConfig, progress: bool) -> dict:
    from tqdm import tqdm

    from bsms import viz
    from bsms.trainer import run_dataset_config, split_files
    from datagen.dataset import load

    device = _device(options.device)
    dataset_name = run_dataset_config(run_dir, config)["dataset"]
    folder = Path(config.dataset.root) / dataset_name
    files = split_files(folder, options.split)[: options.trajectories]
    methods = [(config.name, model, config)]
    for other in compare:
        other_model, other_config, _ = load_model(other)
        methods.append((other_config.name, other_model, other_config))
    labels = [m[0] for m in methods]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"runs to compare must have different names, got {labels}")
    out = run_dir / "evaluation"
    out.mkdir(parents=True, exist_ok=True)
    cache = folder / "hierarchies"
    per_method: dict[str, list[dict]] = {label: [] for label in labels}
    per_solver: dict[str, list[dict]] = {SOLVER_SETTINGS[s]: [] for s in options.solver}
    memory: dict[str, float] = {}
    pictures, frame_dt = [], 1.0
    trajectories = [load(path) for path in files]
    # learned models first, so that the process's peak memory (CPU) is theirs, not the solver's
    for k, trajectory in enumerate(tqdm(trajectories, desc="rollouts", unit="traj", disable=not progress)):
        frame_dt = _frame_dt(trajectory)
        frames = _frames(trajectory, options)
        for label, m, c in methods:
            metrics, result = _learned(m, c, trajectory, cache, frames, options.bound, device)
            per_method[label].append(metrics)
            memory[label] = peak_memory_mb(device)
            if label == labels[0] and k < options.gifs:
                pictures.append(_pictures(out, k, trajectory, result, frames, frame_dt))
    for trajectory in tqdm(trajectories, desc="solver runs", unit="traj", disable=not progress or not options.solver):
        for setting in options.solver:
            per_solver[SOLVER_SETTINGS[setting]].append(
                _run_solver(trajectory, setting, _frames(trajectory, options), options.bound))
    rows = []
    for label in labels:
        rows.append({"label": label, "kind": "learned", **summarize(per_method[label]),
                     "peak_memory_mb": memory[label]})
    for label, results in per_solver.items():
        used = [r for r in results if "skipped" not in r]
        if not used:
            continue
        row = {"label": label, "kind": "solver", **summarize(used)}
        failed = [r["failed"] for r in used if "failed" in r]
        if failed:
            row["failed"] = failed[0]
        if "max_difference_from_stored" in used[0]:
            row["max_difference_from_stored"] = max(r["max_difference_from_stored"] for r in used)
        rows.append(row)
    reference = next((r for r in rows if r["label"] == SOLVER_SETTINGS["reference"]), None)
    for row in rows:
        if reference is not None and row.get("seconds_per_sim_second"):
            row["speedup"] = reference["seconds_per_sim_second"] / row["seconds_per_sim_second"]
    _write_tables(out, rows)
    points = [{"label": r["label"], "kind": "reference" if r is reference else r["kind"],
               "seconds_per_sim_second": r["seconds_per_sim_second"], "rmse": r["rmse_all"],
               "unstable": r["unstable"]} for r in rows]
    viz.speed_accuracy_chart(points, out / "speed_accuracy.png")
    curves = {label: [m["error_curve"] for m in per_method[label]] for label in labels}
    curves.update({label: [r["error_curve"] for r in results if "error_curve" in r]
                   for label, results in per_solver.items() if label != SOLVER_SETTINGS["reference"]
                   and any("error_curve" in r for r in results)})
    sizes = [m["body_size"] for m in per_method[labels[0]]]
    viz.error_curves(curves, frame_dt, out / "error_vs_step.png", bound=options.bound * float(np.mean(sizes)))
    training = None
    if (run_dir / "metrics.csv").is_file():
        try:
            training = viz.training_curve(run_dir / "metrics.csv", out / "training_curve.png")
        except ValueError:
            training = None
    details = {"run": str(run_dir), "split": options.split, "trajectories": [str(f) for f in files],
               "step": int(state["step"]), "rows": rows,
               "learned": {label: per_method[label] for label in labels},
               "solver": per_solver}
    with atomic_path(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(details, indent=1, default=_json_default))
    report = _write_report(run_dir, config, state, options, files, rows, pictures, training, dataset_name)
    return {"rows": rows, "report": report}


def _json_default(value):
    if isinstance(value, np.ndarray):
        return [None if not np.isfinite(v) else float(v) for v in value.ravel()]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return str(value)


def _write_tables(out: Path, rows: list[dict]) -> None:
    keys = [key for key, _ in _COLUMNS]
    with atomic_path(out / "speed_accuracy.csv") as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, keys, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    with atomic_path(out / "speed_accuracy.md") as tmp:
        tmp.write_text(_table(rows, _COLUMNS) + "\n")


def _write_report(run_dir: Path, config, state, options, files, rows, pictures, training,
                  dataset_name: str) -> Path:
    learned = [r for r in rows if r["kind"] == "learned"]
    lines = [
        f"# Evaluation of run `{config.name}`",
        "",
        f"Model `{config.model.name}` after {int(state['step'])} training steps; {len(files)} `{options.split}` "
        f"trajectories of dataset `{dataset_name}`; rollouts from frame 0 over "
        f"{'all frames' if options.steps is None else f'{options.steps} steps'}. Errors are position RMSE over "
        "free body nodes (m); times are wall seconds on this machine, measured in this run.",
        "",
        "## Metrics",
        "",
        _table(rows, _COLUMNS),
        "",
        "## Speed against accuracy",
        "",
        "![speed against accuracy](evaluation/speed_accuracy.png)",
        "",
        "The reference solver point has no error of its own (it is the ground truth); cheaper solver "
        "settings are the honest baseline a surrogate must beat.",
        "",
        "## Error against time",
        "",
        "![rollout error](evaluation/error_vs_step.png)",
        "",
        "## Stability",
        "",
    ]
    for row in rows:
        first = row.get("first_unstable_step")
        state_text = "stable on every trajectory" if not row["unstable"] else \
            f"unstable on {row['unstable']} of {row['trajectories']} (first at step {first})"
        failure = f"; the solver stopped: {row['failed']}" if row.get("failed") else ""
        lines.append(f"- {row['label']}: {state_text} (bound {options.bound} x body size){failure}")
    reference = next((r for r in rows if r["label"] == SOLVER_SETTINGS["reference"]), None)
    if reference is not None and "max_difference_from_stored" in reference:
        lines += ["", f"The re-run reference solver reproduces the stored trajectories to "
                      f"{reference['max_difference_from_stored']:.3g} m."]
    if learned and reference is not None:
        best = min(learned, key=lambda r: r["rmse_all"])
        lines += ["", f"Fastest learned model speed-up over the reference solver: "
                      f"{max(r.get('speedup', 0) for r in learned):.3g}x; most accurate: {best['label']} "
                      f"({_fmt(best['rel_all'])} of the body size over the whole rollout)."]
    if training is not None:
        lines += ["", "## Training", "", "![training curve](evaluation/training_curve.png)"]
    if pictures:
        lines += ["", "## Rollouts (solver left, learned right, coloured by error)", ""]
        lines += [f"![rollout {k}](evaluation/{Path(p).name})" for k, p in enumerate(pictures)]
        lines += ["", "ParaView: `evaluation/rollout_0.xdmf` (warp by `displacement`)."]
    path = run_dir / "report.md"
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


def main(argv=None) -> int:
    import argparse
    import sys

    from bsms.checkpoint import CheckpointError
    from datagen.dataset import DatasetError

    parser = argparse.ArgumentParser(prog="python -m bsms.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a run folder written by train.py (runs/<name>)")
    parser.add_argument("--compare", nargs="*", default=[], help="more run folders to put on the same chart")
    parser.add_argument("--split", default=None, help="dataset split (default: the run's evaluate.split)")
    parser.add_argument("--steps", type=int, default=None, help="rollout steps (default: all frames)")
    parser.add_argument("--trajectories", type=int, default=None, help="at most this many trajectories")
    parser.add_argument("--no-solver", action="store_true", help="skip the solver runs (learned models only)")
    parser.add_argument("--device", default=None, help="auto, cpu or cuda[:N]")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads of the learned models")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        _, config, _ = load_model(args.run_dir)
        options = copy.deepcopy(config.evaluate)
        for key in ("split", "steps", "trajectories", "device", "threads"):
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


if __name__ == "__main__":
    raise SystemExit(main())
