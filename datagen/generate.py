"""Generate a dataset: ``python -m datagen CONFIG [--split S] [--out DIR] [--shard I/N] [--workers W]``.

A dataset config (YAML) names a family from :mod:`datagen.families` and how to sample it::

    dataset: disks            # folder name under --out
    family: disks
    seed: 0
    splits: {train: 100, valid: 10, test: 10}
    ranges: {radius: [0.12, 0.2]}      # family ranges (defaults: the family's RANGES)
    params: {body_size: 0.03}          # fixed scene parameters
    solver: {threads: 1}               # as in datagen.simulation
    output: {frames: 40, frame_interval: 0.1}
    extends: disks.yaml                # optional: a config (relative path) this one overrides;
                                       # mappings merge key by key, except splits (replaced)

Trajectory ``index`` of split ``S`` is simulated from ``family.sample(ranges, rng, S)`` with
``rng = numpy.random.default_rng([seed, split number, index])`` and written to
``OUT/<dataset>/<S>/<index:05d>.h5`` atomically; complete files are skipped, so an
interrupted run resumes. ``--shard I/N`` keeps every N-th job starting at I (0-based), so N
shards cover every trajectory exactly once.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .dataset import DatasetError, is_complete, save
from .families import get_family
from .scenes import ConfigError
from .simulation import resolve_config, simulate

__all__ = [
    "load_dataset_config", "trajectory_config", "parse_shard", "jobs", "generate", "generate_one", "trajectory_path",
    "Summary", "Result", "SPLITS", "main",
]

SPLITS = ("train", "valid", "test")
TOP_LEVEL = {"dataset", "family", "seed", "splits", "ranges", "params", "solver", "output", "extends"}


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in over.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _read_yaml(path: Path, chain: tuple = ()) -> dict:
    import yaml

    if not path.is_file():
        raise ConfigError(f"dataset config {path} does not exist")
    if path.resolve() in chain:
        raise ConfigError(f"dataset config {path}: 'extends' forms a cycle")
    with open(path) as fh:
        config = yaml.safe_load(fh)
    if not isinstance(config, dict):
        raise ConfigError(f"dataset config {path} must hold a mapping")
    parent = config.pop("extends", None)
    if parent is None:
        return config
    merged = _merge(_read_yaml(path.parent / parent, (*chain, path.resolve())), config)
    if "splits" in config:  # a variant's splits replace the parent's rather than add to them
        merged["splits"] = config["splits"]
    return merged


def load_dataset_config(config) -> dict:
    """A checked dataset config from a YAML path or a dict (``extends`` resolved)."""
    config = _read_yaml(Path(config)) if isinstance(config, (str, Path)) else copy.deepcopy(config)
    unknown = sorted(set(config) - TOP_LEVEL)
    if unknown:
        raise ConfigError(f"unknown dataset config key '{unknown[0]}'; known keys: {', '.join(sorted(TOP_LEVEL))}")
    for key in ("dataset", "family", "splits"):
        if key not in config:
            raise ConfigError(f"dataset config key '{key}' is missing")
    if not isinstance(config["dataset"], str) or not config["dataset"] or "/" in config["dataset"]:
        raise ConfigError(f"dataset config key 'dataset' must be a folder name, got {config['dataset']!r}")
    family = get_family(config["family"])
    splits = config["splits"]
    if not isinstance(splits, dict) or set(splits) - set(SPLITS):
        raise ConfigError(f"dataset config key 'splits' must map some of {', '.join(SPLITS)} to counts, got {splits!r}")
    for name, count in splits.items():
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ConfigError(f"dataset config key 'splits.{name}' must be a count >= 0, got {count!r}")
    seed = config.setdefault("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"dataset config key 'seed' must be an integer >= 0, got {seed!r}")
    for key in ("ranges", "params", "solver", "output"):
        config[key] = config.get(key) or {}
    resolve_config(trajectory_config(config, next(iter(splits), "train"), 0, family=family))  # fail early
    return config


def trajectory_config(dconfig: dict, split: str, index: int, *, family=None) -> dict:
    """The simulate() config of trajectory ``index`` of ``split``; depends on nothing else."""
    family = family or get_family(dconfig["family"])
    rng = np.random.default_rng([dconfig["seed"], SPLITS.index(split), index])
    sampled = family.sample(dconfig["ranges"], rng, split)
    return {
        "scene": family.SCENE, "params": {**dconfig["params"], **sampled}, "solver": dict(dconfig["solver"]),
        "output": dict(dconfig["output"]), "seed": int(rng.integers(2**31)),
    }


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` -> (I, N) with 0 <= I < N."""
    try:
        i, n = (int(part) for part in str(text).split("/"))
    except ValueError:
        raise ConfigError(f"--shard must look like I/N (e.g. 0/4), got {text!r}") from None
    if not 0 <= i < n:
        raise ConfigError(f"--shard {text}: need 0 <= I < N (shards are numbered 0 to N-1)")
    return i, n


