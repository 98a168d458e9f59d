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

``python -m bsms.pretrained RUN RUN ... OUT`` writes an ensemble folder (:mod:`bsms.ensemble`):
each run exported as above into ``OUT/members/<k>-<run name>``, and ``OUT/ensemble.yaml``
listing them, written last; the runs must share their graph options and their family's scene.

``--set KEY=VALUE`` changes a config key of :data:`SETTABLE` in what is written: keys that say how
the weights answer at inference, not what they are (``--set model.mirror_average=true``: a run
trained with ``train.mirror`` answers as the mean of it and its mirror image; ``--set model.rigid_step=true``:
each step's affine part made the nearest rigid motion, :mod:`bsms.models.config`).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import yaml

from bsms.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from bsms.config import ConfigError, apply_overrides, build, to_dict
from bsms.data import saved_graph_options
from bsms.ensemble import ENSEMBLE_FILE, check_members, is_ensemble
from bsms.run import Config, checkpoint_path, find_checkpoint, run_dataset_config
from datagen.atomic import atomic_path

__all__ = ["KEEP", "SETTABLE", "export", "export_ensemble", "main", "parse_settings"]

KEEP = ("format", "config", "dim", "fields", "step", "best_valid", "seconds", "model")
"""The checkpoint entries a pretrained model keeps (inference needs no optimiser state)."""

SETTABLE = ("model.mirror_average", "model.rigid_step")
"""Config keys an export may change (``--set``): how trained weights answer at inference, never
what they are."""


def parse_settings(items) -> list[str]:
    """``KEY=VALUE`` strings, checked to name keys of :data:`SETTABLE` (their values are checked
    as every config override is, when applied). Raises ConfigError naming the item that does not."""
    for item in items:
        key, sep, _ = item.partition("=")
        if not sep or key not in SETTABLE:
            raise ConfigError(f"--set {item!r}: give KEY=VALUE with KEY one of {', '.join(SETTABLE)} (keys that "
                              "change how the weights answer, not what they are)")
    return list(items)


def _with_settings(state: dict, config: Config, settings: list[str], run_dir: Path) -> tuple[dict, Config]:
    """``state`` and ``config`` with ``settings`` (:func:`parse_settings`) applied to their config."""
    if not parse_settings(settings):
        return state, config
    try:
        raw = apply_overrides(to_dict(config), settings)
        config = build(Config, raw)
    except ConfigError as exc:
        raise CheckpointError(f"run {run_dir} with {', '.join(settings)}: {exc}") from None
    return {**state, "config": raw}, config


def export(run_dir, out, which: str = "best", settings: list[str] = ()) -> Path:
    """Write the pretrained folder ``out`` from run ``run_dir``'s checkpoint ``which``, its config
    changed by ``settings`` (:func:`parse_settings`); returns the new checkpoint's path. Raises
    CheckpointError naming the run when it cannot be used."""
    run_dir, out = Path(run_dir), Path(out)
    if out.resolve() == run_dir.resolve():
        raise CheckpointError(f"export {run_dir} into another folder than the run itself")
    state, config, dataset = _run(run_dir, which)
    target = _write(run_dir, out, *_with_settings(state, config, list(settings), run_dir), dataset)
    if is_ensemble(out):  # an ensemble exported here before: this model replaces it
        (out / ENSEMBLE_FILE).unlink()
        shutil.rmtree(out / "members", ignore_errors=True)
    return target


def _write(run_dir: Path, out: Path, state: dict, config: Config, dataset: dict) -> Path:
    """The files of a pretrained folder ``out`` of run ``run_dir`` (:func:`_run`'s three); returns
    the checkpoint's path."""
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


def _run(run_dir: Path, which: str) -> tuple[dict, Config, dict]:
    """(checkpoint dict, Config, dataset config) of a trained run folder."""
    if is_ensemble(run_dir):
        raise CheckpointError(f"{run_dir} is an ensemble; give its members' runs to join them into another")
    state = load_checkpoint(find_checkpoint(run_dir, which))
    try:
        config = build(Config, {**state["config"], "graph": saved_graph_options(state["config"].get("graph"))})
    except ConfigError as exc:
        raise CheckpointError(f"run {run_dir} holds a config this bsms cannot read ({exc})") from None
    return state, config, run_dataset_config(run_dir, config)


def export_ensemble(run_dirs, out, which: str = "best", settings: list[str] = ()) -> list[Path]:
    """Write the ensemble folder ``out`` of runs ``run_dirs`` (each's checkpoint ``which``, each
    config changed by ``settings``): members first, ``ensemble.yaml`` last; returns the members'
    checkpoint paths. Raises CheckpointError naming the run that cannot join (another graph or
    scene, no checkpoint)."""
    run_dirs, out = [Path(r) for r in run_dirs], Path(out)
    if len(run_dirs) < 2:
        raise CheckpointError("an ensemble joins at least two runs")
    for run_dir in run_dirs:
        if out.resolve() == run_dir.resolve() or out.resolve() in run_dir.resolve().parents:
            raise CheckpointError(f"run {run_dir} lies in {out}: write the ensemble into a new folder (and move it "
                                  "there after)")
    loaded = []
    for run_dir in run_dirs:
        state, config, dataset = _run(run_dir, which)
        loaded.append((*_with_settings(state, config, list(settings), run_dir), dataset))
    check_members(run_dirs, [config for _, config, _ in loaded], [dataset for _, _, dataset in loaded])
    names = [f"members/{k}-{config.name}" for k, (_, config, _) in enumerate(loaded)]
    shutil.rmtree(out / "members", ignore_errors=True)  # members of an ensemble exported here before
    paths = [_write(run_dir, out / name, *run) for run_dir, name, run in zip(run_dirs, names, loaded, strict=True)]
    for name in ("config.yaml", "dataset.json"):
        with atomic_path(out / name) as tmp:
            tmp.write_text((out / names[0] / name).read_text())
    shutil.rmtree(out / "checkpoints", ignore_errors=True)  # a single model exported here before
    (out / "metrics.csv").unlink(missing_ok=True)
    with atomic_path(out / ENSEMBLE_FILE) as tmp:
        tmp.write_text("# the members of this ensemble, averaged frame by frame (bsms.ensemble)\n"
                       + yaml.safe_dump({"members": names}, sort_keys=False))
    return paths


def main(argv=None, prog: str = "python -m bsms.pretrained") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", metavar="RUN",
                        help="the trained run folder (several: an ensemble of them)")
    parser.add_argument("out", type=Path, help="the pretrained folder to write, e.g. pretrained/press2d")
    parser.add_argument("--which", default="best", choices=("best", "latest"), help="checkpoint (default best)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                        help=f"change a config key of how the weights answer (repeatable): {', '.join(SETTABLE)}")
    args = parser.parse_args(argv)
    try:
        settings = parse_settings(args.settings)
        if len(args.runs) == 1:
            paths = [export(args.runs[0], args.out, args.which, settings)]
        else:
            paths = export_ensemble(args.runs, args.out, args.which, settings)
    except (CheckpointError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    members = f", an ensemble of {len(paths)}" if len(paths) > 1 else ""
    print(f"wrote {args.out} ({sum(p.stat().st_size for p in paths) / 2**20:.2f} MB of weights{members})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
