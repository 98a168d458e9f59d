"""Trajectories as multi-level graphs: scenarios (the fixed part of a trajectory's graphs),
their frames, and the one-step samples training reads.

A :class:`Scenario` builds the bi-stride :class:`~bsms.graph.hierarchy.Hierarchy` of its body
and obstacle nodes once; each frame then becomes a :class:`~bsms.level_graph.LevelGraph` (a PyG
``Data``) holding the node state, the per-level edges and transition maps, and contact edges
per level, of the body nodes and the obstacle nodes within reach of them
(:mod:`bsms.graph.frames`). Frames of several scenarios join into one batch
(:func:`~bsms.level_graph.level_graph`, or PyG's ``Batch``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from bsms.augment import position_noise, random_rotation, rotated, strided, trajectories
from bsms.config import ConfigError
from bsms.fields import FieldSpec, eulerian_state, initial_velocity, spec_of, type_codes, world_positions
from bsms.graph import bistride_levels
from bsms.graph.frames import SubHierarchy
from bsms.graph.obstacles import ObstacleReach, Subdivision, facet_edges, subdivide_obstacles
from bsms.level_graph import FrameArrays, LevelGraph, level_graph
from bsms.options import GraphOptions, NoiseOptions, saved_graph_options
from bsms.physics.elastic import HOLD, ElasticResponse
from bsms.physics.penetration import Clearance, Penetration
from datagen.dataset import DatasetError
from datagen.trajectory import NodeType

__all__ = [
    "NodeType", "N_NODE_TYPES", "LevelGraph", "GraphOptions", "NoiseOptions", "Scenario", "FrameDataset",
    "frame_velocities", "scene_constant", "saved_graph_options",
]


N_NODE_TYPES = len(NodeType)


# ----------------------------------------------------------------------------- trajectories
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


def frame_velocities(positions: np.ndarray, initial_velocity: np.ndarray, frame_dt: float,
                     kinematic: np.ndarray | None = None) -> np.ndarray:
    """(T, N, d) input velocities: the initial condition at frame 0, then (x_t - x_{t-1}) / dt.

    Finite differences make the learned update exact to integrate: x_{t+1} = x_t + dt (v_t + dv).
    kinematic: (N,) bool, nodes whose motion is prescribed (clamped, obstacle): their velocity
    at every frame but the last is that of the coming step, (x_{t+1} - x_t) / dt, so that the
    model knows where they go next (an indenter reversing included); for nodes that stay put
    it is 0 either way.
    """
    velocities = np.empty_like(positions)
    velocities[0] = initial_velocity
    velocities[1:] = np.diff(positions, axis=0) / frame_dt
    if kinematic is not None and kinematic.any():
        velocities[:-1, kinematic] = velocities[1:, kinematic]
    return velocities


def _with_obstacles(rest, edges, node_type, body_id, obstacle_nodes, obstacle_facets, spacing: float):
    """Body arrays extended by the (subdivided) obstacle nodes and their facet edges, and the
    :class:`Subdivision` that places the obstacle nodes."""
    n_body, dim = rest.shape
    obstacle_nodes = np.asarray(obstacle_nodes, np.float64).reshape(-1, dim)
    facets = np.asarray(obstacle_facets, np.int64).reshape(len(obstacle_facets), -1)
    geometry = subdivide_obstacles(obstacle_nodes, facets, spacing)
    m = len(geometry.nodes)
    return (np.concatenate([rest, geometry.nodes]), np.concatenate([edges, facet_edges(geometry.facets) + n_body]),
            np.concatenate([node_type, np.full(m, NodeType.OBSTACLE, np.int64)]),
            np.concatenate([body_id, np.full(m, body_id.max() + 1, np.int64)]), geometry)


def _obstacle_input(kind, wanted: bool, rest, geometry: Subdivision | None, n_body: int, source: str, *args):
    """The scenario's ``kind`` (:class:`Penetration` for ``graph.penetration``, :class:`Clearance`
    for ``graph.clearance``, :class:`ElasticResponse` for ``graph.elastic``) where ``wanted``; None
    without obstacle geometry."""
    if not wanted or geometry is None:
        return None
    try:
        return kind(rest, geometry.facets + n_body, n_body, *args)
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from None


@dataclass
class Scenario:
    """The fixed part of the graphs of one trajectory (or of one mesh placed in a scene).

    Nodes are the body mesh vertices followed by the obstacle nodes (if the options add them).
    rest_pos (N, d), node_type (N,), body_id (N,) (obstacles get one id after the bodies),
    edges (E, 2) mesh edges (body cells and obstacle facets), cells: the body cells, n_body:
    body vertex count, hierarchy: the bi-stride levels of all N nodes, constants (k,),
    frame_dt: time between frames, contact_radius: absolute contact distance; levels: the
    hierarchy prepared for frames that keep some obstacle nodes (:class:`SubHierarchy`); reach:
    which obstacle nodes a frame keeps (:class:`ObstacleReach`); type_codes: (N,) source node
    type codes fed one-hot instead of the roles (:mod:`bsms.fields`), or None; obstacle_geometry:
    the subdivided obstacle geometry and its map from the stored obstacle nodes (None: no obstacle
    nodes), through which moving obstacles place theirs (:meth:`positions`). A frame's graph (:meth:`graph`)
    holds the body nodes and the obstacle nodes within reach of them, so its size changes from
    frame to frame.
    """

    rest_pos: np.ndarray
    node_type: np.ndarray
    body_id: np.ndarray
    edges: np.ndarray
    cells: np.ndarray
    n_body: int
    hierarchy: object
    constants: np.ndarray
    frame_dt: float
    contact_radius: float
    options: GraphOptions
    levels: SubHierarchy = field(repr=False)
    reach: ObstacleReach = field(repr=False)
    type_codes: np.ndarray | None = None
    obstacle_geometry: Subdivision | None = field(default=None, repr=False)
    penetration: Penetration | None = field(default=None, repr=False)
    clearance: Clearance | None = field(default=None, repr=False)
    elastic: ElasticResponse | None = field(default=None, repr=False)
    loss_weight: float | None = field(default=None, repr=False)

    @classmethod
    def build(cls, mesh, options: GraphOptions, *, frame_dt: float, node_type=None, body_id=None,
              obstacle_nodes=None, obstacle_facets=None, params: dict | None = None, cache_dir=None,
              source: str = "the trajectory", type_codes=None) -> Scenario:
        """The scenario of body ``mesh`` (a datagen Mesh) with optional obstacle geometry."""
        n_body = mesh.n_nodes
        node_type = np.full(n_body, NodeType.FREE, np.int64) if node_type is None else np.asarray(node_type, np.int64)
        body_id = np.zeros(n_body, np.int64) if body_id is None else np.asarray(body_id, np.int64)
        rest, edges = mesh.nodes, mesh.edges
        edge_length = float(np.median(mesh.edge_lengths))
        geometry = None
        if options.obstacles and obstacle_nodes is not None and len(obstacle_nodes) > 0:
            if type_codes is not None:
                raise ValueError(f"{source}: node type codes of a source dataset and obstacle geometry do not mix")
            spacing = options.obstacle_spacing * edge_length
            rest, edges, node_type, body_id, geometry = _with_obstacles(rest, edges, node_type, body_id, obstacle_nodes,
                                                                        obstacle_facets, spacing)
        hierarchy = bistride_levels(edges, rest, levels=options.levels, seeding=options.seeding,
                                    self_loops=options.self_loops, max_coarse_degree=options.max_coarse_degree,
                                    cache_dir=cache_dir)
        constants = np.array([scene_constant(params or {}, name, source) for name in options.constants])
        radius = options.contact_radius * edge_length if options.contact_distance is None else \
            options.contact_distance
        reach = None if options.obstacle_margin is None else radius + options.obstacle_margin * edge_length
        clearance = _obstacle_input(Clearance, options.clearance, rest, geometry, n_body, source, radius)
        elastic = _obstacle_input(ElasticResponse, options.elastic, rest, geometry, n_body, source, mesh.cells,
                                  (params or {}).get("nu"), edge_length, HOLD)
        return cls(
            rest_pos=rest, node_type=node_type, body_id=body_id, edges=edges, cells=mesh.cells, n_body=n_body,
            hierarchy=hierarchy, constants=constants, frame_dt=float(frame_dt), contact_radius=radius,
            options=options, levels=SubHierarchy(hierarchy, n_body),
            reach=ObstacleReach(n_body, body_id, radius, reach, options.self_contact, edges,
                                excluded=None if clearance is None else clearance.excluded),
            type_codes=None if type_codes is None else np.asarray(type_codes, np.int64), obstacle_geometry=geometry,
            penetration=_obstacle_input(Penetration, options.penetration, rest, geometry, n_body, source),
            clearance=clearance, elastic=elastic,
        )

    @classmethod
    def from_trajectory(cls, trajectory, options: GraphOptions, cache_dir=None, source: str = "the trajectory",
                        spec: FieldSpec | None = None):
        """The scenario of a stored trajectory (``spec``: its field spec, for its node type codes;
        default: the one stored with it, :func:`bsms.fields.spec_of`)."""
        spec = spec_of(trajectory, source) if spec is None else spec
        frame_dt = float(trajectory.times[1] - trajectory.times[0]) if len(trajectory.times) > 1 else float("nan")
        return cls.build(
            trajectory.mesh, options, frame_dt=frame_dt, node_type=trajectory.node_type,
            body_id=trajectory.body_id, obstacle_nodes=trajectory.obstacle_nodes,
            obstacle_facets=trajectory.obstacle_facets, params=trajectory.config.get("params", {}),
            cache_dir=cache_dir, source=source,
            type_codes=type_codes(spec, trajectory, source),
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

    def positions(self, body_positions: np.ndarray, obstacle_positions: np.ndarray | None = None) -> np.ndarray:
        """(..., N, d) positions of every scenario node: ``body_positions`` (..., N_body, d) of the
        body nodes, and the obstacle nodes placed by ``obstacle_positions`` (..., M, d) of the
        stored obstacle nodes (a trajectory's ``obstacle_positions``) through the subdivision
        map; None: static obstacles, at rest (as :meth:`full`)."""
        if obstacle_positions is None or self.obstacle_geometry is None:
            return self.full(body_positions)
        body_positions = np.asarray(body_positions)
        moved = self.obstacle_geometry.moved(obstacle_positions)
        if moved.shape[:-2] != body_positions.shape[:-2]:
            raise ValueError(f"obstacle positions of shape {np.shape(obstacle_positions)} do not match body positions "
                             f"of shape {body_positions.shape}: give both for the same frames")
        return np.concatenate([body_positions, moved], axis=-2)

    def frames(self, states: list[tuple[np.ndarray, np.ndarray]]) -> list[FrameArrays]:
        """:meth:`frame` of each ``(pos, velocity)`` of ``states``; with ``graph.elastic`` the
        elastic answers of all of them in one solve (:meth:`ElasticResponse.many`)."""
        if not self.options.elastic or self.elastic is None:
            return [self.frame(pos, velocity) for pos, velocity in states]
        loads, answers = self.elastic_answers(states)
        return [self.frame(pos, velocity, inputs=(load, answer))
                for (pos, velocity), load, answer in zip(states, loads, answers, strict=True)]

    def elastic_answers(self, states: list[tuple[np.ndarray, np.ndarray]]) -> tuple[list, list]:
        """The penetration inputs (N, d) of ``states`` ((pos, velocity) of every scenario node) and
        the elastic answers to them, all in one solve (needs ``graph.elastic``)."""
        loads = [self._penetration(pos, velocity) for pos, velocity in states]
        return loads, self.elastic.many(loads)

    def _penetration(self, pos: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """(N, d) the penetration input of every scenario node (0 without obstacle outlines)."""
        pos = np.asarray(pos, np.float64)
        if self.penetration is None:
            return np.zeros_like(pos)
        coming = pos + self.frame_dt * np.asarray(velocity, np.float64)  # kinematic rows: their coming step
        return self.penetration(pos, coming, self.node_type == NodeType.FREE)

    def frame(self, pos: np.ndarray, velocity: np.ndarray, target: np.ndarray | None = None,
              fields: np.ndarray | None = None, inputs: tuple | None = None) -> FrameArrays:
        """The graph of one state in numpy: ``pos``, ``velocity`` (and ``target``) (N, d) of all
        scenario nodes (Eulerian data: the fixed mesh, zero, and ``fields`` (N, k) the node
        inputs of :mod:`bsms.fields`); it holds the body nodes and the obstacle nodes within reach of them
        (``nodes["scenario_nodes"]``: the scenario node of each graph node, sorted). ``inputs``: the
        penetration and elastic answer (N, d) of every scenario node, already computed (:meth:`frames`)."""
        chosen, contacts = self.reach.frame(np.asarray(pos, np.float64))
        present = self.levels.closure(chosen)
        levels, keep, local = self.levels.levels(present)
        if self.options.contact:
            contacts = self.levels.contacts(contacts[:, present[contacts[0]] & present[contacts[1]]], keep, local)
        nodes = np.flatnonzero(present)
        node_type = self.node_type[nodes]
        arrays = {"rest_pos": self.rest_pos[nodes], "pos": np.asarray(pos)[nodes],
                  "velocity": np.asarray(velocity)[nodes], "node_type": node_type,
                  "loss_mask": node_type == NodeType.FREE, "frame_dt": np.full(len(nodes), self.frame_dt),
                  "scenario_nodes": nodes}
        if target is not None:
            arrays["target"] = np.asarray(target)[nodes]
        if fields is not None:
            arrays["fields"] = np.asarray(fields)[nodes]
        if self.type_codes is not None:
            arrays["type_code"] = self.type_codes[nodes]
        if self.loss_weight is not None:
            arrays["loss_weight"] = np.full(len(nodes), self.loss_weight)
        if len(self.constants):
            arrays["constants"] = np.broadcast_to(self.constants, (len(nodes), len(self.constants)))
        if self.options.penetration:
            penetration, answer = (self._penetration(pos, velocity), None) if inputs is None else inputs
            arrays["penetration"] = penetration[nodes]
            if self.options.elastic:
                if answer is None:
                    answer = self.elastic(penetration) if self.elastic is not None else np.zeros_like(penetration)
                arrays["elastic"] = answer[nodes]
        if self.options.clearance:
            arrays["clearance"] = self.clearance(np.asarray(pos, np.float64), self.node_type == NodeType.FREE)[nodes] \
                if self.clearance is not None else np.zeros((len(nodes), np.shape(pos)[1]))
        return FrameArrays(arrays, levels, contacts if self.options.contact else None)

    def graph(self, pos: np.ndarray, velocity: np.ndarray, target: np.ndarray | None = None,
              fields: np.ndarray | None = None) -> LevelGraph:
        """The :class:`LevelGraph` of one state (see :meth:`frame`)."""
        return level_graph([self.frame(pos, velocity, target, fields)])


class NumberedSamples(torch.utils.data.Dataset):
    """Samples numbered across trajectories: trajectory k's samples are ``_starts[k]`` to
    ``_starts[k + 1] - 1``, one per usable frame."""

    _starts: np.ndarray

    def __len__(self) -> int:
        return int(self._starts[-1])

    def locate(self, index: int) -> tuple[int, int]:
        """(trajectory, frame) of sample ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(f"sample {index} out of range for {len(self)} samples")
        trajectory = int(np.searchsorted(self._starts, index, side="right") - 1)
        return trajectory, int(index - self._starts[trajectory])


class FrameDataset(NumberedSamples):
    """Every (trajectory, frame t) of some trajectory files as one-step samples t -> t+1.

    Scenarios (hierarchies) are built once per file (``cache_dir`` keeps hierarchies across
    runs); states are held in memory in float64: Lagrangian positions (all scenario nodes,
    moving obstacles placed per frame, :meth:`Scenario.positions`; input velocities are
    differenced from them per sample, :meth:`sample_velocities`), or Eulerian
    states (:mod:`bsms.fields`). ``spec``: the field spec of the
    files (they must share one). Items are addressed by an integer, or by ``(index,
    noise_seed)`` to add the training noise of ``noise`` drawn from that seed, so the noise of
    a sample does not depend on which process or batch draws it. ``mirror``: each file also
    enters reflected by x -> -x (:mod:`bsms.augment`), after it. ``rotate`` (degrees): a sample
    addressed with a seed is turned by an angle up to this, drawn from that seed (Lagrangian data).
    ``frame_stride`` k (Lagrangian data, ``train.frame_stride``): a sample is the step from frame t
    to t + k (:mod:`bsms.rollouts.stride`); each file enters as k trajectories, its frames from each offset
    0..k-1 every k frames, sharing one scenario (frame time k dt).
    """

    def __init__(self, files, options: GraphOptions, noise: NoiseOptions | None = None, cache_dir=None,
                 progress: bool = False, mirror: bool = False, loss_weight: str = "uniform", rotate: float = 0.0,
                 frame_stride: int = 1):
        self.files = [str(f) for f in files]
        if not self.files:
            raise ValueError("FrameDataset needs at least one trajectory file")
        self.options, self.noise, self.rotate = options, noise or NoiseOptions(), float(rotate)
        self.scenarios: list[Scenario] = []
        self.positions: list[np.ndarray] = []
        self.initial: list[np.ndarray] = []  # each trajectory's frame-0 velocity (N, d)
        self.states: list[np.ndarray] = []
        self.spec: FieldSpec | None = None
        for trajectory, source in tqdm(trajectories(self.files, mirror), desc="graphs", unit="traj",
                                       total=len(self.files) * (2 if mirror else 1), disable=not progress):
            if len(trajectory.times) < 2:
                raise ValueError(f"{source} has {len(trajectory.times)} frame(s); training needs >= 2")
            spec = self._spec(trajectory, source)
            if frame_stride > 1 and not spec.is_lagrangian:
                raise ConfigError(f"config key 'train.frame_stride' applies to Lagrangian data; {source} holds "
                                  f"{spec.describe()} (set train.frame_stride: 1)")
            if len(trajectory.times) < frame_stride + 1:
                raise ValueError(f"{source} has {len(trajectory.times)} frames; a frame stride of {frame_stride} "
                                 f"needs >= {frame_stride + 1}")
            scenario = Scenario.from_trajectory(strided(trajectory, frame_stride), options, cache_dir, source=source,
                                                spec=spec)
            if scenario.elastic is not None:
                scenario.elastic.cache_limit = 0  # samples are drawn across all scenes: keep no unit responses
            if not spec.is_lagrangian:
                self.scenarios.append(scenario)
                self.states.append(eulerian_state(spec, trajectory, source))
                continue
            for offset in range(frame_stride):  # every frame starts a step (train.frame_stride)
                part = strided(trajectory, frame_stride, offset)
                if len(part.times) < 2:
                    continue
                world = world_positions(spec, part, source)
                self.scenarios.append(scenario if offset == 0 else dataclasses.replace(scenario))  # own loss weight
                self.positions.append(scenario.positions(world, part.obstacle_positions))
                self.initial.append(scenario.full(initial_velocity(spec, part, world)[None], 0.0)[0])
        self.dim = self.spec.dim
        if self.rotate and self.states:
            raise ConfigError(f"config key 'train.rotate' turns positions and velocities; {self.files[0]} holds "
                              f"{self.spec.describe()} (set train.rotate: 0)")
        counts = [len(p) - 1 for p in (self.positions or self.states)]
        self._starts = np.concatenate([[0], np.cumsum(counts)])
        if loss_weight == "motion":
            self._weigh_by_motion()
        elif loss_weight != "uniform":
            raise ConfigError(f"config key 'train.loss_weight' must be 'uniform' or 'motion', got {loss_weight!r}")

    def _weigh_by_motion(self) -> None:
        """Each trajectory's loss weight 1 / s^2 (``train.loss_weight: motion``): s its at-rest
        error (RMS distance of the free nodes from frame 0 over frames 1..T-1), floored at a
        quarter of the median; scaled so that the weights average 1 over the samples."""
        if self.states:
            raise ConfigError(f"config key 'train.loss_weight' 'motion' needs Lagrangian data; {self.files[0]} "
                              f"holds {self.spec.describe()} (use 'uniform')")
        free = [scenario.node_type == NodeType.FREE for scenario in self.scenarios]
        scales = np.array([np.sqrt(np.mean(np.sum((p[1:, f] - p[:1, f]) ** 2, axis=-1)))
                           for p, f in zip(self.positions, free, strict=True)])
        weights = 1.0 / np.maximum(scales, 0.25 * np.median(scales)) ** 2
        counts = np.diff(self._starts)
        weights /= np.sum(weights * counts) / np.sum(counts)
        for scenario, weight in zip(self.scenarios, weights, strict=True):
            scenario.loss_weight = float(weight)

    def _spec(self, trajectory, source: str) -> FieldSpec:
        """The field spec of one file, the same as the others'; the options checked against it."""
        try:
            spec = spec_of(trajectory, source)
        except ValueError as exc:
            raise DatasetError(str(exc)) from None
        if self.spec is None:
            if self.options.contact and not spec.is_lagrangian:
                raise ConfigError(f"config key 'graph.contact' must be false for Eulerian data ({source} holds "
                                  "fields on a fixed mesh: no world edges, thesis Table 4.2)")
            self.noise.check(spec, source)
            if self.options.from_rest and (not spec.is_lagrangian or self.noise.position > 0 or
                                           self.noise.velocity > 0):
                raise ConfigError("config key 'graph.from_rest' needs Lagrangian data and no input noise (no state "
                                  f"enters its graphs, so noise has nothing to undo: set noise.position and "
                                  f"noise.velocity to 0); {source} holds {spec.describe()}, noise.position is "
                                  f"{self.noise.position}, noise.velocity {self.noise.velocity}")
            if self.options.quasi_static and (not spec.is_lagrangian or self.noise.velocity > 0):
                raise ConfigError("config key 'graph.quasi_static' needs Lagrangian data and 'noise.velocity' 0 "
                                  f"(free nodes have no velocity input); {source} holds {spec.describe()}, "
                                  f"noise.velocity is {self.noise.velocity}")
            self.spec = spec
        elif spec != self.spec:
            raise DatasetError(f"{source} holds {spec.describe()}, but {self.files[0]} holds "
                               f"{self.spec.describe()}; trajectory files mix dimensions or fields")
        return spec

    def __getitem__(self, key) -> LevelGraph:
        index, noise_seed = key if isinstance(key, tuple) else (key, None)
        k, t = self.locate(int(index))
        if self.states:
            return self._eulerian(self.scenarios[k], self.states[k], t, noise_seed)
        graph = self.scenarios[k].graph(*self.sample_state(k, t, noise_seed))
        if self.rotate and noise_seed is not None:
            rng = np.random.default_rng(np.random.SeedSequence(noise_seed, spawn_key=(1,)))  # not the noise's draws
            graph = rotated(graph, random_rotation(self.dim, self.rotate, rng))
        return graph

    def trajectory_velocities(self, k: int) -> np.ndarray:
        """(T, N, d) the input velocities of Lagrangian trajectory k (:func:`frame_velocities`)."""
        scenario = self.scenarios[k]
        return frame_velocities(self.positions[k], self.initial[k], scenario.frame_dt, scenario.kinematic)

    def sample_velocities(self, k: int, t: int) -> tuple[np.ndarray, np.ndarray]:
        """The input velocities (N, d) of frames t and t + 1 of trajectory k, as
        :meth:`trajectory_velocities` gives them, from the frames they need (computed per sample,
        not kept per trajectory: a scene's memory is mostly its states)."""
        positions, scenario, start = self.positions[k], self.scenarios[k], max(t - 1, 0)
        initial = self.initial[k] if start == 0 else np.zeros_like(self.initial[k])  # row 0 unused then
        window = frame_velocities(positions[start:t + 3], initial, scenario.frame_dt, scenario.kinematic)
        return window[t - start], window[t + 1 - start]  # a fresh array: the caller may change it

    def sample_state(self, k: int, t: int, noise_seed=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(pos, velocity, target) of the Lagrangian sample of frame t of trajectory k, (N, d)
        float64 of every scenario node: the inputs (with the training noise drawn from
        ``noise_seed``, if given) and the one-step target of its graph."""
        scenario, positions = self.scenarios[k], self.positions[k]
        velocity, coming = self.sample_velocities(k, t)
        pos, target = positions[t].copy(), coming - velocity
        if self.options.from_rest:  # free nodes at rest, without velocity; the target: x_{t+1} - X over dt
            free = (scenario.node_type == NodeType.FREE)[:, None]
            rest = scenario.rest_pos
            return (np.where(free, rest, pos), np.where(free, 0.0, velocity),
                    np.where(free, (positions[t + 1] - rest) / scenario.frame_dt, target))
        if self.options.quasi_static:
            free = (scenario.node_type == NodeType.FREE)[:, None]
            target = np.where(free, coming, target)
            if noise_seed is not None and self.noise.position > 0:
                dx = position_noise(np.random.default_rng(noise_seed), pos, free, self.noise.position, self.noise.rigid)
                pos += dx
                target = target - dx / scenario.frame_dt
            return pos, np.where(free, 0.0, velocity), target
        if noise_seed is not None and (self.noise.position > 0 or self.noise.velocity > 0):
            rng = np.random.default_rng(noise_seed)
            free = (scenario.node_type == NodeType.FREE)[:, None]
            dx = position_noise(rng, pos, free, self.noise.position, self.noise.rigid)
            dv = free * rng.normal(0.0, self.noise.velocity, pos.shape)
            pos += dx
            velocity += dx / scenario.frame_dt + dv
            target = target - (1.0 + self.noise.gamma) * dx / scenario.frame_dt - dv
        return pos, velocity, target

    def _eulerian(self, scenario: Scenario, states: np.ndarray, t: int, noise_seed) -> LevelGraph:
        """The sample of frame t of an Eulerian trajectory: noise on the input fields of free
        nodes, removed again by the targets of the fields whose change is predicted."""
        spec = self.spec
        inputs, target = spec.input_values(states[t]), spec.target(states[t], states[t + 1])
        if noise_seed is not None:
            rng = np.random.default_rng(noise_seed)
            free = (scenario.node_type == NodeType.FREE)[:, None]
            changes = {f.name for f in spec.outputs if f.target == "change"}
            start = 0
            for f in spec.inputs:
                std = self.noise.field_std(f.name)
                if std > 0:
                    noise = free * rng.normal(0.0, std, (len(inputs), f.width))
                    inputs[:, start: start + f.width] += noise
                    if f.name in changes:
                        target[:, spec.output_columns(f.name)] -= noise
                start += f.width
        return scenario.graph(scenario.rest_pos, np.zeros_like(scenario.rest_pos), target, inputs)
