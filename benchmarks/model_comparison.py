"""Accuracy and cost of the four models and BSMS-GNN's five transitions on one family, with
one training budget, on one chart (the form of the thesis' Tables 4.5 and 4.7).

Each variant is trained by ``python train.py CONFIG name=<prefix>_<label> model.name=...
model.transition=... train.steps=STEPS`` (everything else from CONFIG: the same data, noise,
batch size, optimiser and seed), one after the other, one process each; a finished run is
kept, an interrupted one resumes. Then one ``python -m bsms.evaluate`` rolls them all out on
the same test trajectories against the solver (``--compare``), each model timed in the same
process with the same threads, and this script writes ``<runs>/<prefix>_comparison.md``:

* train ms/step: the run's training seconds over its steps (``metrics.csv``; the machine's
  other load included, so compare within one invocation);
* train peak RSS: the training process' resident-set high-water mark (``wait4``), data
  loading included, as the thesis' "training RAM";
* infer ms/step and the speed-up over the solver at the data's settings, RMSE-1, RMSE-50 and
  RMSE over all steps (m, free body nodes; and relative to the body size), unstable rollouts
  and the first unstable step: from the evaluation's ``metrics.json``. (Its inference peak
  memory is the evaluating process' high-water mark, the same for every model compared in
  one run, so it is not shown.)

Ends with exactly ``model comparison: RMSE all BSMS a, MGN b, GRID c, GUNETS d`` (m).

    python benchmarks/model_comparison.py [--config configs/glyphs_quickstart.yaml] [--steps 1500]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from model_costs import VARIANTS  # noqa: E402

THESIS_NOTE = ("thesis Table 4.5 (cylinder flow): train ms/step BSMS 10.1, GRID 15.4, MGN 19.3, GUNETS 16.2; "
               "RMSE-all [1e-2] 8.37, 8.49, 10.7, 165. Table 4.7 (transitions, cylinder flow): RMSE-all [1e-2] "
               "bistride 16.8, none 259, graph_conv 551, pos_kernel 20.1, learnable 15.7")


def train(config: str, name: str, variant: list[str], steps: int, runs: Path, extra: list[str]) -> int:
    """Train one variant (``variant``: its key=value overrides of ``config``; resuming an
    interrupted run, keeping a finished one); returns the training process' peak resident set
    in bytes (0 when nothing ran)."""
    run = runs / name
    done = run / "metrics.csv"
    if done.is_file():
        rows = list(csv.DictReader(done.open()))
        if rows and int(rows[-1]["step"]) >= steps and (run / "checkpoints" / "best.pt").is_file():
            return 0
    command = [sys.executable, str(ROOT / "train.py"), config, f"name={name}", f"runs={runs}", *variant,
               f"train.steps={steps}", "evaluate.enabled=false", *extra]
    if (run / "checkpoints" / "latest.pt").is_file():
        command.append("--resume")
    print(f"training {name}: {' '.join(command[2:])}", flush=True)
    process = subprocess.Popen(command, cwd=ROOT)
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode != 0:
        raise SystemExit(f"training {name} failed (exit {process.returncode})")
    peak = usage.ru_maxrss * 1024
    (run / "train_peak_rss.json").write_text(json.dumps({"bytes": peak}))
    return peak


def train_ms_per_step(run: Path) -> float:
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    first, last = rows[0], rows[-1]
    return 1e3 * (float(last["seconds"]) - float(first["seconds"])) / (int(last["step"]) - int(first["step"]))


def evaluate_runs(runs: list[Path], threads: int, trajectories: int | None, no_solver: bool,
                  solver: list[str] | None = None, checkpoint: str = "best") -> dict:
    """One ``bsms.evaluate`` of ``runs[0]`` with the others compared, on the same trajectories and
    threads (``solver``: the solver settings, default the run's; ``checkpoint``: best or latest of
    every run); returns its metrics.json (the report and charts are in ``runs[0]``)."""
    first, *rest = runs
    command = [sys.executable, "-m", "bsms.evaluate", str(first), "--compare", *map(str, rest),
               "--threads", str(threads), "--checkpoint", checkpoint, "--quiet"]
    if trajectories:
        command += ["--trajectories", str(trajectories)]
    if no_solver:
        command.append("--no-solver")
    elif solver:
        command += ["--solver", *solver]
    subprocess.run(command, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return json.loads((first / "evaluation" / "metrics.json").read_text())


def table(runs: Path, names: dict[str, str], metrics: dict) -> list[str]:
    rows = {row["label"]: row for row in metrics["rows"]}
    lines = ["| model | train ms/step | train peak RSS (MB) | infer ms/step, speed-up | RMSE-1 (m) | RMSE-50 (m) "
             "| RMSE all (m) | RMSE all / body size | unstable (first step) |", "|---|---|---|---|---|---|---|---|---|"]
    for label, name in names.items():
        row, run = rows[name], runs / name
        rss = json.loads((run / "train_peak_rss.json").read_text())["bytes"] / 2**20 \
            if (run / "train_peak_rss.json").is_file() else float("nan")
        infer = 1e3 * row["seconds_per_step"]
        lines.append(f"| {label} | {train_ms_per_step(run):.1f} | {rss:.0f} | {infer:.1f}, {row['speedup']:.2f}x "
                     f"| {row['rmse_1']:.3g} | {row['rmse_50']:.3g} | {row['rmse_all']:.3g} "
                     f"| {row['rel_all']:.3g} | {row['unstable']} of {row['trajectories']} "
                     f"({row['first_unstable_step'] if row['first_unstable_step'] is not None else '-'}) |")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/glyphs_quickstart.yaml", help="training config (the family)")
    parser.add_argument("--steps", type=int, default=1500, help="training steps of every variant (default 1500)")
    parser.add_argument("--models", nargs="+", default=[label for label, _, _ in VARIANTS],
                        help="labels of the variants (default all)")
    parser.add_argument("--prefix", default="cmp", help="run names are PREFIX_<label> (default cmp)")
    parser.add_argument("--runs", type=Path, default=Path("runs"), help="runs folder (default runs)")
    parser.add_argument("--trajectories", type=int, default=None, help="test trajectories (default: the config's)")
    parser.add_argument("--threads", type=int, default=1, help="threads of the timed rollouts (default 1)")
    parser.add_argument("--no-solver", action="store_true", help="learned models only")
    parser.add_argument("overrides", nargs="*", help="more key=value overrides for every training run")
    args = parser.parse_args(argv)
    known = {label: (name, transition) for label, name, transition in VARIANTS}
    unknown = [m for m in args.models if m not in known]
    if unknown:
        parser.error(f"unknown --models {' '.join(unknown)}; choose from {' '.join(known)}")
    if args.steps < 1:
        parser.error("--steps must be >= 1")
    names = {label: f"{args.prefix}_{label.replace('-', '_').lower()}" for label in args.models}
    for label, name in names.items():
        model, transition = known[label]
        train(args.config, name, [f"model.name={model}", f"model.transition={transition}"], args.steps, args.runs,
              args.overrides)
    first = args.runs / next(iter(names.values()))
    metrics = evaluate_runs([args.runs / name for name in names.values()], args.threads, args.trajectories,
                            args.no_solver)
    lines = table(args.runs, names, metrics)
    out = args.runs / f"{args.prefix}_comparison.md"
    out.write_text(f"{args.steps} training steps each, config {args.config}\n\n" + "\n".join(lines)
                   + f"\n\n{THESIS_NOTE}\n")
    print("\n".join(lines))
    print(f"written to {out}; report with charts: {first / 'report.md'}")
    rows = {row["label"]: row for row in metrics["rows"]}
    parts = [f"{label} {rows[names[label]]['rmse_all']:.3g}" for label in ("BSMS", "MGN", "GRID", "GUNETS")
             if label in names]
    print(f"model comparison: RMSE all {', '.join(parts)}")


if __name__ == "__main__":
    main()
