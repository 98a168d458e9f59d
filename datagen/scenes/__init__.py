"""Scenes registered by name: each module has NAME, DEFAULTS, OUTPUT, SOLVER, params(), build()."""

from __future__ import annotations

from ..config import ConfigError
from . import (
    balls,
    bodies,
    cantilever,
    colliding_disks,
    disks,
    droplet,
    expansion,
    glyphs,
    pendulum,
    press,
    press3d,
    rotating_plate,
    rotating_square,
    slope,
    stretched_bar,
    vibrating_bar,
    wavy_channel,
)
from .base import Scene

__all__ = ["SCENES", "get_scene", "ConfigError", "Scene"]

SCENES = {
    module.NAME: module
    for module in (vibrating_bar, colliding_disks, cantilever, rotating_square, disks, wavy_channel, glyphs,
                   rotating_plate, stretched_bar, droplet, balls, bodies, slope, expansion, press,
                   press3d, pendulum)
}


def get_scene(name):
    """The scene module registered as ``name``; ConfigError naming the choices otherwise."""
    if not isinstance(name, str) or name not in SCENES:
        from ..csmpm.scenes import GAS_SCENES

        raise ConfigError(f"unknown scene {name!r} (config key 'scene'); "
                          f"choose one of {', '.join(sorted(SCENES) + sorted(GAS_SCENES))}")
    return SCENES[name]
