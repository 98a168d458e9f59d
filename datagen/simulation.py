"""``simulate(config) -> Trajectory``: run a registered scene with the MPM solver.

A config is a dict or a YAML file path::

    scene: vibrating_bar          # a name from datagen.scenes.SCENES
    params: {n_cells: 40}         # scene parameters (defaults: the paper's settings)
    solver: {kernel: umls, transfer: flip, dt: null, cfl: 0.3, device: cpu,
             reference: eulerian, epsilon: 0.01, fraction: 0.01, contact_margin: 1.0}
    output: {frames: 100, frame_interval: 0.1}

solver.reference picks the A-ULMPM reference configuration (datagen.mpm.reference): ``eulerian``
recomputes kernels every step, ``total`` never, ``adaptive`` when the fraction of particles with
|det F^{sn} - 1| >= epsilon reaches ``fraction`` or when two separate clusters of active nodes
may have come within ``contact_margin`` cells of each other (null: no contact trigger).

Unknown keys and bad values raise :class:`ConfigError` naming the key.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from . import interrupts
from .config import ConfigError, read_yaml, reject_unknown, section
from .csmpm.scenes import GAS_SCENES
from .csmpm.scenes import resolve as resolve_gas
from .csmpm.scenes import simulate as simulate_gas
from .layer import ExtendedMesh, with_extra_layer
from .mpm import linalg
from .mpm.boundary import grid_conditions, mesh_conditions
from .mpm.diagnostics import diagnostics
from .mpm.fused import advance
from .mpm.inelastic import initial_fields
from .mpm.kernels import Grid, MeshTables
from .mpm.model import KERNELS, PRECISIONS, REFERENCES, TRANSFERS, Grip, Model, WallPlane
from .mpm.state import State
from .mpm.step import cfl_time_step, step
from .mpm.stress import kirchhoff_stress
from .scenes import Scene, get_scene
from .trajectory import Trajectory

__all__ = ["simulate", "Trajectory", "ConfigError", "resolve_config", "build_simulation", "Simulation"]

TOP_LEVEL = {"scene", "params", "solver", "output", "seed"}
SOLVER_DEFAULTS = {
    "kernel": "umls", "transfer": "flip", "dt": None, "cfl": 0.3, "device": "cpu", "dtype": "float64",
    "grid_spacing": None, "extra_layer": True, "layer_thickness": 1.0, "threads": None,
    "reference": "eulerian", "epsilon": 0.01, "fraction": 0.01, "contact_margin": 1.0, "max_substeps": 100_000,
    "fbar": False, "precision": "float64",
}
# Rough particle-steps per second of one CPU core (docs/solver.md, mpm_throughput.py), only for the time
# an absurd configuration would take, stated when it is refused.
_NOMINAL_RATE = {2: 5e5, 3: 2e5}
OUTPUT_DEFAULTS = {"frames": None, "frame_interval": None, "step_diagnostics": False}
_DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass
class Simulation:
    """A scene turned into a solver model and initial state, with the resolved config."""

    scene: Scene
    model: Model
    state: State
    config: dict
    dt: float
    substeps: int


# ----------------------------------------------------------------------------- config
def _load(config) -> dict:
    if isinstance(config, (str, Path)):
        return read_yaml(config, what="config file")
    if not isinstance(config, dict):
        kind = type(config).__name__
        raise ConfigError(f"a config must be a mapping (or a YAML file holding one), got {kind}")
    return copy.deepcopy(config)


def _positive(value, key: str, *, optional=False, integer=False):
    if value is None and optional:
        return None
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not math.isfinite(value) or value <= 0:
        what = "integer" if integer else "number"
        raise ConfigError(f"config key '{key}' must be a positive {what}, got {value!r}")
    return value


def _check_solver(s: dict) -> None:
    for key, allowed in (("kernel", KERNELS), ("transfer", TRANSFERS), ("dtype", _DTYPES),
                         ("reference", REFERENCES), ("precision", PRECISIONS)):
        if s[key] not in allowed:
            choices = ", ".join(sorted(allowed))
            raise ConfigError(f"config key 'solver.{key}' must be one of {choices}, got {s[key]!r}")
    if s["kernel"] == "linear" and s["transfer"] == "apic":
        raise ConfigError("config key 'solver.transfer' cannot be 'apic' with kernel 'linear': the linear hat's "
                          "APIC inertia D_p is singular at mesh nodes; use flip, pic or musl, or kernel umls")
    if s["precision"] == "float32" and s["dtype"] != "float64":
        raise ConfigError("config key 'solver.precision' float32 is the compiled substeps' arithmetic over a "
                          "float64 state; it needs solver.dtype float64 (dtype float32 runs every step in torch)")
    _positive(s["dt"], "solver.dt", optional=True)
    _positive(s["grid_spacing"], "solver.grid_spacing", optional=True)
    _positive(s["layer_thickness"], "solver.layer_thickness")
    _positive(s["threads"], "solver.threads", optional=True, integer=True)
    _positive(s["max_substeps"], "solver.max_substeps", integer=True)
    _positive(s["epsilon"], "solver.epsilon")
    if not (_positive(s["fraction"], "solver.fraction") <= 1.0):
        raise ConfigError(f"config key 'solver.fraction' must be in (0, 1], got {s['fraction']!r}")
    margin = s["contact_margin"]
    if margin is not None and (isinstance(margin, bool) or not isinstance(margin, (int, float))
                               or not math.isfinite(margin) or margin < 0):
        raise ConfigError(f"config key 'solver.contact_margin' must be a number >= 0 (cells) or null, "
                          f"got {margin!r}")
    if not (_positive(s["cfl"], "solver.cfl") <= 1.0):
        raise ConfigError(f"config key 'solver.cfl' must be in (0, 1], got {s['cfl']!r}")
    for key in ("extra_layer", "fbar"):
        if not isinstance(s[key], bool):
            raise ConfigError(f"config key 'solver.{key}' must be true or false, got {s[key]!r}")
    try:
        device = torch.device(s["device"])
    except (RuntimeError, TypeError):
        raise ConfigError(f"config key 'solver.device' is not a torch device: {s['device']!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("config key 'solver.device' asks for cuda, but no CUDA device is available; "
                          "use 'cpu'")


def resolve_config(config) -> dict:
    """The full config: defaults filled in (scene defaults for params and output), all checked."""
    config = _load(config)
    if config.get("scene") in GAS_SCENES:  # CSMPM's scenes check their own keys
        return resolve_gas(config)
    reject_unknown(config, TOP_LEVEL)
    if "scene" not in config:
        raise ConfigError("config key 'scene' is missing; name a scene, e.g. scene: vibrating_bar")
    scene = get_scene(config["scene"])
    params = scene.params(config.get("params") or {})
    solver = section(config, "solver", {**SOLVER_DEFAULTS, **scene.SOLVER})
    _check_solver(solver)
    output = section(config, "output", {**OUTPUT_DEFAULTS, **scene.OUTPUT})
    _positive(output["frames"], "output.frames", integer=True)
    _positive(output["frame_interval"], "output.frame_interval")
    if not isinstance(output["step_diagnostics"], bool):
        raise ConfigError("config key 'output.step_diagnostics' must be true or false")
    seed = config.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"config key 'seed' must be an integer, got {seed!r}")
    return {"scene": scene.NAME, "params": params, "solver": solver, "output": output, "seed": seed}


def _check_substeps(solver: dict, interval: float, dt: float, source: str, particles: int, dim: int) -> None:
    """ConfigError, before any stepping, when a frame would take more than solver.max_substeps steps."""
    substeps = math.ceil(interval / dt - 1e-9)
    if substeps <= solver["max_substeps"]:
        return
    hours = substeps * particles / _NOMINAL_RATE.get(dim, 5e5) / 3600
    raise ConfigError(
        f"{source} {dt:.3g} s makes {substeps:,} solver steps per {interval:g} s frame (limit solver.max_substeps: "
        f"{solver['max_substeps']:,}), about {hours:.3g} hours per frame for {particles} particles on one core; "
        "use a larger solver.dt (null takes the CFL step), fewer or shorter frames, or raise solver.max_substeps "
        "if you mean it")


# ----------------------------------------------------------------------------- model
def _background(scene: Scene, solver: dict, extended: ExtendedMesh | None, device, dtype):
    """(background, conditions, node positions, CFL length) for the chosen kernel; extended: the
    domain with its extra layer (mesh kernels with solver.extra_layer), else None."""
    domain = scene.domain
    if solver["kernel"] == "bspline":
        spacing = solver["grid_spacing"] or scene.grid_spacing or domain.edge_length_stats.mean
        lower, upper = domain.nodes.min(0), domain.nodes.max(0)
        grid = Grid.covering(lower, upper, spacing)
        conditions = grid_conditions(grid, lower, upper, scene.walls, scene.clamps,
                                     device=device, dtype=dtype)
        return grid, conditions, torch.tensor(grid.nodes(), dtype=dtype, device=device), spacing
    tables = MeshTables.build(extended if extended is not None else domain, device=device, dtype=dtype)
    conditions = mesh_conditions(domain, extended, scene.walls, scene.clamps, device=device, dtype=dtype)
    return tables, conditions, tables.nodes, domain.edge_length_stats.min


def _plane(kind, friction, normal, offset, along: np.ndarray, reach: float, h: float, device, dtype) -> WallPlane:
    """A WallPlane with unit outward ``normal``; along: (n, d) points spanning it."""
    d = len(normal)
    if d == 1:
        tangents = np.zeros((0, 1))
    elif d == 2:
        tangents = np.array([[-normal[1], normal[0]]])
    else:
        helper = np.eye(3)[np.argmin(np.abs(normal))]
        t1 = np.cross(normal, helper)
        t1 /= np.linalg.norm(t1)
        tangents = np.stack([t1, np.cross(normal, t1)])
    coords = along @ tangents.T
    as_t = lambda a: torch.as_tensor(np.asarray(a, float), dtype=dtype, device=device)  # noqa: E731
    return WallPlane(kind=kind, friction=float(friction), normal=as_t(normal), offset=float(offset),
                     tangents=as_t(tangents), lower=as_t(coords.min(0)), upper=as_t(coords.max(0)),
                     depth=reach, margin=reach, tol=1e-6 * h)


def wall_planes(scene: Scene, solver: dict, h: float, device, dtype) -> tuple[WallPlane, ...]:
    """The scene's walls as flat pieces acting on moved node positions (total/adaptive modes).

    Coplanar boundary facets of one wall form one piece; a node within the piece's extent
    (plus the extra layer) that lies on or beyond it is on the wall.
    """
    reach = (solver["layer_thickness"] + 2.0) * h
    domain = scene.domain
    out = []
    if solver["kernel"] == "bspline":
        lower, upper = domain.nodes.min(0), domain.nodes.max(0)
        for axis in range(scene.dim):
            for sign, value in ((-1.0, lower[axis]), (1.0, upper[axis])):
                normal = np.zeros(scene.dim)
                normal[axis] = sign
                corners = np.array([lower, upper], float)
                corners[:, axis] = value
                centre = corners.mean(0, keepdims=True)
                for wall in scene.walls:
                    if bool(np.asarray(wall.where(centre, normal[None]))[0]):
                        out.append(_plane(wall.kind, wall.friction, normal, sign * value, corners, reach, h,
                                          device, dtype))
        return tuple(out)
    facets, normals = domain.boundary_facets, domain.boundary_normals
    points = domain.nodes[facets]  # (F, d, d)
    centroids = points.mean(1)
    offsets = (points[:, 0] * normals).sum(1)
    for wall in scene.walls:
        chosen = np.flatnonzero(np.asarray(wall.where(centroids, normals), dtype=bool))
        if not len(chosen):
            continue
        keys = np.round(np.concatenate([normals[chosen], offsets[chosen, None] / h], 1), 6)
        _, group = np.unique(keys, axis=0, return_inverse=True)
        for g in np.unique(group):
            members = chosen[group.ravel() == g]
            normal = normals[members].mean(0)
            normal /= np.linalg.norm(normal)
            along = points[members].reshape(-1, scene.dim)
            out.append(_plane(wall.kind, wall.friction, normal, float((along @ normal).mean()), along, reach, h,
                              device, dtype))
    return tuple(out)


def _pinned(scene: Scene, background, extended: ExtendedMesh | None, device, dtype) -> tuple:
    """The scene's clamps as index conditions (they hold nodes at rest, which then never move)."""
    if not scene.clamps:
        return ()
    if isinstance(background, Grid):
        lower, upper = scene.domain.nodes.min(0), scene.domain.nodes.max(0)
        return tuple(grid_conditions(background, lower, upper, [], scene.clamps, device=device, dtype=dtype))
    return tuple(mesh_conditions(scene.domain, extended, [], scene.clamps, device=device, dtype=dtype))


