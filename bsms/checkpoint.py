"""Checkpoints: written atomically, read with ``weights_only=True`` (a file cannot run code).

A checkpoint is a dict of tensors and plain values: ``format``, ``config`` (the run's resolved
config as a mapping), ``dim``, ``step``, ``best_valid``, ``seconds``, ``model`` (state dict,
normalisers included), ``optimizer``, ``scheduler`` and ``rng``.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

from datagen.atomic import atomic_path

__all__ = ["CheckpointError", "save_checkpoint", "load_checkpoint", "load_model", "find_checkpoint"]

FORMAT = 1
_REQUIRED = ("format", "config", "dim", "step", "model")


class CheckpointError(ValueError):
    """A checkpoint or run folder that cannot be used; the message names the file and the fix."""


def save_checkpoint(path, state: dict) -> Path:
    path = Path(path)
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(state, tmp)
    return path


def load_checkpoint(path) -> dict:
    """The checkpoint dict at ``path`` (on CPU), checked; raises CheckpointError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, pickle.UnpicklingError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path} is damaged or not a bsms checkpoint ({str(exc).splitlines()[0]}); "
                              "use another checkpoint of the run or retrain") from None
    if not isinstance(state, dict) or any(key not in state for key in _REQUIRED):
        raise CheckpointError(f"checkpoint {path} is not a bsms checkpoint (it lacks "
                              f"{', '.join(k for k in _REQUIRED if not isinstance(state, dict) or k not in state)})")
    if state["format"] != FORMAT:
        raise CheckpointError(f"checkpoint {path} has format {state['format']}; this bsms reads format {FORMAT}")
    return state


def find_checkpoint(run_dir, which: str = "best") -> Path:
    """``<run_dir>/checkpoints/<which>.pt``, falling back from best to latest."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CheckpointError(f"run folder {run_dir} does not exist; train one with python train.py CONFIG")
    folder = run_dir / "checkpoints"
    order = [which] + (["latest"] if which == "best" else [])
    for name in order:
        if (folder / f"{name}.pt").is_file():
            return folder / f"{name}.pt"
    raise CheckpointError(f"run folder {run_dir} has no usable checkpoint (looked for "
                          f"{', '.join(f'checkpoints/{n}.pt' for n in order)}); train it with python train.py CONFIG "
                          "(or --resume an interrupted run)")


def load_model(source, which: str = "best", device="cpu"):
    """(model in eval mode, Config, checkpoint dict) from a run folder or a checkpoint file."""
    from bsms.config import ConfigError, build
    from bsms.trainer import Config, build_model

    path = Path(source)
    path = path if path.is_file() else find_checkpoint(path, which)
    state = load_checkpoint(path)
    try:
        config = build(Config, state["config"])
    except ConfigError as exc:
        raise CheckpointError(f"checkpoint {path} holds a config this bsms cannot read ({exc})") from None
    model = build_model(config, int(state["dim"]))
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"checkpoint {path}: its weights do not fit its own config ({str(exc)[:200]})") from None
    return model.to(device).eval(), config, state
