"""Data generation: meshes, scenes and the MPM solver."""

from . import hugepages

hugepages.configure()  # before any large array: see datagen.hugepages

from .simulation import simulate  # noqa: E402
from .trajectory import NodeType, Trajectory  # noqa: E402

__all__ = ["simulate", "Trajectory", "NodeType"]