def build_solver_model(scene: Scene, solver: dict) -> tuple[Model, State]:
    """The solver's :class:`Model` and initial :class:`State` of a built scene (``solver``: the
    resolved solver section of a config). The extra layer, if any, is built once here."""
    device, dtype = torch.device(solver["device"]), _DTYPES[solver["dtype"]]
    mesh_kernel = solver["kernel"] != "bspline" and solver["extra_layer"]
    extended = with_extra_layer(scene.domain, solver["layer_thickness"]) if mesh_kernel else None
    background, conditions, nodes, h_cfl = _background(scene, solver, extended, device, dtype)
    reference = {}
    if solver["reference"] != "eulerian":
        h = background.spacing if isinstance(background, Grid) else background.h
        reference = {"wall_planes": wall_planes(scene, solver, h, device, dtype),
                     "pinned": _pinned(scene, background, extended, device, dtype)}
    grips = tuple(Grip(torch.as_tensor(ids, dtype=torch.int64, device=device), velocity)
                  for ids, velocity in getattr(scene, "grips", ()))
    materials = tuple(
        (m, None if ids is None else torch.as_tensor(ids, dtype=torch.int64, device=device))
        for m, ids in scene.materials
    )
    gravity = np.zeros(scene.dim) if scene.gravity is None else scene.gravity
    model = Model(
        background=background, kernel=solver["kernel"], transfer=solver["transfer"], materials=materials,
        conditions=tuple(conditions), gravity=torch.as_tensor(gravity, dtype=dtype, device=device),
        node_positions=nodes, h_cfl=float(h_cfl), reference=solver["reference"], epsilon=float(solver["epsilon"]),
        fraction=float(solver["fraction"]), contact_margin=solver["contact_margin"], grips=grips,
        colliders=tuple(scene.colliders), damping=float(scene.damping), fbar=solver["fbar"],
        precision=solver["precision"], **reference,
    )
    state = State.at_rest_shape(scene.x, scene.v, scene.volume, scene.density(), device=device, dtype=dtype)
    if scene.initial_F is not None:  # a body that starts deformed (e.g. compressed)
        F = torch.as_tensor(np.broadcast_to(scene.initial_F, state.F.shape).copy(), dtype=dtype, device=device)
        state = replace(state, F=F)
    return model, replace(state, **initial_fields(model, len(scene.x), device=device, dtype=dtype))


