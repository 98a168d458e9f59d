"""Dataset families: randomized scenes for training data.

Each module has NAME, SCENE (the datagen.scenes scene it samples), DIM, CONTACT, OBSTACLES,
CLAMPED (what the scene has), RANGES (default parameter ranges) and
``sample(ranges, rng, split) -> params`` for that scene. The same ranges and generator state
give the same parameters. ``place(meshes, dconfig, overrides)`` puts any body meshes into the
family's setting for zero-shot tests (a ``datagen.simulate`` config of the ``bodies`` scene),
or raises ConfigError where the family has no room for a foreign body.
"""

from __future__ import annotations

from ..config import ConfigError
from . import balls, bracket, cantilever, disks, glyphs, pendulum, press, press3d, shock_channel, wavy_channel

__all__ = ["FAMILIES", "get_family", "place"]

FAMILIES = {module.NAME: module
            for module in (wavy_channel, disks, cantilever, glyphs, balls, press, bracket, shock_channel, press3d,
                           pendulum)}


def get_family(name):
    """The family module registered as ``name``; ConfigError naming the choices otherwise."""
    if not isinstance(name, str) or name not in FAMILIES:
        raise ConfigError(f"unknown family {name!r} (config key 'family'); choose one of {', '.join(sorted(FAMILIES))}")
    return FAMILIES[name]


def place(family_name: str, meshes, dconfig, overrides: dict | None = None) -> dict:
    """A ``datagen.simulate`` config putting ``meshes`` (Mesh objects or file paths) into family
    ``family_name``'s setting, from its dataset config ``dconfig`` (a mapping or YAML path);
    ``overrides`` replace chosen ``bodies`` scene parameters (e.g. ``{"E": 2e4}``)."""
    return get_family(family_name).place(meshes, dconfig, overrides)
