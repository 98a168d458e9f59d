"""Train a learned simulator from a config file.

``bsms train CONFIG [section.key=value ...] [--resume]``, or in a clone of the repository
``python train.py ...`` (the same code).

Generates the dataset the config names if trajectories are missing, builds (or loads the
cached) bi-stride hierarchies, trains, validates, evaluates rollouts against the solver
(``evaluate.enabled``), and writes everything under ``<runs>/<name>/``, report.md last.
Launch with ``torchrun --nproc_per_node K train.py CONFIG`` for data-parallel training on
K processes (gloo on CPU, nccl on GPU).
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import signal
import sys
from pathlib import Path

from bsms.checkpoint import CheckpointError, load_checkpoint
from bsms.config import ConfigError
from bsms.evaluate import evaluate
from bsms.run import checkpoint_path, load_config
from bsms.training.trainer import Trainer, TrainingDiverged
from datagen import interrupts
from datagen.config import output_folder
from datagen.dataset import DatasetError

EXIT_SIGNAL = {"SIGINT": 130, "SIGTERM": 143}


def _command(args, resume: bool) -> str:
    """The command that starts (or continues) this run, spelled the way this one was started."""
    if args.prog.startswith("python "):
        which = shutil.which("python")
        python = "python" if which and Path(which).resolve() == Path(sys.executable).resolve() else sys.executable
        start = [python, sys.argv[0] or "train.py"]
    else:
        start = args.prog.split()
    words = [*start, args.config, *args.overrides, *(["--quiet"] if args.quiet else [])]
    return shlex.join([*words, *(["--resume"] if resume else [])])


def _after_interrupt(config, args) -> str:
    """True words, after an interruption, on what is saved and the command that goes on from it."""
    if config is None:
        return f"nothing was saved (the config was not read yet). Start again with: {_command(args, False)}"
    latest = checkpoint_path(config.run_dir, "latest")
    try:
        step = int(load_checkpoint(latest)["step"])
    except CheckpointError:
        return f"nothing was saved ({latest} does not exist yet). Start again with: {_command(args, False)}"
    return f"{latest} holds step {step}. Continue with: {_command(args, True)}"


def _interrupt_on_sigterm() -> None:
    """Until training installs its own handler, SIGTERM (what batch schedulers send) acts like Ctrl-C,
    and both are recorded (:mod:`datagen.interrupts`): dataset generation checks between frames, so
    an interrupt swallowed inside a finalizer still stops the start-up. An ignored SIGINT (a
    background job's) stays ignored."""
    ignored = signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    interrupts.install([signal.SIGTERM] if ignored else [signal.SIGTERM, signal.SIGINT])


def main(argv=None, prog: str = "python train.py") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="training config YAML, e.g. configs/quickstart.yaml")
    parser.add_argument("overrides", nargs="*", help="dotted overrides such as optim.lr=3e-4 train.steps=2000")
    parser.add_argument("--resume", action="store_true", help="continue the run from its latest checkpoint")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    args.prog = prog

    _interrupt_on_sigterm()
    overrides = list(args.overrides) + (["train.progress=false"] if args.quiet else [])
    config = trainer = None
    try:
        config = load_config(args.config, overrides)
        output_folder(config.run_dir, "the run folder (config keys 'runs' and 'name')")
        trainer = Trainer(config, resume=args.resume, base=Path(args.config).parent)
        if trainer.rank == 0:
            print(f"run folder {trainer.run_dir}; {len(trainer.samples)} training samples from "
                  f"{trainer.dataset_folder}; model {config.model.name}", flush=True)
        summary = trainer.fit()
    except (ConfigError, CheckpointError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except TrainingDiverged as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:  # during start-up, or a second signal that stopped a step midway
        if trainer is None or trainer.rank == 0:
            print(f"\ninterrupted; {_after_interrupt(config, args)}", file=sys.stderr)
        return 130
    if summary["interrupted"]:
        if trainer.rank == 0:
            print(f"\n{summary['signal']}: interrupted at step {summary['steps']}; saved in {trainer.latest}. "
                  f"Continue with: {_command(args, True)}", file=sys.stderr)
        return EXIT_SIGNAL.get(summary["signal"], 130)
    if trainer.rank != 0:
        return 0
    print(f"trained {summary['steps']} steps in {summary['seconds']:.1f} s; final loss {summary['loss']:.4g}; "
          f"best validation {config.train.validation.replace('_', '-')} RMSE {summary['best_valid_rmse']:.4g} m; "
          f"checkpoints in {trainer.run_dir / 'checkpoints'}", flush=True)
    if config.evaluate.enabled:
        try:
            result = evaluate(trainer.run_dir, options=config.evaluate, progress=config.train.progress)
        except (ConfigError, CheckpointError, DatasetError) as exc:
            print(f"error: evaluation failed: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"\ninterrupted during the evaluation; training is complete ({trainer.latest}). Evaluate with: "
                  f"python -m bsms.evaluate {shlex.quote(str(trainer.run_dir))}", file=sys.stderr)
            return 130
        learned = result["rows"][0]
        error = f"{learned['rmse_all']:.4g} m ({learned['rel_all']:.3g} of the body size)"
        if "field" in learned:  # Eulerian data: the first field the model predicts, in the data's units
            error = f"of {learned['field']} {learned['rmse_all']:.4g} ({learned['rel_all']:.3g} of its RMS)"
        print(f"evaluated on {learned['trajectories']} {config.evaluate.split} trajectories: rollout RMSE "
              f"{error}, {learned['unstable']} unstable; report: {result['report']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
