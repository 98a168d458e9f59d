"""Ensemble folders: several trained runs that every command taking a run reads as one model.

An ensemble folder (written by ``python -m bsms.pretrained RUN RUN ... OUT``) holds

- ``ensemble.yaml``: ``members``, the member folders (relative to the ensemble folder), each a
  run or pretrained folder of its own;
- ``config.yaml`` and ``dataset.json``: the first member's (the graph recipe and the family's
  scene, which every member shares; ``bsms.infer`` places meshes by them).

:func:`bsms.run.load_model` loads one as an :class:`~bsms.models.ensemble.Ensemble`: the
members' mean. Members must read the same graph (equal ``graph`` options) of the same family's
scene (equal dataset configs up to the dataset's name, seed and split sizes): a member trained
on another setting would be averaged with answers to a question it was never asked.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from bsms.checkpoint import CheckpointError
from bsms.config import to_dict
from bsms.models.ensemble import Ensemble

__all__ = ["ENSEMBLE_FILE", "SCENE_KEYS_IGNORED", "is_ensemble", "member_folders", "check_members",
           "load_ensemble", "spread"]

ENSEMBLE_FILE = "ensemble.yaml"
SCENE_KEYS_IGNORED = ("dataset", "seed", "splits", "redraws")
"""Dataset config entries members may differ in: which trajectories, not what a trajectory is."""


def is_ensemble(folder) -> bool:
    """Whether ``folder`` is an ensemble folder (holds ``ensemble.yaml``)."""
    return (Path(folder) / ENSEMBLE_FILE).is_file()


def member_folders(folder) -> list[Path]:
    """The member folders an ensemble folder lists, resolved against it."""
    folder = Path(folder)
    path = folder / ENSEMBLE_FILE
    try:
        members = (yaml.safe_load(path.read_text()) or {}).get("members")
    except (yaml.YAMLError, AttributeError) as exc:
        raise CheckpointError(f"{path} is not an ensemble file ({' '.join(str(exc).split())[:120]}); write it with "
                              "python -m bsms.pretrained RUN RUN ... OUT") from None
    if not isinstance(members, list) or not members or not all(isinstance(m, str) for m in members):
        raise CheckpointError(f"{path} must list its members' folders under 'members' (a list of paths); write "
                              "it with python -m bsms.pretrained RUN RUN ... OUT")
    folders = [folder / member for member in members]
    for member in folders:
        if not member.is_dir():
            raise CheckpointError(f"{path} lists member {member}, which does not exist")
    return folders


def _differ(a: dict, b: dict) -> list[str]:
    """The keys whose values differ between ``a`` and ``b`` (present in one only counts), sorted."""
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))


def check_members(labels: list, configs: list, scenes: list[dict]) -> None:
    """Raise CheckpointError naming the first member (of ``labels``) whose graph options or scene
    (its dataset config, :data:`SCENE_KEYS_IGNORED` aside) differ from the first member's."""
    def scene_of(dataset: dict) -> dict:
        return {k: v for k, v in dataset.items() if k not in SCENE_KEYS_IGNORED}

    graph0, scene0 = to_dict(configs[0].graph), scene_of(scenes[0])
    for label, config, scene in zip(labels[1:], configs[1:], scenes[1:], strict=True):
        differ = _differ(graph0, to_dict(config.graph))
        if differ:
            raise CheckpointError(f"ensemble member {label} builds another graph than {labels[0]} (graph."
                                  f"{', graph.'.join(differ)}): members must share their graph options")
        differ = _differ(scene0, scene_of(scene))
        if differ:
            raise CheckpointError(f"ensemble member {label} learned another scene than {labels[0]} (dataset "
                                  f"{', '.join(differ)} differ): members must be trained on one family's setting")


def load_ensemble(folder, which: str, device, load_member, scene_of) -> tuple[Ensemble, object, dict]:
    """(Ensemble in eval mode on ``device``, the first member's Config named after every member's
    (``a+b``), its checkpoint dict with ``members``: the member folders) of an ensemble folder.
    ``load_member(folder, which, device)`` loads one member as :func:`bsms.run.load_model` does,
    ``scene_of(folder, config)`` gives its dataset config (:func:`bsms.run.run_dataset_config`)."""
    folders = member_folders(folder)
    loaded = [load_member(member, which, device) for member in folders]
    check_members(folders, [config for _, config, _ in loaded],
                  [scene_of(member, config) for member, (_, config, _) in zip(folders, loaded, strict=True)])
    try:
        model = Ensemble([m for m, _, _ in loaded])
    except ValueError as exc:
        raise CheckpointError(f"ensemble {folder}: {exc}") from None
    state = {**loaded[0][2], "members": [str(member) for member in folders]}
    config = replace(loaded[0][1], name="+".join(config.name for _, config, _ in loaded))
    return model.to(device).eval(), config, state


def spread(positions: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, float]:
    """How far an ensemble's members disagree: of their positions ``positions`` (K, T, N, d), per
    node and frame the root mean square distance from their mean (T, N), and its root mean
    square over the ``free`` nodes (N,) and the frames after the first (a length: divide by the
    body size as :func:`bsms.rollouts.rollout.rollout_metrics` divides the error)."""
    per_node = np.sqrt(np.mean(np.sum((positions - positions.mean(axis=0)) ** 2, axis=-1), axis=0))
    return per_node, float(np.sqrt(np.mean(per_node[1:][:, free] ** 2)))
