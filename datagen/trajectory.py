"""What a run produces: a :class:`Trajectory` of tracked body vertices, and the :class:`NodeType`
codes that say which of them the physics moves.

The solver driver (``datagen.simulation``) fills a Trajectory, the scenes tag their vertices
with NodeType codes, and the file format (``datagen.dataset``) writes and reads both.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from .mesh import Mesh

__all__ = ["NodeType", "Trajectory"]


class NodeType(IntEnum):
    """Role of a node in the learned graph."""

    FREE = 0  # moved by the physics (and by the model)
    CLAMPED = 1  # moves as prescribed (e.g. a clamped beam end)
    OBSTACLE = 2  # a node of a wall or container, moves as prescribed


@dataclass
class Trajectory:
    """A simulated run, sampled at frames.

    mesh: the body mesh (rest positions; its vertices are the tracked material points).
    positions, velocities: (T, N, d) of the tracked points. times: (T,). diagnostics: name ->
    (T, ...) per frame (mass, momentum, angular_momentum, kinetic/elastic/gravitational
    energy, center_of_mass, probe_stress (T, n_probes, d, d) Cauchy stress, and probe_names).
    step_diagnostics: the same per solver step when output.step_diagnostics is set, else None.
    wall_time: seconds spent stepping the solver. config: the full resolved config.
    frame_wall_times: (T,) solver seconds spent reaching each frame (0 for frame 0).
    node_type: (N,) NodeType codes of the tracked points (None: all free).
    body_id: (N,) body of each tracked point (None: one body). obstacle_nodes (M, d) and
    obstacle_facets (F, d): wall/container geometry a model can see (None: none); obstacle_nodes
    are where it is at frame 0. obstacle_positions: (T, M, d) where the obstacle nodes are at
    each frame when obstacles move (kinematic, prescribed motion; None: static, they stay at
    obstacle_nodes).
    fields: name -> array of a converted source dataset's own fields, kept exactly as the source
    holds them (e.g. DeepMind's velocity, pressure, cells; None for the solver's runs).
    kernel_rebuilds: how many times kernels were computed: one per step in eulerian mode, one
    per reference update (the first included) in total/adaptive mode. setup_time: seconds from
    the config to the first step (scene, meshes, particles, kernels' tables, time step);
    preroll_time: seconds of the settling pre-roll before frame 0 (0 without one); both None for
    a trajectory read from a file (they are not stored). diagnostics also hold
    kernel_rebuilds and contact_rebuilds (T,), cumulative counts at each frame.
    """

    mesh: Mesh
    positions: np.ndarray
    velocities: np.ndarray
    times: np.ndarray
    diagnostics: dict
    wall_time: float
    config: dict
    dt: float
    substeps: int
    n_particles: int
    step_diagnostics: dict | None = None
    frame_wall_times: np.ndarray | None = None
    node_type: np.ndarray | None = None
    body_id: np.ndarray | None = None
    obstacle_nodes: np.ndarray | None = None
    obstacle_facets: np.ndarray | None = None
    obstacle_positions: np.ndarray | None = None
    kernel_rebuilds: int | None = None
    fields: dict | None = None
    setup_time: float | None = None
    preroll_time: float | None = None
