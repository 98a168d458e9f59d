"""Sampling helpers shared by the dataset families.

A range value in a config is either a fixed value or ``[low, high]``; choices are lists.
Every helper names the offending ``ranges.<key>`` when a value cannot be used.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ..config import ConfigError, Retired, reject_unknown, without_retired

__all__ = [
    "check_ranges", "uniform", "log_uniform", "integer", "choice", "place_disjoint", "midpoint", "log_midpoint",
]


def check_ranges(family: str, defaults: dict, given: dict, retired: Mapping[str, Retired] | None = None) -> dict:
    """``given`` merged over ``defaults``; unknown keys raise ConfigError naming the known ones, keys
    ``retired`` from the family one naming the key (:func:`datagen.config.without_retired`)."""
    if not isinstance(given, dict):
        raise ConfigError(f"config key 'ranges' must be a mapping of {family} ranges, got {given!r}")
    given = without_retired(retired or {}, given, "ranges")
    reject_unknown(given, defaults, prefix="ranges", where=f"family {family!r}")
    return {**defaults, **given}


def _bounds(ranges: dict, key: str) -> tuple[float, float]:
    value = ranges[key]
    pair = value if isinstance(value, (list, tuple)) else [value, value]
    ok = len(pair) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pair)
    if not ok or not all(math.isfinite(v) for v in pair) or pair[0] > pair[1]:
        raise ConfigError(f"ranges.{key} must be a number or [low, high] with low <= high, got {value!r}")
    return float(pair[0]), float(pair[1])


def uniform(ranges: dict, key: str, rng: np.random.Generator) -> float:
    low, high = _bounds(ranges, key)
    return float(rng.uniform(low, high))


def log_uniform(ranges: dict, key: str, rng: np.random.Generator) -> float:
    """Uniform in log scale (for stiffnesses spanning decades)."""
    low, high = _bounds(ranges, key)
    if low <= 0:
        raise ConfigError(f"ranges.{key} must be positive (it is sampled in log scale), got {ranges[key]!r}")
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def midpoint(ranges: dict, key: str) -> float:
    """The middle of a uniform range (the value itself when fixed)."""
    low, high = _bounds(ranges, key)
    return 0.5 * (low + high)


def log_midpoint(ranges: dict, key: str) -> float:
    """The middle in log scale (geometric mean) of a range sampled by :func:`log_uniform`."""
    low, high = _bounds(ranges, key)
    if low <= 0:
        raise ConfigError(f"ranges.{key} must be positive (it is sampled in log scale), got {ranges[key]!r}")
    return math.sqrt(low * high)


def integer(ranges: dict, key: str, rng: np.random.Generator, minimum: int = 1) -> int:
    """An integer in [low, high], both included; ``minimum`` is the smallest a range may hold."""
    low, high = _bounds(ranges, key)
    if low != int(low) or high != int(high):
        raise ConfigError(f"ranges.{key} must hold integers, got {ranges[key]!r}")
    if low < minimum:
        raise ConfigError(f"ranges.{key} must be at least {minimum}, got {ranges[key]!r}")
    return int(rng.integers(int(low), int(high) + 1))


def choice(ranges: dict, key: str, rng: np.random.Generator):
    options = ranges[key]
    if not isinstance(options, (list, tuple)) or not options:
        raise ConfigError(f"ranges.{key} must be a non-empty list of choices, got {options!r}")
    return options[int(rng.integers(len(options)))]


def place_disjoint(radii: list[float], lower, upper, gap: float, rng: np.random.Generator,
                   key: str, tries: int = 200) -> np.ndarray:
    """(n, 2) centres of circles of ``radii`` inside the box, ``gap`` apart from each other and the walls."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    for _ in range(tries):
        centers = []
        for r in radii:
            lo, hi = lower + r + gap, upper - r - gap
            if np.any(lo > hi):
                break
            c = rng.uniform(lo, hi)
            if all(np.linalg.norm(c - o) >= r + ro + gap for o, ro in zip(centers, radii, strict=False)):
                centers.append(c)
        if len(centers) == len(radii):
            return np.array(centers)
    raise ConfigError(f"ranges.{key}: could not place {len(radii)} bodies of radii {np.round(radii, 3).tolist()} "
                      f"apart inside the box; use a larger box or smaller ranges")


def split_kinds(r: dict, split: str, known, shared_ok: str | None = None) -> list[str]:
    """The kinds ``split`` draws from (``ranges.{split}_kinds``), checked: ``train_kinds``,
    ``test_kinds`` and ``final_kinds`` each a non-empty list of ``known`` kinds, and no kind in two of
    them but ``shared_ok`` (e.g. ``letter``, whose characters differ between splits)."""
    lists = {}
    for key in ("train_kinds", "test_kinds", "final_kinds"):
        kinds = r[key]
        if not isinstance(kinds, (list, tuple)) or not kinds or any(k not in known for k in kinds):
            raise ConfigError(f"ranges.{key} must be a non-empty list of {', '.join(known)}, got {kinds!r}")
        lists[key] = set(kinds)
    for a, b in (("train_kinds", "test_kinds"), ("train_kinds", "final_kinds"), ("test_kinds", "final_kinds")):
        shared = lists[a] & lists[b] - {shared_ok}
        if shared:
            excepted = f" ({shared_ok} excepted: each split draws its own)" if shared_ok else ""
            raise ConfigError(f"ranges.{a} and ranges.{b} share {sorted(shared)}; a kind belongs to one split"
                              + excepted)
    return list(r[f"{split}_kinds"])
