"""Train a learned simulator: ``python train.py CONFIG [section.key=value ...] [--resume]``.

Generates the dataset the config names if trajectories are missing, builds (or loads the
cached) bi-stride hierarchies, trains, validates, evaluates rollouts against the solver
(``evaluate.enabled``), and writes everything under ``<runs>/<name>/``, report.md last.
Launch with ``torchrun --nproc_per_node K train.py CONFIG`` for data-parallel training on
K processes (gloo on CPU, nccl on GPU).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python train.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="training config YAML, e.g. configs/quickstart.yaml")
    parser.add_argument("overrides", nargs="*", help="dotted overrides such as optim.lr=3e-4 train.steps=2000")
    parser.add_argument("--resume", action="store_true", help="continue the run from its latest checkpoint")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)

    from bsms.checkpoint import CheckpointError
    from bsms.config import ConfigError
    from bsms.trainer import Trainer, load_config
    from datagen.dataset import DatasetError

    overrides = list(args.overrides) + (["train.progress=false"] if args.quiet else [])
    try:
        config = load_config(args.config, overrides)
        trainer = Trainer(config, resume=args.resume, base=Path(args.config).parent)
        if trainer.rank == 0:
            print(f"run folder {trainer.run_dir}; {len(trainer.train_set)} training samples from "
                  f"{trainer.dataset_folder}; model {config.model.name}", flush=True)
        summary = trainer.fit()
    except (ConfigError, CheckpointError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\ninterrupted; the latest checkpoint is saved. Continue with: python train.py {args.config} "
              f"{' '.join(args.overrides)} --resume".replace("  ", " "), file=sys.stderr)
        return 130
    if trainer.rank != 0:
        return 0
    print(f"trained {summary['steps']} steps in {summary['seconds']:.1f} s; final loss {summary['loss']:.4g}; "
          f"best validation one-step RMSE {summary['best_valid_rmse']:.4g} m; checkpoints in "
          f"{trainer.run_dir / 'checkpoints'}", flush=True)
    if config.evaluate.enabled:
        from bsms.evaluate import evaluate

        try:
            result = evaluate(trainer.run_dir, options=config.evaluate, progress=config.train.progress)
        except (ConfigError, CheckpointError, DatasetError) as exc:
            print(f"error: evaluation failed: {exc}", file=sys.stderr)
            return 2
        learned = result["rows"][0]
        print(f"evaluated on {learned['trajectories']} {config.evaluate.split} trajectories: rollout RMSE "
              f"{learned['rmse_all']:.4g} m ({learned['rel_all']:.3g} of the body size), "
              f"{learned['unstable']} unstable; report: {result['report']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
