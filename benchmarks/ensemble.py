"""How much of a learned model's error is the luck of one training run? Several runs, and their mean.

Rolls every run out on the split of the first run's dataset (each its own graph options and
checkpoint), then scores the mean of their predicted positions (per node and frame) the same
way. Where the mean scores far below each run, the runs err differently and more runs (or
seeds) would pay; where it scores about as each, their error is shared: what the data or the
inputs cannot tell them. Prints one row per run and one for the mean (``vs at rest`` per
trajectory, its mean, the RMSE over all steps relative to the body size), then how far the runs
disagree (:func:`bsms.ensemble.spread`, relative to the body size, per trajectory) and its rank
correlation with the mean's error across trajectories (whether the spread, which needs no
solver, tells which rollouts to distrust). ``--weights W ...`` adds a row per W for the mean that
weighs the first run W and the others 1 - W between them (choose W on the validation split, never
on the test split). Ends with exactly

    ensemble: vs at rest E of the mean of N runs, each R0-R1

``--data FOLDER`` scores the runs on another dataset folder of their family (e.g. the shapes of no
split that ``benchmarks/zero_shot_set.py`` stores); one run is then enough (no mean row).

    python benchmarks/ensemble.py RUN [RUN ...] [--split test] [--trajectories 8] [--checkpoint latest]
        [--data FOLDER] [--weights W ...]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.stats import spearmanr  # noqa: E402

from bsms.ensemble import spread  # noqa: E402
from bsms.fields import world_positions  # noqa: E402
from bsms.rollouts.learned_rollouts import learned_rollouts  # noqa: E402
from bsms.rollouts.motion import skill  # noqa: E402
from bsms.rollouts.rollout import body_size, rollout_metrics  # noqa: E402
from bsms.rollouts.solver_runs import free_nodes  # noqa: E402
from bsms.run import dataset_folder, load_model, split_files  # noqa: E402
from datagen.dataset import load  # noqa: E402


def score(predicted: np.ndarray, trajectory, spec) -> dict:
    """rel_all and vs_rest of positions ``predicted`` (T, N, d) against the trajectory."""
    truth = world_positions(spec, trajectory)[: len(predicted)]
    free, size = free_nodes(trajectory), body_size(trajectory.mesh.nodes)
    metrics = rollout_metrics(predicted, truth, free, size)
    metrics.update(skill(predicted, truth, free, size, metrics["rel_all"]))
    return metrics


def row(label: str, scored: list[dict]) -> str:
    vs = [m["vs_rest"] for m in scored]
    rel = np.mean([m["rel_all"] for m in scored])
    return f"| {label} | {np.mean(vs):.3g} ({', '.join(f'{v:.2f}' for v in vs)}) | {100 * rel:.3g}% |"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="run folders (or pretrained folders) of one family's data")
    parser.add_argument("--split", default="test")
    parser.add_argument("--trajectories", type=int, default=None, help="at most this many (default: all)")
    parser.add_argument("--checkpoint", default="latest", choices=["best", "latest"])
    parser.add_argument("--data", type=Path, default=None,
                        help="score on this dataset folder (default: the first run's dataset)")
    parser.add_argument("--weights", type=float, nargs="+", default=[], metavar="W",
                        help="also score means weighing the first run W (the others share 1 - W)")
    args = parser.parse_args(argv)
    if any(not 0 <= w <= 1 for w in args.weights):
        parser.error(f"--weights must lie in [0, 1], got {args.weights}")
    if len(args.runs) < 2 and args.data is None:
        parser.error("give at least two runs to average (or --data FOLDER to score one)")
    models = [load_model(run, args.checkpoint) for run in args.runs]
    folder = args.data if args.data is not None else dataset_folder(args.runs[0], models[0][1])[0]
    files = split_files(folder, args.split)[: args.trajectories]
    trajectories = [load(path) for path in files]
    spec = models[0][0].spec
    if not spec.is_lagrangian:
        parser.error(f"{args.runs[0]} learned Eulerian fields; the mean of positions needs Lagrangian data")
    frames = [len(world_positions(spec, t)) - 1 for t in trajectories]
    print("| run | vs at rest (per trajectory) | RMSE all / body size |")
    print("|---|---|---|")
    predictions, each = [], []
    for model, config, _ in models:
        out = learned_rollouts(model, config.graph, trajectories, folder / "hierarchies", frames)
        positions = [result.positions[:, : t.mesh.n_nodes] for (_, result), t in zip(out, trajectories, strict=True)]
        predictions.append(positions)
        scored = [score(p, t, spec) for p, t in zip(positions, trajectories, strict=True)]
        each.append(np.mean([m["vs_rest"] for m in scored]))
        print(row(config.name, scored), flush=True)
    if len(models) == 1:
        print(f"ensemble: vs at rest {each[0]:.3g} of 1 run on {folder}")
        return 0
    mean = [score(np.mean([p[k] for p in predictions], axis=0), t, spec) for k, t in enumerate(trajectories)]
    print(row(f"mean of {len(args.runs)}", mean))
    for w in args.weights:
        rest = (1 - w) / (len(predictions) - 1)
        weighted = [score(w * predictions[0][k] + rest * sum(p[k] for p in predictions[1:]), t, spec)
                    for k, t in enumerate(trajectories)]
        print(row(f"weight {w:g} on {models[0][1].name}", weighted))
    spreads = [spread(np.stack([p[k] for p in predictions]), free_nodes(t))[1] / body_size(t.mesh.nodes)
               for k, t in enumerate(trajectories)]
    errors = [m["rel_all"] for m in mean]
    correlation = spearmanr(spreads, errors).statistic if len(spreads) > 2 else float("nan")
    print(f"spread of the runs / body size: {np.mean(spreads):.3g} ({', '.join(f'{v:.2g}' for v in spreads)}); "
          f"its rank correlation with the mean's error over the {len(spreads)} trajectories: {correlation:.2f}")
    print(f"ensemble: vs at rest {np.mean([m['vs_rest'] for m in mean]):.3g} of the mean of {len(args.runs)} runs, "
          f"each {min(each):.3g}-{max(each):.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