def build_simulation(config) -> Simulation:
    """Resolve the config, build the scene, the solver model and the initial state."""
    config = resolve_config(config)
    scene_module = get_scene(config["scene"])
    scene = scene_module.build(config["params"])
    interval = config["output"]["frame_interval"]
    if config["solver"]["dt"] is not None:  # refused before the model is built
        _check_substeps(config["solver"], interval, config["solver"]["dt"], "solver.dt", len(scene.x), scene.x.shape[1])
    model, state = build_solver_model(scene, config["solver"])
    dt_max = config["solver"]["dt"] or cfl_time_step(model, state, config["solver"]["cfl"])
    source = "solver.dt" if config["solver"]["dt"] else "the CFL time step (solver.cfl, material stiffness, mesh size)"
    _check_substeps(config["solver"], interval, dt_max, source, len(scene.x), scene.x.shape[1])
    substeps = max(1, math.ceil(interval / dt_max - 1e-9))
    return Simulation(scene, model, state, config, interval / substeps, substeps)


# ----------------------------------------------------------------------------- run
def _rebuild_counts(sim: Simulation, state: State, steps: int) -> tuple[int, int]:
    """(kernel rebuilds, of which forced by the contact trigger) after ``steps`` steps."""
    ref = state.reference
    if sim.model.reference == "eulerian":
        return steps, 0
    return (0, 0) if ref is None else (ref.rebuilds, ref.contact_rebuilds)


