"""What a learned simulator reads and writes per node, chosen from the dataset (thesis Table 4.2).

A :class:`FieldSpec` is small and explicit:

- ``kind``: ``lagrangian`` -- nodes move: the state is the world positions, the input their
  velocity (backward difference over a frame), the output a velocity change, integrated
  v_{t+1} = v_t + dv, x_{t+1} = x_t + dt v_{t+1}; mesh edges carry material- and world-space
  offsets and their norms, and contact (world) edges world-space ones. ``eulerian`` -- the
  mesh is fixed: the state is node fields (velocity, density, pressure, ...), the inputs some
  of them, the outputs per field either its one-frame change (f_{t+1} = f_t + df) or its next
  value (f_{t+1} = out); mesh edges carry material-space offsets only, and there are no
  contact edges.
- ``dim``: dimension of the world positions (Lagrangian) or of the mesh (Eulerian);
  ``material_dim``: the mesh's own dimension (cloth: 3D positions on a 2D material mesh).
- ``positions`` (Lagrangian): the trajectory field holding the world positions, or ``""``
  for the trajectory's own positions (every MPM trajectory).
- ``inputs`` / ``outputs``: :class:`Field` (name, width, target ``change`` or ``value``).
- ``types``: the trajectory field of per-node type codes fed one-hot with ``n_types``
  classes (DeepMind's ``node_type``: normal, obstacle, airfoil, handle, inflow, outflow,
  wall boundary, so outflow and wall nodes stay distinguishable), or ``""``: the one-hot of
  the node's role (:class:`~datagen.trajectory.NodeType`: free, clamped, obstacle).

Every node whose role is not FREE is prescribed: Lagrangian positions and Eulerian fields of
clamped and obstacle nodes come from the data (inflow, walls, airfoil, handles, actuators).

The spec of a trajectory is stored in its config (``field_spec``, written by the converter of
:mod:`bsms.datasets.convert`) or, for the solver's trajectories, is the Lagrangian default
of their dimension -- exactly the features bsms used before specs existed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from datagen.trajectory import NodeType

__all__ = ["Field", "FieldSpec", "infer_spec", "spec_of", "world_positions", "initial_velocity",
           "eulerian_state", "type_codes", "DEEPMIND_N_TYPES"]

DEEPMIND_N_TYPES = 9  # DeepMind's NodeType.SIZE: the one-hot width of its node types
_TARGETS = ("change", "value")


@dataclass(frozen=True)
class Field:
    """A node field: its name, width and (outputs) whether the model predicts its one-frame
    ``change`` or its next ``value``."""

    name: str
    width: int
    target: Literal["change", "value"] = "change"


@dataclass(frozen=True)
class FieldSpec:
    """Node inputs, outputs, integration and edge features of a learned simulator (module docs)."""

    kind: Literal["lagrangian", "eulerian"]
    dim: int
    material_dim: int
    inputs: tuple[Field, ...]
    outputs: tuple[Field, ...]
    positions: str = ""
    types: str = ""
    n_types: int = len(NodeType)
    _columns: dict = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        problem = self._problem()
        if problem:
            raise ValueError(f"field spec {self.to_dict()}: {problem}")
        columns, start = {}, 0
        for f in self.state_fields:
            columns[f.name] = slice(start, start + f.width)
            start += f.width
        object.__setattr__(self, "_columns", columns)

    def _problem(self) -> str:
        if self.kind not in ("lagrangian", "eulerian"):
            return f"kind must be lagrangian or eulerian, got {self.kind!r}"
        if not (1 <= self.material_dim <= self.dim <= 3):
            return "dimensions must satisfy 1 <= material_dim <= dim <= 3"
        if any(f.target not in _TARGETS or f.width < 1 for f in self.outputs + self.inputs) or not self.outputs:
            return "outputs must be non-empty and every field needs a width >= 1 and a target change or value"
        if self.kind == "lagrangian":
            velocity = (Field("velocity", self.dim),)
            if self.inputs != velocity or self.outputs != velocity:
                return "Lagrangian data read and write the velocity of the world positions (a velocity change)"
        else:
            widths = {}
            for f in self.inputs + self.outputs:
                if widths.setdefault(f.name, f.width) != f.width:
                    return f"field {f.name!r} has two widths"
            if len({f.name for f in self.outputs}) != len(self.outputs) or self.positions:
                return "outputs must name distinct fields, and Eulerian data have no world positions"
        if self.n_types < 1 or (not self.types and self.n_types != len(NodeType)):
            return f"n_types must be {len(NodeType)} (the node roles) unless types names a field of type codes"
        return ""

    # -- construction
    @classmethod
    def lagrangian(cls, dim: int, material_dim: int | None = None, positions: str = "", types: str = "",
                   n_types: int = len(NodeType)) -> FieldSpec:
        """Positions integrated from a predicted velocity change (the solver's trajectories)."""
        velocity = (Field("velocity", dim),)
        return cls("lagrangian", dim, material_dim or dim, velocity, velocity, positions, types, n_types)

    def to_dict(self) -> dict:
        """Plain values (JSON, YAML and ``weights_only`` checkpoints hold it)."""
        return {"kind": self.kind, "dim": self.dim, "material_dim": self.material_dim,
                "inputs": [[f.name, f.width] for f in self.inputs],
                "outputs": [[f.name, f.width, f.target] for f in self.outputs],
                "positions": self.positions, "types": self.types, "n_types": self.n_types}

    @classmethod
    def from_dict(cls, data: dict, where: str = "the field spec") -> FieldSpec:
        try:
            return cls(data["kind"], int(data["dim"]), int(data["material_dim"]),
                       tuple(Field(str(n), int(w)) for n, w in data["inputs"]),
                       tuple(Field(str(n), int(w), t) for n, w, t in data["outputs"]),
                       str(data.get("positions", "")), str(data.get("types", "")),
                       int(data.get("n_types", len(NodeType))))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where} is not a usable field spec ({exc}); convert the dataset again with "
                             "python -m bsms.datasets convert") from None

    # -- sizes and layout
    @property
    def is_lagrangian(self) -> bool:
        return self.kind == "lagrangian"

    @property
    def node_in(self) -> int:
        """Width of the node inputs before the one-hot node type and the scene constants."""
        return sum(f.width for f in self.inputs)

    @property
    def node_out(self) -> int:
        return sum(f.width for f in self.outputs)

    @property
    def mesh_edge_dim(self) -> int:
        """Mesh-edge features: material offset and norm (+ world offset and norm, Lagrangian)."""
        return self.material_dim + 1 + (self.dim + 1 if self.is_lagrangian else 0)

    @property
    def contact_edge_dim(self) -> int | None:
        """Contact-edge features (world offset and norm); None: no contact edges (Eulerian)."""
        return self.dim + 1 if self.is_lagrangian else None

    @property
    def state_fields(self) -> tuple[Field, ...]:
        """Eulerian: the fields of the state, inputs first, then outputs that are not inputs."""
        if self.is_lagrangian:
            return ()
        names = [f.name for f in self.inputs]
        return self.inputs + tuple(Field(f.name, f.width) for f in self.outputs if f.name not in names)

    def columns(self, name: str) -> slice:
        """Columns of field ``name`` in an Eulerian state array (..., N, state width)."""
        return self._columns[name]

    def describe(self) -> str:
        """One line for reports: inputs -> outputs, integration and edges."""
        if self.is_lagrangian:
            where = f"field {self.positions}" if self.positions else "positions"
            return (f"Lagrangian ({where}, {self.dim}D on a {self.material_dim}D mesh): velocity -> velocity change; "
                    "mesh edges: material and world offsets; contact edges: world offsets")
        outputs = ", ".join(f"{f.name} {f.target}" for f in self.outputs)
        return (f"Eulerian ({self.dim}D fixed mesh): {', '.join(f.name for f in self.inputs)} -> {outputs}; "
                "mesh edges: material offsets")

    # -- Eulerian state arithmetic (numpy, float64)
    def input_values(self, state: np.ndarray) -> np.ndarray:
        """(..., N, node_in) inputs of an Eulerian state (..., N, k)."""
        return np.concatenate([state[..., self.columns(f.name)] for f in self.inputs], axis=-1)

    def target(self, state: np.ndarray, following: np.ndarray) -> np.ndarray:
        """(N, node_out) one-step target from state t to state t+1."""
        return np.concatenate([following[..., self.columns(f.name)] - (state[..., self.columns(f.name)]
                                                                        if f.target == "change" else 0.0)
                               for f in self.outputs], axis=-1)

    def advance(self, state: np.ndarray, output: np.ndarray) -> np.ndarray:
        """State t+1 from state t (N, k) and the model's output (N, node_out) in physical units."""
        following, start = state.copy(), 0
        for f in self.outputs:
            part = output[:, start: start + f.width]
            cols = self.columns(f.name)
            following[:, cols] = state[:, cols] + part if f.target == "change" else part
            start += f.width
        return following

    def output_columns(self, name: str) -> slice | None:
        """Columns of field ``name`` in an output (N, node_out), None when not an output."""
        start = 0
        for f in self.outputs:
            if f.name == name:
                return slice(start, start + f.width)
            start += f.width
        return None


