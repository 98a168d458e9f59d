"""Checkpoint files: written atomically, read with ``weights_only=True`` (a file cannot run code).

A checkpoint is a dict of tensors and plain values: ``format``, ``config`` (the run's resolved
config as a mapping), ``dim``, ``step``, ``best_valid``, ``seconds``, ``model`` (state dict,
normalisers included), ``optimizer``, ``scheduler`` and ``rng``. Where a run keeps its
checkpoints, and how a model is rebuilt from one, is :mod:`bsms.run`'s business.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

from datagen.atomic import atomic_path

__all__ = ["CheckpointError", "FORMAT", "save_checkpoint", "load_checkpoint"]

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
