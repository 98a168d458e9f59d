"""Data generation: meshes, scenes and the MPM solver."""

from .simulation import simulate
from .trajectory import NodeType, Trajectory

__all__ = ["simulate", "Trajectory", "NodeType"]
