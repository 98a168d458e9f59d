"""Frames of trajectories as multi-level graphs that batch correctly.

A mesh's bi-stride :class:`~bsms.graph.hierarchy.Hierarchy` is converted once into
:class:`MeshLevels` (torch tensors); each frame then becomes a :class:`LevelGraph` (a PyG
``Data``) holding the node state, the per-level edges and transition maps, and optional
contact edges per level. Batching graphs of different meshes with PyG's ``Batch`` offsets
every index field by the node count of the level it points into.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Data
from tqdm import tqdm

from bsms.config import ConfigError
from bsms.graph import Transition, bistride_levels, coarsen_contacts, contact_edges
from datagen.dataset import load
from datagen.trajectory import NodeType

__all__ = [
    "NodeType", "N_NODE_TYPES", "MeshLevels", "LevelGraph", "frame_graph", "GraphOptions", "NoiseOptions",
    "Scenario", "FrameDataset", "frame_velocities", "scene_constant",
]


N_NODE_TYPES = len(NodeType)


def _tensor(array, dtype) -> Tensor:
    return torch.tensor(np.asarray(array), dtype=dtype)


@dataclass(frozen=True)
class MeshLevels:
    """The levels of one mesh in torch form, level 0 first (built once per mesh).

    nodes[l]: (n_l,) level-0 index of each level-l node. edge_index[l]: (2, E_l).
    down[l]: the :class:`~bsms.graph.Transition` level l -> l+1 (rows index level l+1);
    up[l]: the one level l+1 -> l; both with torch tensors (weights float32).
    """

    nodes: tuple[Tensor, ...]
    edge_index: tuple[Tensor, ...]
    down: tuple[Transition, ...]
    up: tuple[Transition, ...]

    @property
    def n_levels(self) -> int:
        return len(self.nodes)

    @classmethod
    def from_hierarchy(cls, hierarchy, n_levels: int | None = None) -> MeshLevels:
        """Torch form of the first ``n_levels`` (default all) levels of a bi-stride hierarchy."""
        levels = hierarchy.levels[: n_levels or hierarchy.n_levels]
        nodes = tuple(_tensor(hierarchy.finest_indices(l), torch.long) for l in range(len(levels)))
        edges = tuple(_tensor(level.edge_index, torch.long) for level in levels)

        def in_torch(transition: Transition) -> Transition:
            return Transition(_tensor(transition.rows, torch.long), _tensor(transition.cols, torch.long),
                              _tensor(transition.weights, torch.float32), transition.shape)

        down = tuple(in_torch(level.down) for level in levels[1:])
        up = tuple(in_torch(level.up) for level in levels[1:])
        return cls(nodes, edges, down, up)


# How PyG's Batch offsets each index field of a LevelGraph: field prefix -> which level's node
# count (relative to the field's own level l) the field's values index. The transitions are
# stored as their triplets, ``{down,up}_{rows,cols,weights}_{l}`` (weights are never offset).
_OFFSETS = {
    "edge_index": 0, "contact_index": 0, "down_rows": 1, "down_cols": 0, "up_rows": 0, "up_cols": 1,
}


class LevelGraph(Data):
    """One frame on one mesh, with its levels; fields per level l are suffixed ``_{l}``.

    x-like fields on level-0 nodes: ``pos``, ``rest_pos``, ``velocity`` (N, d),
    ``node_type`` (N,), optional ``constants`` (N, k), ``target`` (N, d), ``loss_mask`` (N,).
    Per level: ``nodes_{l}``, ``edge_index_{l}``, ``contact_index_{l}``, ``down_*_{l}`` and
    ``up_*_{l}`` (rows, cols, weights) of the transitions between l and l+1 (:meth:`transition`),
    ``n_nodes_{l}``.
    """

    def __inc__(self, key: str, value, *args, **kwargs):
        prefix, _, level = key.rpartition("_")
        if prefix in _OFFSETS:
            return getattr(self, f"n_nodes_{int(level) + _OFFSETS[prefix]}")
        if prefix == "nodes":
            return self.num_nodes
        if prefix in ("down_weights", "up_weights"):
            return 0
        return super().__inc__(key, value, *args, **kwargs)

    def __cat_dim__(self, key: str, value, *args, **kwargs):
        if key.rpartition("_")[0] in ("edge_index", "contact_index"):
            return -1
        return super().__cat_dim__(key, value, *args, **kwargs)

    @property
    def n_levels(self) -> int:
        return sum(1 for key in self.keys() if key.startswith("nodes_"))

    def transition(self, kind: str, level: int) -> Transition:
        """The ``"down"`` (l -> l+1) or ``"up"`` (l+1 -> l) transition of ``level`` l, in torch
        (of the whole batch for a batch)."""
        shape = (self.level_size(level + 1), self.level_size(level))
        return Transition(self[f"{kind}_rows_{level}"], self[f"{kind}_cols_{level}"], self[f"{kind}_weights_{level}"],
                          shape if kind == "down" else shape[::-1])

    def level_size(self, level: int) -> int:
        """Total node count of ``level`` (summed over the graphs of a batch)."""
        count = getattr(self, f"n_nodes_{level}")
        return int(count.sum()) if torch.is_tensor(count) else int(count)


def frame_graph(levels: MeshLevels, *, rest_pos, pos, velocity, node_type, target=None, loss_mask=None,
                constants=None, contacts: tuple | None = None) -> LevelGraph:
    """Build the graph of one frame.

    rest_pos, pos, velocity: (N, d); node_type: (N,) NodeType codes; target: (N, d) or None;
    loss_mask: (N,) bool (default: free nodes); constants: (N, k) per-node scene constants;
    contacts: one (2, C_l) contact edge index per level (``coarsen_contacts``), or None.
    """
    n = levels.nodes[0].shape[0]
    node_type = _tensor(node_type, torch.long)
    data = LevelGraph(
        num_nodes=n, rest_pos=_tensor(rest_pos, torch.float32), pos=_tensor(pos, torch.float32),
        velocity=_tensor(velocity, torch.float32), node_type=node_type,
    )
    if data.pos.shape != (n, data.rest_pos.shape[1]) or data.velocity.shape != data.pos.shape:
        raise ValueError(f"rest_pos, pos and velocity must all be (N, d) with N = {n} mesh nodes")
    if target is not None:
        data.target = _tensor(target, torch.float32)
    data.loss_mask = node_type == NodeType.FREE if loss_mask is None else _tensor(loss_mask, torch.bool)
    if constants is not None:
        data.constants = _tensor(constants, torch.float32)
    if contacts is not None and len(contacts) < levels.n_levels:
        raise ValueError(f"contacts must give one edge index per level ({levels.n_levels}); got {len(contacts)}")
    for l in range(levels.n_levels):
        setattr(data, f"n_nodes_{l}", int(levels.nodes[l].shape[0]))
        setattr(data, f"nodes_{l}", levels.nodes[l])
        setattr(data, f"edge_index_{l}", levels.edge_index[l])
        if contacts is not None:
            setattr(data, f"contact_index_{l}", _tensor(contacts[l], torch.long).reshape(2, -1))
        if l + 1 < levels.n_levels:
            for kind, transition in (("down", levels.down[l]), ("up", levels.up[l])):
                for part in ("rows", "cols", "weights"):
                    setattr(data, f"{kind}_{part}_{l}", getattr(transition, part))
    return data


# ----------------------------------------------------------------------------- trajectories
@dataclass
class GraphOptions:
    """How a trajectory becomes graphs (the ``graph`` section of a training config).

    levels: bi-stride levels, the mesh included (every graph of a run has exactly this many,
        so that batches line up; meshgraphnets uses level 0 only).
    seeding, self_loops: options of :func:`bsms.graph.bistride_levels`.
    obstacles: add the wall/container geometry of the trajectory as OBSTACLE nodes (with the
        edges of its facets), so that the model can see the walls it bounces off.
    contact: add world-space contact edges per frame, carried to every level.
    contact_radius: contact distance in units of the median rest edge length of the body.
        MPM bodies feel a wall about one background cell before they reach it, so it should
        cover a background cell (the family configs use 3 body edges = ~1.5 cells).
    obstacle_spacing: obstacle facets are subdivided until no obstacle edge is longer than
        this many median body edges (0: keep the geometry as stored), so that a body node
        near a wall always finds wall nodes within the contact radius.
    self_contact: also join close nodes of the same body that are not mesh neighbours.
    constants: scene parameters (names in the trajectory's ``params``) fed to every node,
        such as ``E``; positive values spanning a decade or more are best given as ``log_E``
        (the natural log of ``E``).
    """

    levels: int = 4
    seeding: Literal["min_ave", "close_center", "random"] = "min_ave"
    self_loops: bool = True
    obstacles: bool = True
    contact: bool = True
    contact_radius: float = 3.0
    obstacle_spacing: float = 1.0
    self_contact: bool = False
    constants: list[str] = field(default_factory=list)

    def validate(self, prefix: str = "graph") -> None:
        if not 1 <= self.levels <= 16:
            raise ConfigError(f"config key '{prefix}.levels' must be from 1 to 16 (the mesh included), "
                              f"got {self.levels}")
        if self.obstacle_spacing < 0:
            raise ConfigError(f"config key '{prefix}.obstacle_spacing' must be >= 0 (0 keeps the stored "
                              f"geometry), got {self.obstacle_spacing}")
        if self.contact_radius <= 0:
            raise ConfigError(f"config key '{prefix}.contact_radius' must be positive (in median rest edge "
                              f"lengths), got {self.contact_radius}")
        for name in self.constants:
            if not name or name == "log_":
                raise ConfigError(f"config key '{prefix}.constants' holds an empty name")


def scene_constant(params: dict, name: str, source: str = "the trajectory") -> float:
    """The value of constant ``name`` (``X`` or ``log_X``) from scene parameters ``params``."""
    key = name[4:] if name.startswith("log_") else name
    value = params.get(key)
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not np.isfinite(value):
        known = sorted(k for k, v in params.items() if isinstance(v, (int, float)) and not isinstance(v, bool))
        raise ValueError(f"graph constant {name!r}: {source} has no numeric scene parameter {key!r}; "
                         f"numeric parameters: {', '.join(known) or 'none'}")
    if key != name:
        if value <= 0:
            raise ValueError(f"graph constant {name!r}: {source} has {key} = {value}, which has no logarithm")
        return float(np.log(value))
    return float(value)


def frame_velocities(positions: np.ndarray, initial_velocity: np.ndarray, frame_dt: float) -> np.ndarray:
    """(T, N, d) input velocities: the initial condition at frame 0, then (x_t - x_{t-1}) / dt.

    Finite differences make the learned update exact to integrate: x_{t+1} = x_t + dt (v_t + dv).
    """
    velocities = np.empty_like(positions)
    velocities[0] = initial_velocity
    velocities[1:] = np.diff(positions, axis=0) / frame_dt
    return velocities


def subdivide_facets(nodes: np.ndarray, facets: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Obstacle geometry with no facet edge longer than ``spacing`` (2D: original nodes first).

    nodes (M, d); facets (F, k) with k = 2 (segments) or 3 (triangles). Each facet is split
    uniformly into n pieces per edge (segments: n per segment; triangles: one n for all, so
    shared edges get the same points); points shared by facets are merged.
    """
    k = facets.shape[1]
    if len(facets) == 0 or k not in (2, 3):
        return nodes, facets
    corners = nodes[facets]  # (F, k, d)
    lengths = np.linalg.norm(corners[:, [1, 2, 0][:k]] - corners, axis=-1) if k == 3 else \
        np.linalg.norm(corners[:, 1] - corners[:, 0], axis=-1)[:, None]
    if lengths.max() <= spacing:
        return nodes, facets
    if k == 2:
        pieces = np.maximum(1, np.ceil(lengths[:, 0] / spacing).astype(int))
        points, segments = [nodes], []
        count = len(nodes)
        for (a, b), n in zip(facets, pieces, strict=True):
            inner = nodes[a] + np.outer(np.arange(1, n) / n, nodes[b] - nodes[a])
            ids = np.concatenate([[a], count + np.arange(n - 1), [b]])
            points.append(inner)
            count += n - 1
            segments.append(np.stack([ids[:-1], ids[1:]], axis=1))
        return np.concatenate(points), np.concatenate(segments)
    n = int(np.ceil(lengths.max() / spacing))
    # barycentric lattice (i, j) with i + j <= n, and its small triangles
    lattice = np.array([(i, j) for i in range(n + 1) for j in range(n + 1 - i)])
    index = {tuple(p): q for q, p in enumerate(lattice)}
    small = []
    for i in range(n):
        for j in range(n - i):
            small.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j < n - 1:
                small.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    small = np.array(small)
    weights = np.column_stack([n - lattice.sum(1), lattice[:, 0], lattice[:, 1]]) / n  # (L, 3)
    points = np.einsum("lc,fcd->fld", weights, corners).reshape(-1, nodes.shape[1])
    triangles = (small[None] + len(lattice) * np.arange(len(facets))[:, None, None]).reshape(-1, 3)
    scale = max(float(np.abs(points).max()), 1.0)
    _, first, inverse = np.unique(np.round(points / (1e-9 * scale)).astype(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
    return points[first], inverse.reshape(-1)[triangles]


@dataclass
class Scenario:
    """The fixed part of the graphs of one trajectory (or of one mesh placed in a scene).

    Nodes are the body mesh vertices followed by the obstacle nodes (if the options add them).
    rest_pos (N, d), node_type (N,), body_id (N,) (obstacles get one id after the bodies),
    edges (E, 2) mesh edges (body cells and obstacle facets), cells: the body cells, n_body:
    body vertex count, hierarchy / levels: the bi-stride levels, constants (k,), frame_dt:
    time between frames, contact_radius: absolute contact distance.
    """

    rest_pos: np.ndarray
    node_type: np.ndarray
    body_id: np.ndarray
    edges: np.ndarray
    cells: np.ndarray
    n_body: int
    hierarchy: object
    levels: MeshLevels
    constants: np.ndarray
    frame_dt: float
    contact_radius: float
    options: GraphOptions

    @classmethod
    def build(cls, mesh, options: GraphOptions, *, frame_dt: float, node_type=None, body_id=None,
              obstacle_nodes=None, obstacle_facets=None, params: dict | None = None, cache_dir=None,
              source: str = "the trajectory") -> Scenario:
        """The scenario of body ``mesh`` (a datagen Mesh) with optional obstacle geometry."""
        n_body, dim = mesh.nodes.shape
        node_type = np.full(n_body, NodeType.FREE, np.int64) if node_type is None else np.asarray(node_type, np.int64)
        body_id = np.zeros(n_body, np.int64) if body_id is None else np.asarray(body_id, np.int64)
        rest, edges = mesh.nodes, mesh.edges
        has_obstacles = options.obstacles and obstacle_nodes is not None and len(obstacle_nodes) > 0
        spacing = options.obstacle_spacing * float(np.median(mesh.edge_lengths))
        if has_obstacles:
            obstacle_nodes = np.asarray(obstacle_nodes, np.float64).reshape(-1, dim)
            facets = np.asarray(obstacle_facets, np.int64).reshape(len(obstacle_facets), -1)
            if spacing > 0:
                obstacle_nodes, facets = subdivide_facets(obstacle_nodes, facets, spacing)
            pairs = np.concatenate([facets[:, [a, b]] for a in range(facets.shape[1])
                                    for b in range(a + 1, facets.shape[1])]) + n_body
            rest = np.concatenate([rest, obstacle_nodes])
            edges = np.concatenate([edges, np.unique(np.sort(pairs, axis=1), axis=0)])
            node_type = np.concatenate([node_type, np.full(len(obstacle_nodes), NodeType.OBSTACLE, np.int64)])
            body_id = np.concatenate([body_id, np.full(len(obstacle_nodes), body_id.max() + 1, np.int64)])
        hierarchy = bistride_levels(edges, rest, levels=options.levels, seeding=options.seeding,
                                    self_loops=options.self_loops, cache_dir=cache_dir)
        constants = np.array([scene_constant(params or {}, name, source) for name in options.constants])
        return cls(
            rest_pos=rest, node_type=node_type, body_id=body_id, edges=edges, cells=mesh.cells, n_body=n_body,
            hierarchy=hierarchy, levels=MeshLevels.from_hierarchy(hierarchy), constants=constants,
            frame_dt=float(frame_dt), contact_radius=options.contact_radius * float(np.median(mesh.edge_lengths)),
            options=options,
        )

    @classmethod
    def from_trajectory(cls, trajectory, options: GraphOptions, cache_dir=None, source: str = "the trajectory"):
        frame_dt = float(trajectory.times[1] - trajectory.times[0]) if len(trajectory.times) > 1 else float("nan")
        return cls.build(
            trajectory.mesh, options, frame_dt=frame_dt, node_type=trajectory.node_type,
            body_id=trajectory.body_id, obstacle_nodes=trajectory.obstacle_nodes,
            obstacle_facets=trajectory.obstacle_facets, params=trajectory.config.get("params", {}),
            cache_dir=cache_dir, source=source,
        )

    @property
    def n_nodes(self) -> int:
        return self.rest_pos.shape[0]

    @property
    def kinematic(self) -> np.ndarray:
        """(N,) bool: nodes whose motion is prescribed (clamped and obstacle nodes)."""
        return self.node_type != NodeType.FREE

    def full(self, body_values: np.ndarray, obstacle_value: np.ndarray | float | None = None) -> np.ndarray:
        """(..., N, d): body-node values extended to the obstacle nodes (static: rest / 0)."""
        extra = self.n_nodes - self.n_body
        if extra == 0:
            return np.asarray(body_values)
        if obstacle_value is None:
            obstacle_value = self.rest_pos[self.n_body:]
        pad = np.broadcast_to(obstacle_value, body_values.shape[:-2] + (extra, body_values.shape[-1]))
        return np.concatenate([body_values, pad], axis=-2)

    def contacts(self, pos: np.ndarray) -> tuple | None:
        """Contact edges of positions ``pos`` (N, d) on every level, or None without contact."""
        if not self.options.contact:
            return None
        level0 = contact_edges(pos, self.body_id, self.contact_radius, exclude=self.edges,
                               self_contact=self.options.self_contact)
        return coarsen_contacts(self.hierarchy, level0)

    def graph(self, pos: np.ndarray, velocity: np.ndarray, target: np.ndarray | None = None) -> LevelGraph:
        """The graph of one state: ``pos`` and ``velocity`` (N, d) of all nodes."""
        constants = None
        if len(self.constants):
            constants = np.broadcast_to(self.constants, (self.n_nodes, len(self.constants)))
        graph = frame_graph(self.levels, rest_pos=self.rest_pos, pos=pos, velocity=velocity, node_type=self.node_type,
                            target=target, constants=constants, contacts=self.contacts(pos))
        graph.frame_dt = torch.full((self.n_nodes,), self.frame_dt, dtype=torch.float32)
        return graph


@dataclass
class NoiseOptions:
    """Training noise on the inputs of free nodes, with the target corrected (``data.noise``).

    position: std (m) added to x_t; the input velocity sees it, and the target asks for a
        fraction ``gamma`` of it to be undone in position (gamma = 0 restores the velocity only,
        1 also the position; MeshGraphNets uses 0.1 for cloth).
    velocity: std (m/s) added to the input velocity only; the target restores the velocity.
    """

    position: float = 0.0
    velocity: float = 0.0
    gamma: float = 0.1

    def validate(self, prefix: str = "noise") -> None:
        for name in ("position", "velocity"):
            if getattr(self, name) < 0:
                raise ConfigError(f"config key '{prefix}.{name}' is a standard deviation and must be >= 0, "
                                  f"got {getattr(self, name)}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ConfigError(f"config key '{prefix}.gamma' must lie in [0, 1], got {self.gamma}")


class FrameDataset(torch.utils.data.Dataset):
    """Every (trajectory, frame t) of some trajectory files as one-step samples t -> t+1.

    Scenarios (hierarchies) are built once per file (``cache_dir`` keeps hierarchies across
    runs); positions are held in memory in float64. Items are addressed by an integer, or by
    ``(index, noise_seed)`` to add the training noise of ``noise`` drawn from that seed, so the
    noise of a sample does not depend on which process or batch draws it.
    """

    def __init__(self, files, options: GraphOptions, noise: NoiseOptions | None = None, cache_dir=None,
                 progress: bool = False):
        self.files = [str(f) for f in files]
        if not self.files:
            raise ValueError("FrameDataset needs at least one trajectory file")
        self.options, self.noise = options, noise or NoiseOptions()
        self.scenarios: list[Scenario] = []
        self.positions: list[np.ndarray] = []
        self.velocities: list[np.ndarray] = []
        for path in tqdm(self.files, desc="graphs", unit="traj", disable=not progress):
            trajectory = load(path)
            if len(trajectory.times) < 2:
                raise ValueError(f"trajectory file {path} has {len(trajectory.times)} frame(s); training needs >= 2")
            scenario = Scenario.from_trajectory(trajectory, options, cache_dir, source=f"trajectory file {path}")
            positions = scenario.full(trajectory.positions)
            initial = scenario.full(trajectory.velocities[:1], 0.0)[0]
            self.scenarios.append(scenario)
            self.positions.append(positions)
            self.velocities.append(frame_velocities(positions, initial, scenario.frame_dt))
        dims = {s.rest_pos.shape[1] for s in self.scenarios}
        if len(dims) > 1:
            raise ValueError(f"trajectory files mix dimensions {sorted(dims)}")
        self.dim = dims.pop()
        counts = [len(p) - 1 for p in self.positions]
        self._starts = np.concatenate([[0], np.cumsum(counts)])

    def __len__(self) -> int:
        return int(self._starts[-1])

    def locate(self, index: int) -> tuple[int, int]:
        """(trajectory, frame) of sample ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(f"sample {index} out of range for {len(self)} samples")
        trajectory = int(np.searchsorted(self._starts, index, side="right") - 1)
        return trajectory, int(index - self._starts[trajectory])

    def __getitem__(self, key) -> LevelGraph:
        index, noise_seed = key if isinstance(key, tuple) else (key, None)
        k, t = self.locate(int(index))
        scenario, positions, velocities = self.scenarios[k], self.positions[k], self.velocities[k]
        pos, velocity = positions[t].copy(), velocities[t].copy()
        target = velocities[t + 1] - velocities[t]
        if noise_seed is not None and (self.noise.position > 0 or self.noise.velocity > 0):
            rng = np.random.default_rng(noise_seed)
            free = (scenario.node_type == NodeType.FREE)[:, None]
            dx = free * rng.normal(0.0, self.noise.position, pos.shape)
            dv = free * rng.normal(0.0, self.noise.velocity, pos.shape)
            pos += dx
            velocity += dx / scenario.frame_dt + dv
            target = target - (1.0 + self.noise.gamma) * dx / scenario.frame_dt - dv
        return scenario.graph(pos, velocity, target)