def _frame_record(sim: Simulation, state: State, steps: int) -> dict:
    out = {k: v.detach().cpu().numpy() for k, v in diagnostics(sim.model, state).items()}
    out["kernel_rebuilds"], out["contact_rebuilds"] = (np.array(c) for c in _rebuild_counts(sim, state, steps))
    if sim.scene.frame_diagnostics is not None:
        out.update({k: np.asarray(v.detach().cpu().numpy() if torch.is_tensor(v) else v)
                    for k, v in sim.scene.frame_diagnostics(sim, state).items()})
    m = state.mass
    out["center_of_mass"] = ((m[:, None] * state.x).sum(0) / m.sum()).cpu().numpy()
    ids = torch.as_tensor(list(sim.scene.probes.values()), dtype=torch.int64, device=state.x.device)
    if ids.numel():
        F = state.F[ids]
        tau = kirchhoff_stress(sim.model, state.F, state.out_of_plane)[ids]
        out["probe_stress"] = (tau / linalg.det(F)[:, None, None]).cpu().numpy()
    return out


def _stack(records: list[dict]) -> dict:
    return {k: np.stack([r[k] for r in records]) for k in records[0]}


def settle(sim: Simulation) -> State:
    """The initial state after the scene's settling pre-roll (``scene.settle = (seconds, damping)``):
    the body relaxes under gravity with mass-proportional damping (1/s) from t = -seconds, the
    colliders held at their start (paths hold before t = 0), and the clock is set to 0 after, so
    frame 0 is a body at rest in equilibrium instead of one about to ring as gravity comes on."""
    if not sim.scene.settle:
        return sim.state
    seconds, damping = sim.scene.settle
    model = replace(sim.model, damping=float(damping))
    steps = max(1, math.ceil(seconds / sim.dt - 1e-9))
    state = replace(sim.state, time=-steps * sim.dt)
    done = 0
    while done < steps:  # a frame's worth of substeps per call, checking for a stop request between
        interrupts.check()
        count = min(sim.substeps, steps - done)
        state = advance(model, state, sim.dt, count)
        done += count
    # the particles' velocities are zeroed: FLIP keeps particle-level noise after the motion has died
    # out, and frame 0's velocity is a learned model's first input
    return replace(state, time=0.0, step=0, v=torch.zeros_like(state.v))


