"""Explicit MPM on unstructured simplex meshes (UMLS-MPM) and on regular grids (reference)."""

from .kernels import Grid, KernelResult, MeshTables, bspline_kernel, linear_kernel, umls_kernel
from .locate import CellLocator, LocateStatus, locate
from .solver import Model, SimulationError, State, step

__all__ = [
    "Grid", "KernelResult", "MeshTables", "bspline_kernel", "linear_kernel", "umls_kernel",
    "CellLocator", "LocateStatus", "locate", "Model", "SimulationError", "State", "step",
]
