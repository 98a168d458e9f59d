"""Dataset configs: what a dataset is and which scene config each of its trajectories gets.

A dataset config (YAML, or the same keys as a dict) names a family from
:mod:`datagen.families` and how to sample it::

    dataset: disks            # folder name under the output root
    family: disks
    seed: 0
    splits: {train: 100, valid: 10, test: 10}
    ranges: {radius: [0.12, 0.2]}      # family ranges (defaults: the family's RANGES)
    params: {body_size: 0.03}          # fixed scene parameters
    solver: {threads: 1}               # as in datagen.simulation
    output: {frames: 40, frame_interval: 0.1}
    extends: disks.yaml                # optional: a config (relative path) this one overrides;
                                       # mappings merge key by key, except splits (replaced)
    retry_cfl: [0.5]                   # optional: a trajectory the solver reports unstable is run
                                       # again at these smaller CFL numbers, in order
    redraws: 1                         # optional: then drawn afresh up to this many times

Trajectory ``index`` of split ``S`` is simulated from ``family.sample(ranges, rng, S)`` with
``rng = numpy.random.default_rng([seed, split number, index])`` (:func:`trajectory_config`)
(redraw ``k`` of it: ``[seed, split number, index, k]``) and lives at
``ROOT/<dataset>/<S>/<index:05d>.h5`` (:func:`trajectory_path`).

Splits: ``train`` and ``valid`` (the kinds a model learns; decisions such as checkpoints and
recipes use ``valid``), ``test`` (kinds training never saw) and ``final``: a held-out split
evaluated once per published model after its recipe is fixed. A family that defines ``FINAL``
draws it its own way (new draws of the test kinds plus shapes of no kind in training); any other
family draws it as its test split, from a random stream of its own (new draws).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from .config import ConfigError, read_yaml, reject_unknown
from .families import get_family
from .simulation import SOLVER_DEFAULTS, resolve_config

__all__ = ["SPLITS", "load_dataset_config", "trajectory_config", "trajectory_path"]

SPLITS = ("train", "valid", "test", "final")
TOP_LEVEL = {"dataset", "family", "seed", "splits", "ranges", "params", "solver", "output", "retry_cfl", "redraws"}


def load_dataset_config(config) -> dict:
    """A checked dataset config from a YAML path or a dict (``extends`` resolved)."""
    if isinstance(config, (str, Path)):
        config = read_yaml(config, what="dataset config", replace=("splits",))
    elif isinstance(config, dict):
        config = copy.deepcopy(config)
    else:
        raise ConfigError(f"a dataset config must be a mapping or a YAML file path, got {type(config).__name__}")
    reject_unknown(config, TOP_LEVEL, where="a dataset config")
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
    if "retry_cfl" in config:
        config["retry_cfl"] = _retry_cfl(config)
    redraws = config.get("redraws", 0)
    if isinstance(redraws, bool) or not isinstance(redraws, int) or redraws < 0:
        raise ConfigError(f"dataset config key 'redraws' must be an integer >= 0 (how many times a trajectory the "
                          f"solver cannot run is drawn afresh), got {redraws!r}")
    resolve_config(trajectory_config(config, next(iter(splits), "train"), 0, family=family))  # fail early
    return config


def _retry_cfl(config: dict) -> list[float]:
    """The checked ``retry_cfl``: CFL numbers in (0, 1], each smaller than the one before it and than
    the solver's own ``cfl``."""
    given = config["retry_cfl"]
    first = config["solver"].get("cfl", SOLVER_DEFAULTS["cfl"])  # the CFL number the first run uses
    fix = f"give CFL numbers in (0, 1], each smaller than the one before and than solver.cfl ({first})"
    if not isinstance(given, list) or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in given):
        raise ConfigError(f"dataset config key 'retry_cfl' must be a list of numbers, got {given!r}: {fix}")
    for before, cfl in zip([first, *given], given, strict=False):
        if not 0 < cfl < before:
            raise ConfigError(f"dataset config key 'retry_cfl' = {given!r} has {cfl} after {before}: {fix}")
    return [float(c) for c in given]


def trajectory_config(dconfig: dict, split: str, index: int, *, family=None, draw: int = 0) -> dict:
    """The simulate() config of trajectory ``index`` of ``split`` (``draw`` > 0: its redraw of that
    number); depends on nothing else."""
    family = family or get_family(dconfig["family"])
    key = [dconfig["seed"], SPLITS.index(split), index] + ([draw] if draw else [])
    rng = np.random.default_rng(key)
    drawn_as = split if split != "final" or getattr(family, "FINAL", False) else "test"
    sampled = family.sample(dconfig["ranges"], rng, drawn_as)
    return {
        "scene": family.SCENE, "params": {**dconfig["params"], **sampled}, "solver": dict(dconfig["solver"]),
        "output": dict(dconfig["output"]), "seed": int(rng.integers(2**31)),
    }


def trajectory_path(out, dconfig: dict, split: str, index: int) -> Path:
    """Where trajectory ``index`` of ``split`` lives under the datasets root ``out``."""
    return Path(out) / dconfig["dataset"] / split / f"{index:05d}.h5"