def run(sim: Simulation) -> Trajectory:
    """Step the simulation through its frames (after its settling pre-roll, if any) and collect
    the trajectory."""
    frames = sim.config["output"]["frames"]
    tracked = torch.as_tensor(sim.scene.tracked, dtype=torch.int64, device=sim.state.x.device)
    start = time.perf_counter()
    state = settle(sim)
    preroll = time.perf_counter() - start
    positions, velocities, times, records, per_step = [], [], [], [], []

    def snapshot(s: State):
        positions.append(s.x[tracked].cpu().numpy())
        velocities.append(s.v[tracked].cpu().numpy())
        times.append(s.time)
        records.append(_frame_record(sim, s, s.step))

    snapshot(state)
    frame_wall = [0.0]
    for _ in range(frames):
        interrupts.check()  # a stop request whose KeyboardInterrupt was swallowed
        start = time.perf_counter()
        if sim.config["output"]["step_diagnostics"]:
            for _ in range(sim.substeps):
                state = step(sim.model, state, sim.dt)
                per_step.append({k: v.cpu().numpy() for k, v in diagnostics(sim.model, state).items()})
        else:  # the frame's substeps in one compiled call where the model allows (datagen.mpm.fused)
            state = advance(sim.model, state, sim.dt, sim.substeps)
        frame_wall.append(time.perf_counter() - start)
        snapshot(state)
    wall = float(sum(frame_wall))
    diag = _stack(records)
    diag["probe_names"] = np.array(list(sim.scene.probes))
    return Trajectory(
        mesh=sim.scene.body, positions=np.stack(positions), velocities=np.stack(velocities),
        times=np.array(times), diagnostics=diag, wall_time=wall, config=sim.config, dt=sim.dt,
        substeps=sim.substeps, n_particles=len(sim.scene.x),
        step_diagnostics=_stack(per_step) if per_step else None, frame_wall_times=np.array(frame_wall),
        node_type=sim.scene.node_type, body_id=sim.scene.body_id, obstacle_nodes=sim.scene.obstacle_nodes,
        obstacle_facets=sim.scene.obstacle_facets, obstacle_positions=sim.scene.obstacle_positions(times),
        kernel_rebuilds=_rebuild_counts(sim, state, sim.substeps * frames)[0], preroll_time=preroll,
    )


def simulate(config) -> Trajectory:
    """Run ``config`` (a dict or a YAML path) and return its :class:`Trajectory`.

    solver.threads, if set, is the number of torch CPU threads for this run (restored after);
    on small problems or a busy machine one thread is often fastest. The gas scenes of
    :mod:`datagen.csmpm.scenes` (``shock_tube``) run on CSMPM's grid solver instead.
    """
    config = _load(config)
    if config.get("scene") in GAS_SCENES:  # CSMPM's gas on its grid (datagen.csmpm)
        return simulate_gas(config)
    config = resolve_config(config)
    threads, before = config["solver"]["threads"], torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        start = time.perf_counter()
        sim = build_simulation(config)
        setup = time.perf_counter() - start
        return replace(run(sim), setup_time=setup)
    finally:
        torch.set_num_threads(before)
