"""Pretrained models: a trained run cut down to what inference needs, small enough for git.

``python -m bsms.pretrained RUN_DIR OUT [--which best|latest]`` writes ``OUT`` as a run folder
that every command taking a run reads (``bsms.infer``, ``bsms.evaluate``):

- ``checkpoints/best.pt``: the weights (normalisers included, as module buffers), the run's
  config, dimension, field spec, step and best validation loss -- no optimiser, scheduler or
  RNG state -- loadable with ``torch.load(..., weights_only=True)``;
- ``config.yaml``: the run's config (``python train.py OUT/config.yaml`` retrains it);
- ``dataset.json``: the generating dataset config (the family, its ranges and the solver
  settings that inference places meshes with and ``--solver`` checks against);
- ``metrics.csv``: the training log, where the run has one.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import yaml

from bsms.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from bsms.config import ConfigError, build, to_dict
from bsms.data import saved_graph_options
from bsms.run import Config, checkpoint_path, find_checkpoint, run_dataset_config
from datagen.atomic import atomic_path

__all__ = ["KEEP", "export", "main"]

KEEP = ("format", "config", "dim", "fields", "step", "best_valid", "seconds", "model")
"""The checkpoint entries a pretrained model keeps (inference needs no optimiser state)."""


def export(run_dir, out, which: str = "best") -> Path:
    """Write the pretrained folder ``out`` from run ``run_dir``'s checkpoint ``which``; returns
    the new checkpoint's path. Raises CheckpointError naming the run when it cannot be used."""
    run_dir, out = Path(run_dir), Path(out)
    if out.resolve() == run_dir.resolve():
        raise CheckpointError(f"export {run_dir} into another folder than the run itself")
    state = load_checkpoint(find_checkpoint(run_dir, which))
    try:
        config = build(Config, {**state["config"], "graph": saved_graph_options(state["config"].get("graph"))})
    except ConfigError as exc:
        raise CheckpointError(f"run {run_dir} holds a config this bsms cannot read ({exc})") from None
    dataset = run_dataset_config(run_dir, config)
    slim = {key: state[key] for key in KEEP if key in state}
    target = checkpoint_path(out, "best")
    target.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(target, slim)
    with atomic_path(out / "config.yaml") as tmp:
        tmp.write_text(yaml.safe_dump(to_dict(config), sort_keys=False))
    with atomic_path(out / "dataset.json") as tmp:
        tmp.write_text(json.dumps(dataset, indent=1))
    if (run_dir / "metrics.csv").is_file():
        shutil.copyfile(run_dir / "metrics.csv", out / "metrics.csv")
    return target


def main(argv=None, prog: str = "python -m bsms.pretrained") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="the trained run folder")
    parser.add_argument("out", type=Path, help="the pretrained folder to write, e.g. pretrained/press2d")
    parser.add_argument("--which", default="best", choices=("best", "latest"), help="checkpoint (default best)")
    args = parser.parse_args(argv)
    try:
        path = export(args.run, args.out, args.which)
    except (CheckpointError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({path.stat().st_size / 2**20:.2f} MB of weights)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
