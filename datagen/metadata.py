"""``metadata.json`` of a dataset folder: dim, frame dt, counts, bounds, node counts, feature statistics.

Bounds hold every body position of every frame and the obstacle nodes (where obstacles move,
their positions at every frame).

Statistics of velocities and of per-frame velocity changes are per component (mean, std)
over every node of every frame of the train split (all splits when there is no train split).
Written atomically (temporary name, then rename).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .dataset import FORMAT_VERSION, DatasetError, load

__all__ = ["dataset_metadata", "write_metadata"]


class _Moments:
    """Running per-component count, sum and sum of squares."""

    def __init__(self):
        self.n, self.s, self.ss = 0, 0.0, 0.0

    def add(self, values: np.ndarray) -> None:
        flat = values.reshape(-1, values.shape[-1])
        self.n += len(flat)
        self.s = self.s + flat.sum(0)
        self.ss = self.ss + (flat**2).sum(0)

    def result(self) -> dict:
        mean = self.s / max(self.n, 1)
        std = np.sqrt(np.maximum(self.ss / max(self.n, 1) - mean**2, 0.0))
        return {"mean": np.atleast_1d(mean).tolist(), "std": np.atleast_1d(std).tolist()}


def _split_files(root: Path, splits) -> dict[str, list[Path]]:
    return {s: sorted((root / s).glob("*.h5")) for s in splits if (root / s).is_dir()}


def dataset_metadata(root, dconfig: dict) -> dict:
    """The metadata of the dataset folder ``root`` generated from ``dconfig`` (reads every file)."""
    root = Path(root)
    files = _split_files(root, dconfig["splits"])
    stats_split = "train" if files.get("train") else None
    velocity, change = _Moments(), _Moments()
    lower, upper, frame_dts, dims, nodes = None, None, set(), set(), {}
    for split, paths in files.items():
        nodes[split] = []
        for path in paths:
            t = load(path)
            nodes[split].append(int(t.mesh.n_nodes))
            dims.add(int(t.mesh.dim))
            frame_dts.add(round(float(np.diff(t.times).mean()), 12))
            obstacles = t.obstacle_nodes if t.obstacle_positions is None else t.obstacle_positions
            points = np.concatenate([t.positions.reshape(-1, t.mesh.dim), obstacles.reshape(-1, t.mesh.dim)])
            lower = points.min(0) if lower is None else np.minimum(lower, points.min(0))
            upper = points.max(0) if upper is None else np.maximum(upper, points.max(0))
            if stats_split in (None, split):
                velocity.add(t.velocities)
                change.add(np.diff(t.velocities, axis=0))
    if len(dims) != 1 or len(frame_dts) != 1:
        raise DatasetError(f"dataset {root} mixes dimensions {sorted(dims)} or frame intervals {sorted(frame_dts)}; "
                           "regenerate it from one config")
    return {
        "format_version": FORMAT_VERSION, "dataset": dconfig["dataset"], "family": dconfig["family"],
        "dim": dims.pop(), "dt": frame_dts.pop(), "counts": {s: len(p) for s, p in files.items()},
        "bounds": {"lower": lower.tolist(), "upper": upper.tolist()},
        "nodes": {s: {"min": min(n), "max": max(n), "mean": float(np.mean(n))} for s, n in nodes.items() if n},
        "statistics_split": stats_split or "all",
        "velocity": velocity.result(), "velocity_change": change.result(), "config": dconfig,
    }


def write_metadata(root, dconfig: dict) -> Path:
    """Compute and write ``root/metadata.json`` atomically; returns its path."""
    root = Path(root)
    text = json.dumps(dataset_metadata(root, dconfig), indent=2, sort_keys=True)
    path = root / "metadata.json"
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")
    return path
