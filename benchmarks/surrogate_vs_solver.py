"""The pretrained surrogate against every solver setting on its family's held-out split.

Generates the split (default ``final``: held out, evaluated once per published model after its
recipe is fixed; ``--split test`` the test split) of the pretrained model's dataset where it is
missing (the dataset config is the one beside the weights, ``dataset.json``), rolls the model out
from frame 0 of every trajectory, and runs the MPM solver at the data's settings (the ground
truth, the speed-up's baseline) and at every cheaper setting of
:data:`bsms.rollouts.solver_runs.SOLVER_SETTINGS` -- A-ULMPM ``adaptive`` and ``total`` where the data used
another reference, background meshes 1.5x and 2x coarser, fewer particles, larger time steps up to
the stability limit, and where the drive is quasi-static mass scaling x10, x100, x1000, x3000 and
on until the solver's error passes the model's -- and, for a model with the elastic input, that
input alone (the physics-only answer). Every point is timed on one thread. ``--workers K``
(default 2) spreads the work over K one-thread processes: the learned rollouts are one job, each
trajectory's solver runs another, so every point is timed while the other workers run (the same
footing for all; 1: everything in this process, one after another, on an otherwise idle
machine). ``bsms.evaluate`` computes the metrics, the Pareto front and which settings dominate
which.

Writes ``OUT/run/evaluation/`` (metrics.json, speed_accuracy.md/.csv/.png, error curves) and,
with ``--docs``, copies the table and chart to ``docs/surrogate_vs_solver.md`` and
``docs/images/surrogate_vs_solver.png`` (what the README shows). Ends with exactly this line
(one line, wrapped here)::

    surrogate: speedup S x end to end (T x throughput), rel RMSE all E, vs at rest R,
    unstable U of N, dominated by none|<settings>

S: the ground-truth solver's wall time over the model's, end to end for each new mesh (the
model's per-mesh setup and its rollout of the mesh alone against the solver's setup and frames,
its settling pre-roll apart; :mod:`bsms.rollouts.learned_rollouts`); T: the same with the model's frames
batched over all trajectories and its setup amortised; E: the model's rollout RMSE over all steps
and free nodes relative to the body size (mean over trajectories); R: the mean over trajectories
of that RMSE over the one of predicting no motion (``vs_rest``, :mod:`bsms.rollouts.motion`: above 1 the
model has learned nothing); U of N: unstable rollouts; the settings (names of SOLVER_SETTINGS,
``mass_scaling_S``, or ``elastic_answer`` for the physics-only row) that are both at least as fast
and at least as accurate, one of them strictly. A line before it names the CPU (AVX2 / AVX-512).

    python benchmarks/surrogate_vs_solver.py [--family press | --pretrained DIR] [--split final|test]
        [--trajectories N] [--workers K] [--docs]

``--pretrained DIR`` may be an ensemble folder (``python -m bsms.pretrained RUN RUN ... OUT``).
``--family NAME`` takes ``pretrained/<NAME>2d``; with ``--docs`` the table and chart of a family
other than press are copied under its name (``docs/surrogate_vs_solver_<NAME>.md``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from bsms.ensemble import ENSEMBLE_FILE, is_ensemble, member_folders  # noqa: E402
from bsms.evaluate import evaluate  # noqa: E402
from bsms.rollouts.learned_rollouts import PHYSICS_LABEL  # noqa: E402
from bsms.rollouts.solver_runs import SOLVER_SETTINGS, mass_scaling_factor  # noqa: E402
from bsms.run import EvaluateConfig, load_model  # noqa: E402
from datagen.compiled import cpu_summary  # noqa: E402
from datagen.dataset_config import trajectory_path  # noqa: E402
from datagen.generate import generate, jobs  # noqa: E402


def setting_name(row: dict) -> str:
    """The name of a row's method: its solver setting (SOLVER_SETTINGS or ``mass_scaling_S``),
    ``elastic_answer`` for the physics-only row, else its label."""
    if row.get("setting") and (row["setting"] in SOLVER_SETTINGS or mass_scaling_factor(row["setting"])):
        return row["setting"]
    return "elastic_answer" if row["label"] == PHYSICS_LABEL else row["label"]


def ensure_split(dconfig: dict, root: Path, split: str, workers: int = 1, count: int | None = None) -> None:
    """Generate the trajectories of ``split`` (its first ``count``; None: all) that are not on disk
    yet (``workers`` processes)."""
    if split not in dconfig["splits"]:
        raise SystemExit(f"error: dataset {dconfig['dataset']} has no {split} split (splits: "
                         f"{', '.join(dconfig['splits'])}); add it to the splits of the model's dataset.json")
    missing = [j for j in jobs(dconfig, [split])[:count] if not trajectory_path(root, dconfig, *j).is_file()]
    if missing:
        print(f"generating {len(missing)} {split} trajectories of {dconfig['dataset']} into {root}", flush=True)
        if count is not None:
            dconfig = {**dconfig, "splits": {**dconfig["splits"], split: count}}
        generate(dconfig, out=root, splits=[split], workers=workers)


def copy_run(pretrained: Path, run: Path) -> None:
    """The pretrained folder copied to ``run`` (evaluation writes beside the weights); an
    ensemble folder (:mod:`bsms.ensemble`) with its members."""
    run.mkdir(parents=True, exist_ok=True)
    for name in ("config.yaml", "dataset.json", "metrics.csv", ENSEMBLE_FILE):
        if (pretrained / name).is_file():
            shutil.copyfile(pretrained / name, run / name)
    if is_ensemble(pretrained):
        for member in member_folders(pretrained):
            copy_run(member, run / member.relative_to(pretrained))
        return
    (run / "checkpoints").mkdir(exist_ok=True)
    shutil.copyfile(pretrained / "checkpoints" / "best.pt", run / "checkpoints" / "best.pt")


def verdict(rows: list[dict]) -> str:
    """The last line, from the evaluation's rows (the first learned row is the model)."""
    model = next(r for r in rows if r["kind"] == "learned")
    by_label = {r["label"]: r for r in rows}
    dominated = [setting_name(by_label[label]) if label in by_label else label
                 for label in model.get("dominated_by") or []]
    return (f"surrogate: speedup {model['speedup']:.3g} x end to end ({model['speedup_throughput']:.3g} x "
            f"throughput), rel RMSE all {model['rel_all']:.3g}, vs at rest {model['vs_rest']:.3g}, unstable "
            f"{model['unstable']} of {model['trajectories']}, dominated by {', '.join(dominated) or 'none'}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default=None, help="the pretrained model of this family: pretrained/<family>2d")
    parser.add_argument("--pretrained", type=Path, default=None, help="a pretrained folder (default: press2d)")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "surrogate_vs_solver")
    parser.add_argument("--split", default="final", choices=["final", "test", "valid"],
                        help="the split to evaluate (default final: the held-out one)")
    parser.add_argument("--trajectories", type=int, default=None, help="trajectories of the split (default: all)")
    parser.add_argument("--solver", nargs="+", default=list(SOLVER_SETTINGS), choices=list(SOLVER_SETTINGS))
    parser.add_argument("--gifs", type=int, default=2)
    parser.add_argument("--workers", type=int, default=2,
                        help="one-thread processes the learned rollouts and the solver runs share (default 2)")
    parser.add_argument("--docs", action="store_true", help="copy the table and chart into docs/")
    args = parser.parse_args(argv)
    if args.family is not None and args.pretrained is not None:
        parser.error("give --family or --pretrained, not both")
    family = args.family or "press"
    args.pretrained = args.pretrained or ROOT / "pretrained" / f"{family}2d"
    if not (args.pretrained / "checkpoints" / "best.pt").is_file() and not is_ensemble(args.pretrained):
        parser.error(f"no pretrained model at {args.pretrained} (checkpoints/best.pt); export one with "
                     f"python -m bsms.pretrained RUN {args.pretrained}")
    suffix = "" if family == "press" else f"_{family}"
    os.chdir(ROOT)
    torch.set_num_threads(1)
    run = args.out / "run"
    copy_run(args.pretrained, run)
    _, config, _ = load_model(run)
    dconfig = json.loads((run / "dataset.json").read_text())
    # the run's dataset root, from the repository root
    ensure_split(dconfig, Path(config.dataset.root), args.split, args.workers, args.trajectories)
    options = EvaluateConfig(split=args.split, trajectories=args.trajectories, solver=args.solver, gifs=args.gifs,
                             threads=1, batch=1, workers=args.workers)
    options.validate("evaluate")
    result = evaluate(run, options=options, progress=True)
    evaluation = run / "evaluation"
    print((evaluation / "speed_accuracy.md").read_text())
    if args.docs:
        (ROOT / "docs" / "images").mkdir(parents=True, exist_ok=True)
        chart = ROOT / "docs" / "images" / f"surrogate_vs_solver{suffix}.png"
        shutil.copyfile(evaluation / "speed_accuracy.png", chart)
        shutil.copyfile(evaluation / "speed_accuracy.md", ROOT / "docs" / f"surrogate_vs_solver{suffix}.md")
    print(f"cpu: {cpu_summary()}, one thread per method, {args.workers} worker(s)")
    print(verdict(result["rows"]))


if __name__ == "__main__":
    main()
