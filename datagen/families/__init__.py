"""Dataset families: randomized scenes for training data.

Each module has NAME, SCENE (the datagen.scenes scene it samples), DIM, CONTACT, OBSTACLES,
CLAMPED (what the scene has), RANGES (default parameter ranges) and
``sample(ranges, rng, split) -> params`` for that scene. The same ranges and generator state
give the same parameters.
"""

from __future__ import annotations

from ..scenes import ConfigError
from . import cantilever, disks, glyphs, wavy_channel

__all__ = ["FAMILIES", "get_family"]

FAMILIES = {module.NAME: module for module in (wavy_channel, disks, cantilever, glyphs)}


def get_family(name):
    """The family module registered as ``name``; ConfigError naming the choices otherwise."""
    if not isinstance(name, str) or name not in FAMILIES:
        raise ConfigError(f"unknown family {name!r} (config key 'family'); choose one of {', '.join(sorted(FAMILIES))}")
    return FAMILIES[name]
