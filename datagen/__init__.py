"""Data generation: meshes, scenes and the MPM solver."""

from .simulation import Trajectory, simulate

__all__ = ["simulate", "Trajectory"]
