"""Reading what a user wrote: the one error for a bad configuration and the known-keys check.

Config files are YAML; :func:`read_yaml` resolves ``extends`` (a config, by relative path,
that this one overrides). Every configuration a person writes (a simulation config, scene parameters, a dataset's
ranges, a training run) goes through :func:`reject_unknown`, so a misspelt key gets the same
message everywhere: the dotted key and what the place accepts. A key retired from a place
(:class:`Retired`, an experiment measured and not adopted: docs/experiments.md) goes through
:func:`without_retired`: dropped where its value asks for what the code does now (the saved configs
of earlier runs list every key), else one error that names it and the commit that has it.
"""

from __future__ import annotations

import copy
import tempfile
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["ConfigError", "Retired", "reject_unknown", "without_retired", "section", "read_yaml", "merge",
           "output_folder"]


class ConfigError(ValueError):
    """A configuration a user wrote that cannot be used; the message names the key."""


def reject_unknown(given: Mapping, known: Iterable[str], *, prefix: str = "", where: str = "the config") -> None:
    """Raise :class:`ConfigError` naming the first key of ``given`` (sorted) not in ``known``.

    ``prefix`` is the dotted path of ``given`` inside the whole config ('' at the top level);
    ``where`` says in words what accepts the keys ("scene 'droplet'", "'optim'").
    Message: ``unknown config key 'PREFIX.KEY'; WHERE accepts: A, B, C``.
    """
    known = set(known)
    unknown = sorted(str(key) for key in set(given) - known)
    if unknown:
        name = f"{prefix}.{unknown[0]}" if prefix else unknown[0]
        raise ConfigError(f"unknown config key '{name}'; {where} accepts: {', '.join(sorted(known))}")


@dataclass(frozen=True)
class Retired:
    """A config key retired from the place that accepted it: an experiment measured and not adopted
    (docs/experiments.md).

    what: what the key did, in a few words; now: the value whose behaviour the code keeps, in
    words; commit: the commit that last has the key (``git checkout`` brings it back); keeps:
    ``keeps(value, section)`` is true where ``value``, given in the ``section`` mapping, asks for
    what the code does now -- such a key is dropped, so that the saved configs of earlier runs,
    which list every key, still load."""

    what: str
    now: str
    commit: str
    keeps: Callable[[Any, Mapping], bool]


def without_retired(retired: Mapping[str, Retired], given: Mapping, prefix: str = "") -> dict:
    """``given`` less the keys of ``retired``, each checked: a value that asks for anything but what
    the code does now is a ConfigError that names the dotted key (``prefix``: the dotted path of
    ``given``), says it was retired, and gives the commit that has it."""
    for name in sorted(set(given) & set(retired)):
        entry = retired[name]
        if not entry.keeps(given[name], given):
            import yaml

            key = f"{prefix}.{name}" if prefix else name
            value = yaml.safe_dump(given[name], default_flow_style=True).strip().removesuffix("...").strip()
            raise ConfigError(f"config key '{key}' is retired ({entry.what}: measured and not adopted, "
                              f"docs/experiments.md); got {value}: leave it out (this version always does what "
                              f"{entry.now} did), or use the commit that has it: git checkout {entry.commit}")
    return {key: value for key, value in given.items() if key not in retired}


def section(config: Mapping, name: str, defaults: Mapping, where: str | None = None) -> dict:
    """Section ``name`` of ``config`` over its ``defaults``: ConfigError where it is not a
    mapping or holds a key the defaults do not (``where``: what accepts the keys, in words;
    default the section's own name)."""
    given = config.get(name) or {}
    if not isinstance(given, Mapping):
        raise ConfigError(f"config key '{name}' must be a mapping, got {given!r}")
    reject_unknown(given, defaults, prefix=name, where=where or f"'{name}'")
    return {**defaults, **given}


def merge(base: Mapping, over: Mapping) -> dict:
    """``over`` on top of ``base``: mappings merge key by key, anything else is replaced."""
    out = copy.deepcopy(dict(base))
    for key, value in over.items():
        nested = isinstance(value, Mapping) and isinstance(out.get(key), Mapping)
        out[key] = merge(out[key], value) if nested else copy.deepcopy(value)
    return out


def read_yaml(path, *, what: str = "config", replace: Iterable[str] = (), _chain: tuple = ()) -> dict:
    """The mapping in YAML file ``path``, with ``extends: PARENT`` resolved.

    PARENT is a path relative to ``path``'s folder; this file's keys merge over the parent's
    (:func:`merge`), except the top-level keys named in ``replace``, which this file's value
    replaces whole. ``what`` names the file in errors ("dataset config").
    """
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{what} {path} does not exist")
    if path.resolve() in _chain:
        raise ConfigError(f"{what} {path}: 'extends' forms a cycle")
    try:
        with open(path) as fh:
            config = yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{what} {path} is not valid YAML: {exc}") from None
    if not isinstance(config, dict):
        raise ConfigError(f"{what} {path} must hold a mapping of keys to values, got {type(config).__name__}")
    parent = config.pop("extends", None)
    if parent is None:
        return config
    if not isinstance(parent, str):
        raise ConfigError(f"{what} {path}: 'extends' must be a file path, got {parent!r}")
    base = read_yaml(path.parent / parent, what=what, replace=replace, _chain=(*_chain, path.resolve()))
    merged = merge(base, config)
    for key in replace:
        if key in config:
            merged[key] = config[key]
    return merged


def output_folder(path, key: str) -> Path:
    """Folder ``path``, created with its parents when missing, once a file could be written in it.

    ``key`` names where the user gave it (``--out``, ``runs``). Raises ConfigError before any
    work starts when part of the path is a file or the folder cannot be written to.
    """
    path = Path(path).expanduser()
    for existing in (path, *path.parents):
        if existing.exists():
            if not existing.is_dir():
                raise ConfigError(f"{key} {path}: {existing} is a file, not a folder; give a folder path")
            break
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise ConfigError(f"{key} {path}: cannot write there ({exc.strerror or exc}); give a folder you can "
                          "write to") from None
    return path
