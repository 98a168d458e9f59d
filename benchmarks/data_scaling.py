"""How much data does a surrogate need? The learning curve of a family's recipe.

Trains the recipe of ``--config`` (default the press family's) on the first 24 / 48 / 96 / 192
training trajectories (``train.trajectories``; ``--trajectories``) at each step budget of
``--steps`` (each run its own cosine schedule; multi-step training, where the recipe has it,
from half the budget on), ``--workers`` runs at a time, each on one CPU thread. Every run is
``python train.py CONFIG name=<prefix>_n<N>_s<STEPS> train.trajectories=N train.steps=STEPS``
(resumable: a finished run is kept). Then one ``bsms.evaluate`` rolls every run's last
checkpoint out on the test split (no solver: the learned models only) and reads its error
relative to the body size (``rel_all``) and to predicting no motion (``vs_rest``,
:mod:`bsms.rollouts.motion`), both means over the test trajectories.

Writes ``<runs>/<prefix>_data_scaling.md`` (the table) and ``docs/images/data_scaling.png``
(``vs_rest`` and rel RMSE against trajectories, one line per budget, and against steps, one
line per data size). Ends with exactly

    data scaling: vs_rest A at N0 trajectories, B at N1 trajectories (S steps)

(the smallest and the largest data size at the largest budget).

    python benchmarks/data_scaling.py [--config configs/press.yaml] [--trajectories 24 48 96 192]
        [--steps 4000 8000] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ["OMP_NUM_THREADS"] = "1"  # every training process on one thread (inherited)

from model_comparison import evaluate_runs, train, train_ms_per_step  # noqa: E402


def run_name(prefix: str, trajectories: int, steps: int) -> str:
    return f"{prefix}_n{trajectories}_s{steps}"


def draw(results: dict, path: Path) -> None:
    """vs_rest and rel RMSE against trajectories (a line per budget) and against steps (a line
    per data size); ``results[(n, steps)] = (vs_rest, rel_all)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = sorted({n for n, _ in results})
    budgets = sorted({s for _, s in results})
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for s in budgets:
        axes[0].plot(sizes, [results[n, s][0] for n in sizes], "o-", label=f"{s} steps")
        axes[1].plot(sizes, [100 * results[n, s][1] for n in sizes], "o-", label=f"{s} steps")
    for n in sizes:
        axes[2].plot(budgets, [results[n, s][0] for s in budgets], "o-", label=f"{n} trajectories")
    axes[0].set(xlabel="training trajectories", ylabel="rollout RMSE / predicting no motion (vs_rest)",
                xscale="log", yscale="log")
    axes[1].set(xlabel="training trajectories", ylabel="rollout RMSE / body size (%)", xscale="log", yscale="log")
    axes[2].set(xlabel="training steps", ylabel="vs_rest", xscale="log", yscale="log")
    for ax in (axes[0], axes[2]):
        ax.axhline(1.0, color="grey", ls=":", lw=1)  # predicting no motion
    for ax in axes:
        ax.legend(fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("test split, rollouts from frame 0 over all frames (mean over trajectories)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/press.yaml")
    parser.add_argument("--trajectories", type=int, nargs="+", default=[24, 48, 96, 192])
    parser.add_argument("--steps", type=int, nargs="+", default=[4000, 8000])
    parser.add_argument("--workers", type=int, default=2, help="training runs at a time (one thread each)")
    parser.add_argument("--runs", type=Path, default=ROOT / "runs")
    parser.add_argument("--prefix", default="ds")
    parser.add_argument("--picture", type=Path, default=ROOT / "docs" / "images" / "data_scaling.png")
    args = parser.parse_args(argv)
    jobs = [(n, s) for s in sorted(args.steps) for n in sorted(args.trajectories)]

    def one(job):
        n, steps = job
        overrides = [f"train.trajectories={n}", f"train.unroll_warmup={steps // 2}", "train.progress=false"]
        train(args.config, run_name(args.prefix, n, steps), overrides, steps, args.runs, [])

    with ThreadPoolExecutor(args.workers) as pool:
        list(pool.map(one, jobs))
    runs = [args.runs / run_name(args.prefix, n, s) for n, s in jobs]
    metrics = evaluate_runs(runs, threads=1, trajectories=None, no_solver=True, checkpoint="latest")
    rows = {row["label"]: row for row in metrics["rows"]}
    results = {(n, s): (rows[run_name(args.prefix, n, s)]["vs_rest"], rows[run_name(args.prefix, n, s)]["rel_all"])
               for n, s in jobs}
    lines = ["| training trajectories | steps | train ms/step | rel RMSE all | vs at rest | unstable |",
             "|---|---|---|---|---|---|"]
    for (n, s), run in zip(jobs, runs, strict=True):
        row = rows[run.name]
        lines.append(f"| {n} | {s} | {train_ms_per_step(run):.0f} | {100 * row['rel_all']:.3g}% "
                     f"| {row['vs_rest']:.3g} | {row['unstable']} of {row['trajectories']} |")
    table = "\n".join(lines)
    (args.runs / f"{args.prefix}_data_scaling.md").write_text(table + "\n")
    print(table)
    draw(results, args.picture)
    top = max(args.steps)
    small, large = min(args.trajectories), max(args.trajectories)
    print(f"data scaling: vs_rest {results[small, top][0]:.3g} at {small} trajectories, "
          f"{results[large, top][0]:.3g} at {large} trajectories ({top} steps)")


if __name__ == "__main__":
    main()