def jobs(dconfig: dict, splits=None, shard: tuple[int, int] = (0, 1)) -> list[tuple[str, int]]:
    """The (split, index) pairs of this shard: every N-th of all jobs in split order, from I."""
    chosen = list(dconfig["splits"]) if splits is None else list(splits)
    for name in chosen:
        if name not in dconfig["splits"]:
            raise ConfigError(f"--split {name!r} is not in the config's splits ({', '.join(dconfig['splits'])})")
    every = [(s, k) for s in SPLITS if s in chosen for k in range(dconfig["splits"][s])]
    return every[shard[0]::shard[1]]


def trajectory_path(out, dconfig: dict, split: str, index: int) -> Path:
    return Path(out) / dconfig["dataset"] / split / f"{index:05d}.h5"


@dataclass
class Result:
    """One job's outcome: skipped (already complete) or generated with its sizes and solver time."""

    path: str
    skipped: bool
    frames: int = 0
    nodes: int = 0
    solver_seconds: float = 0.0


def generate_one(dconfig: dict, out, split: str, index: int) -> Result:
    """Simulate and save one trajectory unless its file is already complete."""
    path = trajectory_path(out, dconfig, split, index)
    if path.exists() and is_complete(path):
        return Result(str(path), True)
    for stale in path.parent.glob(f".{path.stem}.*.tmp"):  # left by a killed run of this job
        stale.unlink(missing_ok=True)
    trajectory = simulate(trajectory_config(dconfig, split, index))
    save(path, trajectory)
    frames = len(trajectory.times) - 1
    return Result(str(path), False, frames, trajectory.mesh.n_nodes, trajectory.wall_time)


@dataclass
class Summary:
    """What a run did: results per job and its wall time."""

    results: list[Result] = field(default_factory=list)
    seconds: float = 0.0

    def describe(self) -> str:
        made = [r for r in self.results if not r.skipped]
        frames = sum(r.frames for r in made)
        lines = [f"{len(made)} trajectories generated, {len(self.results) - len(made)} already complete "
                 f"({self.seconds:.1f} s)"]
        if made:
            nodes = [r.nodes for r in made]
            per_frame = sum(r.solver_seconds for r in made) / max(frames, 1)
            lines.append(f"{frames} frames; nodes per mesh {min(nodes)}-{max(nodes)} (mean {np.mean(nodes):.0f}); "
                         f"solver {per_frame * 1e3:.1f} ms per frame")
        return "\n".join(lines)


def _run_jobs(dconfig, out, todo, workers: int, progress: bool) -> list[Result]:
    from tqdm import tqdm

    bar = tqdm(total=len(todo), desc=dconfig["dataset"], unit="traj", disable=not progress)
    results = []
    if workers <= 1:
        for split, index in todo:
            results.append(generate_one(dconfig, out, split, index))
            bar.update()
    else:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(generate_one, dconfig, out, s, k) for s, k in todo]
            for future in as_completed(futures):
                results.append(future.result())
                bar.update()
    bar.close()
    return sorted(results, key=lambda r: r.path)


def generate(config, *, out="data", splits=None, shard: tuple[int, int] = (0, 1), workers: int = 1,
             progress: bool = True) -> Summary:
    """Generate this shard's missing trajectories, then metadata.json when the dataset is complete."""
    from .metadata import write_metadata

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"--workers must be a positive integer, got {workers!r}")
    dconfig = load_dataset_config(config)
    start = time.perf_counter()
    results = _run_jobs(dconfig, out, jobs(dconfig, splits, shard), workers, progress)
    summary = Summary(results, time.perf_counter() - start)
    every = jobs(dconfig)
    if all(trajectory_path(out, dconfig, s, k).exists() for s, k in every):
        write_metadata(Path(out) / dconfig["dataset"], dconfig)
    return summary


def main(argv=None) -> int:
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog="python -m datagen", description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="dataset config YAML, e.g. configs/datasets/disks_quick.yaml")
    parser.add_argument("--split", action="append", choices=SPLITS, help="only this split (repeatable)")
    parser.add_argument("--out", default="data", help="root folder of datasets (default: data)")
    parser.add_argument("--shard", default="0/1", help="I/N: generate every N-th trajectory from I")
    parser.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        summary = generate(args.config, out=args.out, splits=args.split, shard=parse_shard(args.shard),
                           workers=args.workers, progress=not args.quiet)
    except (ConfigError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(summary.describe())
    return 0