def infer_spec(fields: dict, mesh_dim: int) -> FieldSpec:
    """The spec of a source trajectory from its field names (DeepMind's and the authors' naming).

    ``world_pos`` -> Lagrangian (positions from that field when its dimension is not the mesh's,
    as for cloth). Otherwise Eulerian with ``velocity`` (required) and, where present,
    ``density`` as inputs; outputs the velocity change, the density change and, where density is
    a field (compressible flow, AIRFOIL), the next ``pressure`` (thesis Table 4.2: CYLINDERFLOW
    predicts the velocity change only). ``node_type`` codes are fed one-hot (9 classes).
    """
    types = "node_type" if "node_type" in fields else ""
    n_types = DEEPMIND_N_TYPES if types else len(NodeType)

    def width(name: str) -> int:
        return int(np.shape(fields[name])[-1])

    if "world_pos" in fields:
        dim = width("world_pos")
        return FieldSpec.lagrangian(dim, mesh_dim, "world_pos" if dim != mesh_dim else "", types, n_types)
    if "velocity" not in fields:
        raise ValueError("the trajectory has neither world_pos (Lagrangian) nor velocity (Eulerian) among its fields "
                         f"({', '.join(sorted(fields))}); bsms cannot tell what to learn")
    inputs = [Field("velocity", width("velocity"))]
    if "density" in fields:
        inputs.append(Field("density", width("density")))
    outputs = [Field(f.name, f.width, "change") for f in inputs]
    if "density" in fields and "pressure" in fields:
        outputs.append(Field("pressure", width("pressure"), "value"))
    return FieldSpec("eulerian", mesh_dim, mesh_dim, tuple(inputs), tuple(outputs), "", types, n_types)


