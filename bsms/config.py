"""Typed configs: YAML (safe-loaded) or dicts into dataclasses, validated, with dotted overrides.

:func:`build` turns a nested mapping into a dataclass tree. Every field is checked against its
annotation (bool, int, float, str, Literal choices, Optional, lists, mappings, nested dataclasses);
unknown keys and bad values raise one :class:`ConfigError` that names the dotted key and
what it expects; a key retired from a section (:class:`Retired`) is dropped where its value is what
the code does now (a saved run's config lists every key) and is one error naming it otherwise.
:func:`apply_overrides` applies command-line ``section.key=value`` strings, each value parsed as
YAML (``optim.lr=3e-4``, ``train.steps=2000``, ``model.name=meshgraphnets``).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import types
import typing
from typing import Any, Literal, Union, get_args, get_origin

import yaml

from datagen.config import ConfigError, Retired, read_yaml, reject_unknown, without_retired

# ConfigError is the one error of every config in the project (datasets, scenes, training runs);
# Retired and without_retired handle the keys retired from one (datagen.config).
__all__ = ["ConfigError", "Retired", "build", "without_retired", "load", "apply_overrides", "to_dict", "at_least"]


def _type_name(annotation) -> str:
    origin = get_origin(annotation)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(annotation))
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(annotation))
    if origin is list:
        return f"a list of {_type_name(get_args(annotation)[0])}"
    if origin is dict:
        return f"a mapping of names to {_type_name(get_args(annotation)[1])}"
    if annotation is type(None):
        return "null"
    if dataclasses.is_dataclass(annotation):
        return "a mapping"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        annotation, getattr(annotation, "__name__", str(annotation))
    )


def _convert(value, annotation, key: str):
    """``value`` checked against (and coerced to) ``annotation``; raises ConfigError naming ``key``."""
    origin = get_origin(annotation)
    if dataclasses.is_dataclass(annotation):
        return build(annotation, value, prefix=key)
    if origin in (Union, types.UnionType):
        for option in get_args(annotation):
            try:
                return _convert(value, option, key)
            except ConfigError:
                continue
    elif origin is Literal:
        if value in get_args(annotation):
            return value
    elif origin is list:
        if isinstance(value, (list, tuple)):
            return [_convert(item, get_args(annotation)[0], f"{key}[{i}]") for i, item in enumerate(value)]
    elif origin is dict:
        if isinstance(value, dict):
            names, values = get_args(annotation)
            return {_convert(k, names, key): _convert(v, values, f"{key}.{k}") for k, v in value.items()}
    elif annotation is type(None):
        if value is None:
            return None
    elif annotation is bool:
        if isinstance(value, bool):
            return value
    elif annotation is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif annotation is float:
        if isinstance(value, str):  # YAML 1.1 reads 3e-4 (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
    elif annotation is str:
        if isinstance(value, str):
            return value
    elif annotation is Any:
        return value
    raise ConfigError(f"config key '{key}' must be {_type_name(annotation)}, got {value!r}")


def build(cls, data, prefix: str = ""):
    """An instance of dataclass ``cls`` from the mapping ``data`` (missing keys take defaults).

    Keys retired from ``cls`` (its ``RETIRED`` class attribute) are checked and dropped first
    (:func:`~datagen.config.without_retired`). After
    construction, a ``validate()`` method on the dataclass (if any) may raise ConfigError for
    constraints between fields; it gets the dotted prefix.
    """
    where = f"'{prefix}'" if prefix else "the config"
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a mapping of keys to values, got {data!r}")
    data = without_retired(getattr(cls, "RETIRED", {}), data, prefix)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    reject_unknown(data, fields, prefix=prefix, where=where)
    values = {}
    for name, field in fields.items():
        key = f"{prefix}.{name}" if prefix else name
        if name in data:
            values[name] = _convert(data[name], hints[name], key)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ConfigError(f"config key '{key}' is required ({_type_name(hints[name])})")
    instance = cls(**values)
    if hasattr(instance, "validate"):
        instance.validate(prefix)
    return instance


def load(path) -> dict:
    """Mapping from a YAML file, read with ``yaml.safe_load`` (no file can execute code); an
    ``extends: PARENT`` key merges the file over PARENT (:func:`datagen.config.read_yaml`)."""
    return read_yaml(path, what="config file")


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """A copy of ``data`` with each ``dotted.key=value`` applied (value parsed as YAML)."""
    data = copy.deepcopy(data)
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key or any(not part for part in key.split(".")):
            raise ConfigError(f"override {item!r} must look like section.key=value")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {item!r}: the value is not valid YAML: {exc}") from None
        node = data
        parts = key.split(".")
        for depth, part in enumerate(parts[:-1]):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigError(f"override {item!r}: '{'.'.join(parts[: depth + 1])}' is not a section")
            node = child
        node[parts[-1]] = value
    return data


def to_dict(instance) -> dict:
    """Plain nested dict of a config dataclass (YAML-ready)."""
    return dataclasses.asdict(instance)


def at_least(section, prefix: str, lowest: int, keys, optional: bool = False) -> None:
    """ConfigError naming the first of ``keys`` below ``lowest`` (None passes when ``optional``)."""
    for key in keys:
        value = getattr(section, key)
        if value is None and optional:
            continue
        if value < lowest:
            allowed = f">= {lowest}" + (" or null" if optional else "")
            raise ConfigError(f"config key '{prefix}.{key}' must be {allowed}, got {value}")
