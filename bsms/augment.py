"""Training-set augmentation by mirroring (``train.mirror``) and by rotation (``train.rotate``).

The solver's scenes are symmetric under the reflection x -> -x whenever gravity has no x part
and the materials are isotropic (every family here): the mirror image of a trajectory, its body,
walls and moving obstacles reflected together, is another exact trajectory of the same physics.
A learned model is not mirror-equivariant by construction (its MLPs see signed offsets), so
the reflected copies are new samples: a C and a reflected C are different shapes to it, and a
push from the left teaches the push from the right. Only relative quantities enter the graphs,
so where the reflection puts the scene does not matter.

Rotation turns one training sample's whole graph -- body, walls, obstacles, every vector input
and the target -- by a random angle (:func:`rotated`). It is exact where nothing in the physics
points a way: no gravity, or gravity negligible against the loads (a stiff body pressed by an
indenter sags by microns under its weight, and moves by millimetres), and isotropic materials.
The network then cannot learn a shape's response in one orientation only; it has to learn it
from the local geometry and the load, which is what carries to shapes it has not seen.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import torch

from bsms.config import ConfigError
from datagen.dataset import load
from datagen.mesh import Mesh

__all__ = ["mirrored", "strided", "trajectories", "random_rotation", "rotated", "reflected", "ROTATED_FIELDS"]

# The vector fields of a graph on its level-0 nodes (bsms.level_graph.LevelGraph) that turn with it;
# everything else in a graph is a scalar, an index, or derived from these by the model.
ROTATED_FIELDS = ("pos", "rest_pos", "velocity", "target", "penetration", "clearance", "elastic")


def mirrored(trajectory, source: str = "the trajectory"):
    """``trajectory`` reflected by x -> -x: body nodes, positions, velocities and obstacle
    geometry reflected, cells and obstacle facets re-ordered so that they keep their orientation.
    Per-frame diagnostics are dropped (their vectors would need reflecting; training reads none).

    Raises ConfigError for trajectories of converted datasets (their fields are kept as the
    source stores them) and for scenes whose gravity has an x part (no longer symmetric)."""
    if trajectory.fields is not None:
        raise ConfigError(f"config key 'train.mirror': {source} holds a converted dataset's fields; mirroring "
                          "applies to the solver's trajectories")
    gravity = np.atleast_1d(np.asarray(trajectory.config.get("params", {}).get("gravity", 0.0), float))
    if gravity.size > 1 and gravity[0] != 0.0:
        raise ConfigError(f"config key 'train.mirror': {source} has gravity {gravity.tolist()} with an x part, so "
                          "its scene is not symmetric under x -> -x; train without it")
    flip = np.ones(trajectory.mesh.dim)
    flip[0] = -1.0
    obstacles = {}
    if trajectory.obstacle_nodes is not None:
        obstacles = {"obstacle_nodes": np.asarray(trajectory.obstacle_nodes) * flip,
                     "obstacle_facets": _swap_last_two(np.asarray(trajectory.obstacle_facets))}
    if trajectory.obstacle_positions is not None:
        obstacles["obstacle_positions"] = np.asarray(trajectory.obstacle_positions) * flip
    return dataclasses.replace(
        trajectory, mesh=Mesh(trajectory.mesh.nodes * flip, _swap_last_two(trajectory.mesh.cells)),
        positions=trajectory.positions * flip, velocities=trajectory.velocities * flip, diagnostics={},
        step_diagnostics=None, **obstacles)


def _swap_last_two(simplices: np.ndarray) -> np.ndarray:
    """Cells or facets with their last two vertices swapped: undoes the orientation flip of a
    reflection (a segment reversed, a triangle or tetrahedron re-wound)."""
    order = np.arange(simplices.shape[1])
    order[[-2, -1]] = order[[-1, -2]]
    return simplices[:, order]


def strided(trajectory, stride: int, offset: int = 0):
    """``trajectory`` (a :class:`~datagen.trajectory.Trajectory`) at frames offset, offset + k, ...:
    times, positions, velocities and moving obstacles taken every ``stride`` frames. The first
    frame's velocity is the stored one (the solver's, as frame 0's initial condition is);
    per-frame diagnostics and wall times are dropped (training reads none)."""
    if stride < 1 or not 0 <= offset < stride:
        raise ValueError(f"a frame stride must be >= 1 and its offset in [0, stride); got {stride}, {offset}")
    if stride == 1:
        return trajectory
    take = slice(offset, None, stride)
    moving = trajectory.obstacle_positions
    return dataclasses.replace(
        trajectory, times=trajectory.times[take], positions=trajectory.positions[take],
        velocities=trajectory.velocities[take], diagnostics={}, step_diagnostics=None, frame_wall_times=None,
        obstacle_positions=None if moving is None else moving[take])


def trajectories(files, mirror: bool = False):
    """(trajectory, source) of every file, each followed by its mirror image when ``mirror``."""
    for path in files:
        trajectory, source = load(path), f"trajectory file {path}"
        yield trajectory, source
        if mirror:
            yield mirrored(trajectory, source), f"{source}, mirrored"


def position_noise(rng: np.random.Generator, pos: np.ndarray, free: np.ndarray, std: float,
                   rigid: bool = False) -> np.ndarray:
    """(N, d) training noise on the positions ``pos`` of the ``free`` (N, 1) nodes: normal of ``std``
    per component (``noise.position``); ``rigid`` (``noise.rigid``): its rigid-motion part over the
    free nodes (the scene one body: :func:`bsms.models.body_motion.rigid_part`, a 2D similarity or
    3D affine field), scaled by sqrt(free components / the space's dimension) so that each component
    keeps variance std^2 -- noise only in what a ``model.rigid_part`` model's rigid part can err in."""
    dx = free * rng.normal(0.0, std, pos.shape)
    mask = free[:, 0]
    if not rigid or not mask.any():
        return dx
    from bsms.models.body_motion import rigid_part, space_dimension

    d = pos.shape[1]
    part = rigid_part(torch.from_numpy(dx), torch.from_numpy(np.asarray(pos, np.float64)),
                      torch.zeros(len(pos), dtype=torch.long), 1, torch.from_numpy(mask)).numpy()
    return free * part * np.sqrt(mask.sum() * d / space_dimension(d))


def random_rotation(dim: int, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """A (dim, dim) rotation by an angle drawn uniformly from [-degrees, degrees]: in 2D about
    the plane's normal, in 3D about an axis drawn uniformly on the sphere (1D: the identity)."""
    angle = np.radians(rng.uniform(-degrees, degrees))
    if dim == 1:
        return np.eye(1)
    c, s = np.cos(angle), np.sin(angle)
    if dim == 2:
        return np.array([[c, -s], [s, c]])
    axis = rng.normal(size=3)
    x, y, z = axis / np.linalg.norm(axis)
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + s * cross + (1.0 - c) * cross @ cross  # Rodrigues


def rotated(graph, rotation: np.ndarray):
    """``graph`` (one frame's LevelGraph) with every vector field of :data:`ROTATED_FIELDS` it
    holds turned by ``rotation`` (d, d), in place; returns it. Offsets, norms and the contact
    and hierarchy structure built from them are those of the turned scene."""
    matrix = torch.as_tensor(rotation.T)
    for key in ROTATED_FIELDS:
        if key in graph:
            graph[key] = graph[key] @ matrix.to(graph[key].dtype)
    return graph


def reflected(graph):
    """A new graph: ``graph`` (a LevelGraph, one frame or a batch) reflected by x -> -x, the
    vector fields of :data:`ROTATED_FIELDS` turned by :func:`rotated` with the reflection; the
    other fields are ``graph``'s own (shared, not copied). The reflection keeps every distance, so
    the levels, contact edges and transitions built for ``graph`` are the reflected scene's too."""
    flip = np.eye(graph.pos.shape[1])
    flip[0, 0] = -1.0
    return rotated(copy.copy(graph), flip)