def spec_of(trajectory, source: str = "the trajectory") -> FieldSpec:
    """The spec a trajectory was stored with (``config['field_spec']``), checked against its
    fields; the Lagrangian default of its dimension when it has none."""
    stored = trajectory.config.get("field_spec")
    if stored is None:
        return FieldSpec.lagrangian(trajectory.mesh.dim)
    spec = FieldSpec.from_dict(stored, f"{source}: config['field_spec']")
    needed = [f.name for f in spec.state_fields] + [n for n in (spec.positions, spec.types) if n]
    missing = [name for name in needed if name not in (trajectory.fields or {})]
    if missing:
        raise ValueError(f"{source} lacks the field {missing[0]!r} its field spec names; convert it again with "
                         "python -m bsms.datasets convert")
    if spec.material_dim != trajectory.mesh.dim:
        raise ValueError(f"{source}: its field spec says a {spec.material_dim}D mesh but the mesh is "
                         f"{trajectory.mesh.dim}D")
    return spec


def _frames(array: np.ndarray, trajectory, name: str, width: int, source: str) -> np.ndarray:
    """(T, N, width) float64 of a static (1, N, w) or dynamic (T, N, w) field."""
    frames, n = len(trajectory.times), trajectory.mesh.n_nodes
    array = np.asarray(array)
    if array.ndim != 3 or array.shape[1:] != (n, width) or array.shape[0] not in (1, frames):
        raise ValueError(f"{source}: field {name!r} has shape {array.shape}, expected ({frames}, {n}, {width}) "
                         f"(or (1, {n}, {width}) if static); convert it again")
    return np.broadcast_to(array, (frames, n, width)).astype(np.float64)


def world_positions(spec: FieldSpec, trajectory, source: str = "the trajectory") -> np.ndarray:
    """(T, N, dim) world positions of a Lagrangian trajectory's body nodes."""
    if not spec.positions:
        return trajectory.positions
    return _frames(trajectory.fields[spec.positions], trajectory, spec.positions, spec.dim, source)


def initial_velocity(spec: FieldSpec, trajectory, positions: np.ndarray) -> np.ndarray:
    """(N, dim) velocity at frame 0: the trajectory's own, or for positions from a field (which
    have no stored velocity) their first difference, as the converter gives stored positions."""
    if not spec.positions:
        return trajectory.velocities[0]
    if len(positions) < 2:
        return np.zeros_like(positions[0])
    return (positions[1] - positions[0]) / float(trajectory.times[1] - trajectory.times[0])


def eulerian_state(spec: FieldSpec, trajectory, source: str = "the trajectory") -> np.ndarray:
    """(T, N, k) float64 state of an Eulerian trajectory: its :attr:`FieldSpec.state_fields`."""
    return np.concatenate([_frames(trajectory.fields[f.name], trajectory, f.name, f.width, source)
                           for f in spec.state_fields], axis=-1)


def type_codes(spec: FieldSpec, trajectory, source: str = "the trajectory") -> np.ndarray | None:
    """(N,) int64 node type codes fed one-hot (None: the node roles)."""
    if not spec.types:
        return None
    codes = np.asarray(trajectory.fields[spec.types]).reshape(-1)[: trajectory.mesh.n_nodes].astype(np.int64)
    if codes.size != trajectory.mesh.n_nodes or codes.min() < 0 or codes.max() >= spec.n_types:
        raise ValueError(f"{source}: field {spec.types!r} must hold one code in [0, {spec.n_types}) per node")
    return codes
