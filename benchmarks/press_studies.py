"""The press family's training recipe and model size, measured: the ablation and the sweep.

``--study ablation`` trains the recipe's variants (second-order learning as every other
family, the velocity an input and its change the output; quasi-static learning with position
noise of several sizes; multi-step training with the gradient through the last step
(pushforward) or through every step's loss, from half the steps on) with one config and one
budget; ``--study sweep`` trains
BSMS-GNN at latent widths 32/64/128, fewer and more levels and MLP depths 1-3 around latent 32
(the family's) and 64 (every variant one point of the speed-accuracy chart). Each variant is ``python train.py CONFIG
name=<prefix>_<label> <its overrides> train.steps=STEPS`` (resumable: a finished run is kept);
then one ``bsms.evaluate`` rolls them all out on the same test trajectories, timed on the
same threads, every variant at its last checkpoint (``--checkpoint best``: best.pt), with the
solver at the data's settings for the speed-ups (``--solver S ...``: more
settings; ``--no-solver``: models only).

Writes ``<runs>/<prefix>_<study>.md``: per variant the training cost, inference ms/step and
speed-up over the solver, rollout RMSE (all steps, relative to the body size), unstable
rollouts and the first unstable step, and whether it meets the accuracy target. Ends with
exactly ``press <study>: smallest meeting TARGET: <label>|none`` (the sweep: the variant with
the fewest inference ms/step whose relative RMSE is within the target and that has no unstable
rollout; the ablation: the same rule over the recipes).

    python benchmarks/press_studies.py --study ablation [--steps 20000] [--config configs/press.yaml]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from model_comparison import evaluate_runs, train, train_ms_per_step  # noqa: E402

STUDIES = {
    "ablation": {
        "second_order_noise_1e-4": ["graph.quasi_static=false", "train.unroll=1", "noise.position=1.0e-4",
                                    "noise.gamma=0.1"],
        "quasi_static_noise_2e-5": ["train.unroll=1", "noise.position=2.0e-5"],
        "quasi_static_noise_6e-5": ["train.unroll=1", "noise.position=6.0e-5"],
        "quasi_static_noise_2e-4": ["train.unroll=1", "noise.position=2.0e-4"],
        "multi3_last": ["train.unroll=3", "train.unroll_gradient=last"],
        "multi3_all": ["train.unroll=3", "train.unroll_gradient=all"],
    },
    "sweep": {
        "latent32": ["model.latent=32"],
        "latent64": ["model.latent=64"],
        "latent128": ["model.latent=128"],
        "latent32_levels4": ["model.latent=32", "graph.levels=4"],
        "latent32_mlp1": ["model.latent=32", "model.hidden_layers=1"],
        "latent64_levels4": ["model.latent=64", "graph.levels=4"],
        "latent64_levels8": ["model.latent=64", "graph.levels=8"],
        "latent64_mlp1": ["model.latent=64", "model.hidden_layers=1"],
        "latent64_mlp3": ["model.latent=64", "model.hidden_layers=3"],
    },
}


def rows_table(names: dict[str, str], overrides: dict[str, list[str]], metrics: dict, runs: Path,
               target: float) -> list[str]:
    rows = {row["label"]: row for row in metrics["rows"]}
    lines = ["| variant | overrides | train ms/step | infer ms/step | speed-up | rel RMSE all | unstable (first step) "
             "| meets target |", "|---|---|---|---|---|---|---|---|"]
    for label, name in names.items():
        row = rows[name]
        first = row["first_unstable_step"] if row["first_unstable_step"] is not None else "-"
        lines.append(f"| {label} | `{' '.join(overrides[label])}` | {train_ms_per_step(runs / name):.0f} "
                     f"| {1e3 * row['seconds_per_step']:.2f} | {row.get('speedup', float('nan')):.3g}x "
                     f"| {row['rel_all']:.3g} | {row['unstable']} of {row['trajectories']} ({first}) "
                     f"| {'yes' if meets(row, target) else 'no'} |")
    return lines


def meets(row: dict, target: float) -> bool:
    return row["unstable"] == 0 and row["rel_all"] <= target


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--study", required=True, choices=sorted(STUDIES))
    parser.add_argument("--config", default="configs/press.yaml", help="training config (default configs/press.yaml)")
    parser.add_argument("--steps", type=int, default=20000, help="training steps of every variant (default 20000)")
    parser.add_argument("--variants", nargs="+", default=None, help="labels to run (default: all of the study)")
    parser.add_argument("--prefix", default="press", help="run names are PREFIX_<label> (default press)")
    parser.add_argument("--runs", type=Path, default=Path("runs"), help="runs folder (default runs)")
    parser.add_argument("--trajectories", type=int, default=None, help="test trajectories (default: the config's)")
    parser.add_argument("--threads", type=int, default=1, help="threads of the timed rollouts (default 1)")
    parser.add_argument("--target", type=float, default=0.01, help="relative RMSE target (default 0.01)")
    parser.add_argument("--no-solver", action="store_true", help="learned models only")
    parser.add_argument("--solver", nargs="+", default=["ground_truth"],
                        help="solver settings timed with the models (default ground_truth: the speed-ups)")
    parser.add_argument("--checkpoint", choices=("best", "latest"), default="latest",
                        help="checkpoint of every variant (default latest: the same budget for all; best.pt is "
                             "only as good as the validation split)")
    parser.add_argument("overrides", nargs="*", help="more key=value overrides for every training run")
    args = parser.parse_args(argv)
    study = STUDIES[args.study]
    chosen = args.variants or list(study)
    unknown = [v for v in chosen if v not in study]
    if unknown:
        parser.error(f"unknown --variants {' '.join(unknown)}; choose from {' '.join(study)}")
    if args.steps < 1:
        parser.error("--steps must be >= 1")
    names = {label: f"{args.prefix}_{label}" for label in chosen}
    overrides = {label: study[label] + ([f"train.unroll_warmup={args.steps // 2}"] if label.startswith("multi") else [])
                 for label in chosen}
    for label, name in names.items():
        train(args.config, name, overrides[label], args.steps, args.runs, args.overrides)
    metrics = evaluate_runs([args.runs / name for name in names.values()], args.threads, args.trajectories,
                            args.no_solver, args.solver, args.checkpoint)
    lines = rows_table(names, overrides, metrics, args.runs, args.target)
    out = args.runs / f"{args.prefix}_{args.study}.md"
    out.write_text(f"{args.steps} training steps each ({args.checkpoint} checkpoint), config {args.config}, "
                   f"extra overrides "
                   f"{' '.join(args.overrides) or 'none'}\n\n" + "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"written to {out}; report with charts: {args.runs / names[chosen[0]] / 'report.md'}")
    rows = {row["label"]: row for row in metrics["rows"]}
    passing = [label for label in chosen if meets(rows[names[label]], args.target)]
    best = min(passing, key=lambda label: rows[names[label]]["seconds_per_step"]) if passing else "none"
    print(f"press {args.study}: smallest meeting {args.target:g}: {best}")


if __name__ == "__main__":
    main()
