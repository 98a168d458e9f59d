"""Generate a dataset: ``python -m datagen CONFIG [--split S] [--out DIR] [--shard I/N] [--workers W]``.

Trajectory ``index`` of split ``S`` of a dataset config (:mod:`datagen.dataset_config`) is
simulated and written to ``OUT/<dataset>/<S>/<index:05d>.h5`` atomically; complete files are
skipped, so an interrupted run resumes. A trajectory the solver reports unstable
(:class:`~datagen.mpm.errors.SimulationError`) is run again at each of the config's ``retry_cfl``
numbers in turn, then drawn afresh up to ``redraws`` times (its file's config holds what ran); with
none left, the error stands. ``--shard I/N`` keeps every N-th job starting at I (0-based), so N
shards cover every trajectory exactly once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import interrupts
from .config import ConfigError, output_folder
from .dataset import DatasetError, is_complete, save
from .dataset_config import SPLITS, load_dataset_config, trajectory_config, trajectory_path
from .metadata import write_metadata
from .mpm.errors import SimulationError
from .simulation import simulate

__all__ = ["parse_shard", "jobs", "generate", "generate_one", "Summary", "Result", "main"]

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
    trajectory = _simulate_stable(dconfig, split, index)
    save(path, trajectory)
    frames = len(trajectory.times) - 1
    return Result(str(path), False, frames, trajectory.mesh.n_nodes, trajectory.wall_time)


def simulate_retrying(config: dict, retry_cfl=(), errors: list | None = None):
    """``simulate(config)``, then again at each CFL number of ``retry_cfl`` while the solver raises
    SimulationError (each run's config says the CFL number it ran at). Returns the trajectory and
    the retry's CFL number that ran (None: the config's own); raises the last error where every run
    fails. ``errors`` collects each failure's message."""
    tries = [None, *retry_cfl]
    for k, cfl in enumerate(tries):
        run = config if cfl is None else {**config, "solver": {**config.get("solver", {}), "cfl": cfl}}
        try:
            return simulate(run), cfl
        except SimulationError as exc:
            if errors is not None:
                errors.append(str(exc))
            if k == len(tries) - 1:
                raise


def _simulate_stable(dconfig: dict, split: str, index: int):
    """Trajectory ``index`` of ``split`` simulated at the solver's CFL number, then at each of
    ``retry_cfl``; where every one fails, the same again for each of ``redraws`` fresh draws."""
    errors = []
    for draw in range(dconfig.get("redraws", 0) + 1):
        try:
            return simulate_retrying(trajectory_config(dconfig, split, index, draw=draw),
                                     dconfig.get("retry_cfl", []), errors)[0]
        except SimulationError:
            pass
    tried = "" if len(errors) == 1 else f" (the last of {len(errors)} runs)"
    raise SimulationError(f"{split} trajectory {index} of {dconfig['dataset']}{tried}: {errors[-1]}")


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
            interrupts.check()
            results.append(generate_one(dconfig, out, split, index))
            bar.update()
    else:
        from concurrent.futures import ProcessPoolExecutor, as_completed

        pool = ProcessPoolExecutor(max_workers=workers)
        try:
            futures = [pool.submit(generate_one, dconfig, out, s, k) for s, k in todo]
            for future in as_completed(futures):
                results.append(future.result())
                bar.update()
        except BaseException:  # an interrupt or a failed job: the queued jobs never start (the running
            pool.shutdown(wait=True, cancel_futures=True)  # ones finish, their files written atomically)
            raise
        pool.shutdown()
    bar.close()
    return sorted(results, key=lambda r: r.path)


def generate(config, *, out="data", splits=None, shard: tuple[int, int] = (0, 1), workers: int = 1,
             progress: bool = True) -> Summary:
    """Generate this shard's missing trajectories, then metadata.json when the dataset is complete."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"--workers must be a positive integer, got {workers!r}")
    dconfig = load_dataset_config(config)
    output_folder(out, "--out")
    start = time.perf_counter()
    results = _run_jobs(dconfig, out, jobs(dconfig, splits, shard), workers, progress)
    summary = Summary(results, time.perf_counter() - start)
    every = jobs(dconfig)
    if all(trajectory_path(out, dconfig, s, k).exists() for s, k in every):
        write_metadata(Path(out) / dconfig["dataset"], dconfig)
    return summary


def main(argv=None, prog: str = "python -m datagen") -> int:
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
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




if __name__ == "__main__":  # python -m datagen.generate, like python -m datagen
    raise SystemExit(main())
