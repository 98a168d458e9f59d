"""The pretrained surrogate against every solver setting on its family's test split.

Generates the test split of the pretrained model's dataset where it is missing (the dataset
config is the one beside the weights, ``dataset.json``), rolls the model out from frame 0 of
every test trajectory, and runs the MPM solver at the data's settings (the ground truth, the
speed-up's baseline) and at every cheaper setting of :data:`bsms.solver_runs.SOLVER_SETTINGS`
-- A-ULMPM ``adaptive`` and ``total`` where the data used another reference, background meshes
1.5x and 2x coarser, fewer particles, larger time steps up to the stability limit -- every point
timed on one thread. ``--workers K`` (default 2) spreads the work over K one-thread processes:
the learned rollouts are one job, each trajectory's solver runs another, so every point is
timed while the other workers run (the same footing for all; 1: everything in this process,
one after another, on an otherwise idle machine). ``bsms.evaluate`` computes the metrics, the
Pareto front and which settings dominate which.

Writes ``OUT/run/evaluation/`` (metrics.json, speed_accuracy.md/.csv/.png, error curves) and,
with ``--docs``, copies the table and chart to ``docs/surrogate_vs_solver.md`` and
``docs/images/surrogate_vs_solver.png`` (what the README shows). Ends with exactly::

    surrogate: speedup S x, rel RMSE all E, vs at rest R, unstable U of N, dominated by none|<settings>

S: the ground-truth solver's wall seconds per simulated second over the model's; E: the
model's rollout RMSE over all steps and free nodes relative to the body size (mean over
trajectories); R: the mean over trajectories of that RMSE over the one of predicting no motion
(``vs_rest``, :mod:`bsms.motion`: above 1 the model has learned nothing); U of N: unstable
rollouts; the settings (names of SOLVER_SETTINGS) that are both at least as fast and at least
as accurate, one of them strictly.

    python benchmarks/surrogate_vs_solver.py [--family press | --pretrained DIR] [--trajectories N] [--workers K]

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
from bsms.run import EvaluateConfig, load_model  # noqa: E402
from bsms.solver_runs import SOLVER_SETTINGS  # noqa: E402
from datagen.dataset_config import trajectory_path  # noqa: E402
from datagen.generate import generate, jobs  # noqa: E402


def setting_name(label: str) -> str:
    """The SOLVER_SETTINGS name of a row label (``stability_limit``'s carries its step factor)."""
    names = [name for name, prefix in SOLVER_SETTINGS.items() if label == prefix or label.startswith(prefix + " (")]
    return names[0] if names else label


def ensure_test_split(dconfig: dict, root: Path) -> None:
    """Generate the trajectories of the test split that are not on disk yet (one process)."""
    missing = [j for j in jobs(dconfig, ["test"]) if not trajectory_path(root, dconfig, *j).is_file()]
    if missing:
        print(f"generating {len(missing)} test trajectories of {dconfig['dataset']} into {root}", flush=True)
        generate(dconfig, out=root, splits=["test"], workers=1)


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
    model = next(r for r in rows if r["kind"] != "solver")
    dominated = [setting_name(label) for label in model.get("dominated_by") or []]
    return (f"surrogate: speedup {model['speedup']:.3g} x, rel RMSE all {model['rel_all']:.3g}, "
            f"vs at rest {model['vs_rest']:.3g}, unstable {model['unstable']} of {model['trajectories']}, "
            f"dominated by {', '.join(dominated) or 'none'}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default=None, help="the pretrained model of this family: pretrained/<family>2d")
    parser.add_argument("--pretrained", type=Path, default=None, help="a pretrained folder (default: press2d)")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "surrogate_vs_solver")
    parser.add_argument("--trajectories", type=int, default=None, help="test trajectories (default: all)")
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
    ensure_test_split(dconfig, Path(config.dataset.root))  # the run's dataset root, from the repository root
    options = EvaluateConfig(split="test", trajectories=args.trajectories, solver=args.solver, gifs=args.gifs,
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
    print(verdict(result["rows"]))


if __name__ == "__main__":
    main()
