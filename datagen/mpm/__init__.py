"""Explicit MPM on unstructured simplex meshes (UMLS-MPM) and on regular grids (the structured
B-spline solver), with the A-ULMPM reference configurations.

Static :class:`Model` (model.py), evolving :class:`State` (state.py), ``step(model, state, dt)``
(step.py: the eulerian step; reference.py: the A-ULMPM total/adaptive step), the transfers over
kernel slots (transfers.py) or fixed sparse operators (operators.py), one nodal update for both
(nodal.py), and diagnostics (diagnostics.py).
"""

from .diagnostics import diagnostics
from .errors import SimulationError
from .fused import advance
from .kernels import Grid, KernelResult, MeshTables, bspline_kernel, linear_kernel, umls_kernel
from .locate import CellLocator, LocateStatus, locate
from .model import Grip, Model, WallPlane, compute_kernel
from .state import State
from .step import cfl_time_step, step

__all__ = [
    "Grid", "KernelResult", "MeshTables", "bspline_kernel", "linear_kernel", "umls_kernel",
    "CellLocator", "LocateStatus", "locate", "Model", "SimulationError", "State", "step",
    "Grip", "WallPlane", "compute_kernel", "cfl_time_step", "diagnostics", "advance",
]
