"""Zero-shot inference on any mesh: ``python -m bsms.infer RUN_DIR --mesh FILE [...]``.

The mesh (any format meshio reads, of the run's dimension) is placed in the setting of the
dataset family the run was trained on -- the family's box, walls, gravity and mid-range
material and speed, scaled like the family's bodies (``--scene KEY=VALUE`` changes any
scene parameter) -- and the model rolls it out. Meshes larger than any seen in training
work: the hierarchy is built for the new mesh (its levels are the run's ``graph.levels``).
A mesh coarser than the family's own bodies is subdivided to their resolution where the family
places it so (the press families: each triangle into four, its nodes kept first;
:mod:`datagen.refine`): the model and the solver run on the finer body, and everything below is
reported on the given mesh's nodes (``--scene refine=false`` keeps it as given).
A 3D run also takes a part as its closed surface, as a CAD tool exports it (STL ascii or binary,
OBJ, any meshio file of triangles off the plane z = 0): merged, checked to bound a solid (one
error naming the file, what is wrong and the fix where it does not: holes, edges of more than
two triangles, inconsistent facets; :mod:`datagen.surface`) and tetrahedralised with gmsh at the
model's spacing -- the family's bodies' ``body_size`` once the part is scaled like them, or their
node count -- into ``<name>_tetrahedra.vtu`` in the output folder, which is then placed and
rolled out as any mesh file (:mod:`bsms.infer.surfaces`; ``tetrahedralised`` and ``meshing_s`` in
``summary.json``, apart from the times below: the model and the solver both start from the
tetrahedra). A 2D run refuses a surface in 3D.
Outputs, in ``--out`` (default ``RUN_DIR/infer/<mesh name>``): ``prediction.xdmf`` (+ .h5)
for ParaView, ``prediction.gif`` and ``summary.json``. With ``--solver`` the MPM solver
runs the same setup: ``solver.xdmf`` (+ .h5) holds its body nodes at the same frames (to put
prediction and truth side by side in ParaView), and ``summary.json`` the error, the error of
predicting no motion (``rest_rel_all``), their ratio ``vs_rest``, both split into rigid and
deformation parts (:mod:`bsms.rollouts.motion`), and the speed-up (the error is drawn in the GIF): ``speedup``
end to end for this new mesh -- ``solver_s`` (the solver from the scene to the last frame, its
setup included, its settling pre-roll apart: ``solver_preroll_s``) over ``setup_s + learned_s``
(placing the mesh and building its scenario: hierarchy, factorisations, outlines; then the
rollout as run, graph building included, no untimed warm-up) -- beside ``speedup_throughput``
(the rollout's frames batched, the setup not counted) and ``latency_ms`` (one frame per call, as a
controller or an interactive user calls the model; over the first :data:`LATENCY_FRAMES` frames).
Not in the end-to-end time, and reported apart: ``model_load_s`` (reading the weights, once per
process) and ``outputs_s`` (writing the XDMF files and the GIF); ``call_s`` is the whole call up
to this summary (all of the above, the latency measurement and any ensemble members' rollouts;
the solver's run not counted), what a caller timing ``infer`` sees. ``cpu`` names the processor
they were timed on.
An ensemble folder (:mod:`bsms.ensemble`) answers with its members' mean, timed as such; each
member is then also rolled out alone (untimed) and how far they disagree is reported: per node
and frame the root mean square distance of the members' positions from their mean (``spread``
in ``prediction.xdmf``) and, over the free nodes and every frame after the first, relative to the
body size (``spread_rel_all`` in ``summary.json``): where the members disagree, none is to be
trusted.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from bsms.checkpoint import CheckpointError
from bsms.config import ConfigError
from bsms.data import NodeType, Scenario
from bsms.ensemble import spread as ensemble_spread
from bsms.models.ensemble import Ensemble
from bsms.rollouts import viz
from bsms.rollouts.motion import skill
from bsms.rollouts.rollout import DEFAULT_BOUND, body_size, rollout_metrics, rollouts
from bsms.run import load_model, resolve_device, run_dataset_config
from datagen.atomic import atomic_path
from datagen.compiled import cpu_summary
from datagen.config import output_folder
from datagen.dataset import DatasetError
from datagen.families import place
from datagen.generate import simulate_retrying
from datagen.mesh import Mesh, MeshError
from datagen.mpm.errors import SimulationError
from datagen.scenes import get_scene
from datagen.simulation import resolve_config
from datagen.surface import ClosedSurface, closed_surface, surface_arrays

from .surfaces import tetrahedralise_parts

__all__ = ["InferError", "infer", "main"]


# latency_ms of a model with independent frames: the mean over at most this many frames, one per call
LATENCY_FRAMES = 10


class InferError(ValueError):
    """An input of ``infer`` that cannot be used; the message names the file and the fix."""


def read_mesh(path, dim: int, run_dir) -> Mesh | ClosedSurface:
    """The mesh at ``path``, checked against the run's dimension; for a 3D run, a file holding a
    surface in 3D (STL, OBJ, triangles off z = 0: :func:`datagen.surface.surface_arrays`) is read as
    a closed surface (:func:`datagen.surface.closed_surface`), tetrahedralised once it is known
    where it goes (:mod:`bsms.infer.surfaces`)."""
    try:
        found = surface_arrays(path)
    except MeshError as exc:
        raise InferError(f"{exc} (fix or re-export the mesh, then try again)") from None
    if found is not None and dim != 3:
        raise InferError(f"mesh file {path} is a surface in 3D (triangles off the plane z = 0) but run {run_dir} was "
                         f"trained on {dim}D meshes; give a {dim}D mesh (.msh, .vtu; a 2D mesh with z = 0)")
    if found is not None:
        try:
            return closed_surface(*found, path)
        except MeshError as exc:
            raise InferError(str(exc)) from None
    try:
        mesh = Mesh.read(path)
    except MeshError as exc:
        raise InferError(f"{exc} (fix or re-export the mesh, then try again)") from None
    if mesh.dim != dim:
        raise InferError(f"mesh file {path} is {mesh.dim}D but run {run_dir} was trained on {dim}D meshes; "
                         f"give a {dim}D mesh")
    return mesh


def parse_overrides(items) -> dict:
    """``["E=2e4", "velocities=[[0, -0.3]]"]`` -> {"E": 20000.0, "velocities": [[0, -0.3]]}."""
    out = {}
    for item in items or ():
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--scene {item!r} must look like KEY=VALUE (a scene parameter, e.g. E=2e4)")
        value = yaml.safe_load(text)
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                pass
        out[key] = value
    return out


@dataclass
class _Placement:
    """Meshes placed together in the family's setting: the simulate() config, the scene, its
    scenario and initial state (all scenario nodes), frames and frame interval; where the scene's
    obstacles move, their stored nodes' positions at every frame (``obstacle_path`` (T, M, d))
    and the positions of all scenario nodes that prescribe the kinematic ones (``known``)."""

    paths: list[Path]
    setup_s: float
    sim_config: dict
    resolved: dict
    scene: object
    scenario: Scenario
    x0: np.ndarray
    v0: np.ndarray
    steps: int
    frame_dt: float
    obstacle_path: np.ndarray | None = None
    known: np.ndarray | None = None


def _obstacle_path(scene, steps: int, frame_dt: float) -> np.ndarray | None:
    """(steps + 1, M, d) positions of the scene's obstacle nodes at the frames of a rollout, or
    None where they stand still (or the scene cannot say where they go)."""
    obstacle_positions = getattr(scene, "obstacle_positions", None)
    if obstacle_positions is None or scene.obstacle_nodes is None or not len(scene.obstacle_nodes):
        return None
    return obstacle_positions(frame_dt * np.arange(steps + 1))


def _place(paths: list[Path], config, dconfig: dict, overrides: dict | None, steps: int | None,
           files: list[Path] | None = None) -> _Placement:
    """The meshes at ``paths`` (read from ``files`` where given: the tetrahedral meshes of surface
    files) placed in the family's setting, their scene and scenario built (timed: the learned side's
    per-mesh setup, ``setup_s``)."""
    start = time.perf_counter()
    sim_config = place(dconfig["family"], [str(p) for p in files or paths], dconfig, overrides or {})
    if steps is not None:
        sim_config.setdefault("output", {})["frames"] = int(steps)
    resolved = resolve_config(sim_config)
    scene = get_scene(resolved["scene"]).build(resolved["params"])
    frame_dt = float(resolved["output"]["frame_interval"])
    scenario = Scenario.build(
        scene.body, config.graph, frame_dt=frame_dt, node_type=scene.node_type, body_id=scene.body_id,
        obstacle_nodes=scene.obstacle_nodes, obstacle_facets=scene.obstacle_facets, params=resolved["params"],
        source=f"the scene of {', '.join(map(str, paths))}",
    )
    frames = int(resolved["output"]["frames"])
    path = _obstacle_path(scene, frames, frame_dt)
    body = scene.x[scene.tracked]
    known = None if path is None else scenario.positions(np.broadcast_to(body, (frames + 1, *body.shape)), path)
    x0 = scenario.full(body) if known is None else known[0]
    v0 = scenario.full(scene.v[scene.tracked][None], 0.0)[0]
    return _Placement(paths, time.perf_counter() - start, sim_config, resolved, scene, scenario, x0, v0, frames,
                      frame_dt, path, known)


def _summary(run_dir: Path, placed: _Placement, result, nodes: list[int], folder: Path, solver: bool,
             bound: float, members, timing: dict, started: float) -> dict:
    """What one rollout did (and, with ``solver``, its error and speed-up against the MPM solver;
    with ``members``, the rollouts of an ensemble's members alone, how far they disagree); writes
    its outputs and summary.json into ``folder``."""
    scenario, cells = placed.scenario, _reported_cells(placed.scene)
    n = int(cells.max()) + 1  # the given meshes' nodes: the body's first ones (datagen.refine)
    predicted = result.positions[:, :n]
    free, size = scenario.node_type[:n] == NodeType.FREE, body_size(placed.scene.body.nodes[:n])
    summary = {
        "run": str(run_dir), "meshes": [str(p) for p in placed.paths], "nodes": nodes,
        "body_nodes": scenario.n_body,
        "graph_nodes_per_level": [int(round(n)) for n in np.mean(result.graph_nodes, axis=0)],
        "graph_nodes_ratio": float(np.mean(result.graph_nodes[:, 0])) / scenario.n_body,
        "steps": len(predicted) - 1, "frame_dt": placed.frame_dt, "finite": result.finite,
        "seconds_per_step": result.seconds_per_step, "scene": placed.resolved["scene"],
        "params": placed.resolved["params"], "out": str(folder), "cpu": cpu_summary(), **timing,
    }
    spread = None
    if members is not None:
        spread, summary["spread_all"] = ensemble_spread(np.stack([m.positions[:, :n] for m in members]), free)
        summary.update(members=len(members), spread_rel_all=summary["spread_all"] / size)
    truth = None
    solver_wall = 0.0
    if solver:
        start = time.perf_counter()
        trajectory, summary["solver_cfl"] = simulate_stable(placed.sim_config)
        solver_wall = time.perf_counter() - start
        summary["solver_s"] = float(trajectory.setup_time or 0.0) + trajectory.wall_time
        summary["solver_preroll_s"] = float(trajectory.preroll_time or 0.0)
        summary["solver_seconds_per_step"] = summary["solver_s"] / placed.steps
        truth = trajectory.positions[:, :n]
        metrics = rollout_metrics(predicted, truth, free, size, bound)
        summary.update({k: metrics[k] for k in ("rmse_1", "rmse_50", "rmse_all", "rel_all", "unstable_step")})
        summary.update(skill(predicted, truth, free, size, metrics["rel_all"]))
        summary["speedup"] = summary["solver_s"] / (summary["setup_s"] + summary["learned_s"])
        summary["speedup_throughput"] = summary["solver_seconds_per_step"] / result.seconds_per_step
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    _write_outputs(folder, placed.scene, cells, predicted, truth, placed.frame_dt, placed.obstacle_path, spread)
    summary["outputs_s"] = time.perf_counter() - start
    # the whole call so far (model load, setup, rollouts, outputs), the solver's run not counted
    summary["call_s"] = time.perf_counter() - started - solver_wall
    with atomic_path(folder / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1, default=float))
    return summary


def simulate_stable(config: dict):
    """The solver on a simulate() config, then, where it goes non-finite, at half and a quarter of
    its CFL number (a body meshed about as coarse as the background mesh can need a smaller step
    than the data's bodies; not where ``solver.dt`` is fixed). Returns the trajectory and the CFL
    number that ran: the speed-up is against that run."""
    solver = resolve_config(config)["solver"]
    retry = [] if solver["dt"] else [solver["cfl"] / 2, solver["cfl"] / 4]
    try:
        trajectory, cfl = simulate_retrying(config, retry)
    except SimulationError as exc:
        tried = ", ".join(f"{c:g}" for c in [solver["cfl"], *retry])
        raise InferError(f"the MPM solver went non-finite on this placement at CFL {tried} ({exc}); run without "
                         "--solver, or mesh the body finer") from None
    return trajectory, solver["cfl"] if cfl is None else cfl


def _subfolders(folder: Path, paths: list[Path]) -> list[Path]:
    """One output folder per mesh inside ``folder``: its name, numbered where names repeat."""
    stems = [p.stem for p in paths]
    return [folder / (stem if stems.count(stem) == 1 else f"{stem}_{k}") for k, stem in enumerate(stems)]


def infer(run_dir, meshes, *, overrides: dict | None = None, steps: int | None = None, solver: bool = False,
          out=None, device: str = "cpu", which: str = "best", progress: bool = True,
          bound: float = DEFAULT_BOUND, separately: bool = False) -> dict:
    """Roll the run's model out on ``meshes`` (paths) placed in its family's setting: together in
    one scene, or with ``separately`` each alone in its own scene, all rolled out as one batch
    (outputs in one subfolder per mesh).

    Returns the summary written to ``summary.json`` (with ``out``, the output folder); with
    ``separately``, {"run", "out", "rollouts": the summary of each mesh}.
    """
    run_dir = Path(run_dir)
    started = time.perf_counter()
    model, config, state = load_model(run_dir, which)
    loaded = time.perf_counter() - started
    if config.dataset.kind != "mpm":
        raise InferError(f"run {run_dir} was trained on a converted {config.dataset.kind} dataset, not on an MPM "
                         f"family whose scene a mesh could be placed in; roll it out on its own data with "
                         f"python -m bsms.evaluate {run_dir} --no-solver")
    dim = int(state["dim"])
    paths = [Path(m) for m in meshes]
    if not paths:
        raise InferError("give at least one mesh file (--mesh FILE)")
    resolve_device(device, "--device")  # checked, with the output folder, before any work
    folder = Path(out) if out is not None else run_dir / "infer" / "_".join(p.stem for p in paths)
    output_folder(folder, "--out" if out is not None else "the output folder (give another with --out)")
    parts = {p: read_mesh(p, dim, run_dir) for p in paths}
    dconfig = run_dataset_config(run_dir, config)
    groups = [[p] for p in paths] if separately else [paths]
    volumes = _tetrahedralise(parts, groups, dconfig, overrides, folder)
    nodes = {p: (volumes[p].mesh if p in volumes else parts[p]).n_nodes for p in paths}
    placed = [_place(group, config, dconfig, overrides, steps, [volumes[p].file if p in volumes else p for p in group])
              for group in groups]

    def roll_out(m, shown: bool, per_call: int | None = None, warmup: int = 0, most: int | None = None):
        # independent frames (graph.from_rest): all in one call unless per_call says otherwise
        return rollouts(m, [p.scenario for p in placed], [p.x0 for p in placed], [p.v0 for p in placed],
                        [min(p.steps, most or p.steps) for p in placed], [p.known for p in placed], device=device,
                        progress=shown, frames_per_call=per_call or max(p.steps for p in placed), warmup=warmup)

    start = time.perf_counter()
    results = roll_out(model, progress)  # what the user waits for: no untimed warm-up call
    learned = (time.perf_counter() - start) / len(placed)  # with --separately, each mesh's share of the batch
    latency = results
    if config.graph.from_rest and max(p.steps for p in placed) > 1:  # one frame per call, after a warm-up call
        latency = roll_out(model, False, per_call=1, warmup=1, most=LATENCY_FRAMES)
    members = [None] * len(placed)
    if isinstance(model, Ensemble):  # each member alone, untimed: how far they disagree
        members = list(zip(*[roll_out(member, False) for member in model.members], strict=True))
    folders = _subfolders(folder, paths) if separately else [folder]
    summaries = [_summary(run_dir, p, result, [nodes[m] for m in p.paths], where, solver, bound, alone,
                          {"setup_s": p.setup_s, "learned_s": learned, "latency_ms": 1e3 * one.seconds_per_step,
                           "model_load_s": loaded, **_meshed(volumes, p.paths)}, started)
                 for p, result, where, alone, one in zip(placed, results, folders, members, latency, strict=True)]
    if not separately:
        return summaries[0]
    summary = {"run": str(run_dir), "out": str(folder), "rollouts": summaries}
    with atomic_path(folder / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1, default=float))
    return summary


def _tetrahedralise(parts: dict, groups: list[list[Path]], dconfig: dict, overrides: dict | None, folder: Path) -> dict:
    """The surface files among ``parts`` tetrahedralised at the run's spacing (:mod:`bsms.infer.surfaces`),
    each written to ``folder/<name>_tetrahedra.vtu``."""
    paths = list(parts)
    files = {p: folder / f"{sub.name}_tetrahedra.vtu" for p, sub in zip(paths, _subfolders(folder, paths), strict=True)}
    try:
        return tetrahedralise_parts(parts, groups, dconfig, overrides, files)
    except MeshError as exc:
        raise InferError(str(exc)) from None


def _meshed(volumes: dict, paths: list[Path]) -> dict:
    """summary.json's record of the surface files among ``paths`` that were tetrahedralised:
    ``tetrahedralised`` (each one's file, size, nodes, time) and ``meshing_s``, their total time
    (apart from ``setup_s`` and the solver's time: both sides start from the tetrahedra)."""
    done = [volumes[p] for p in dict.fromkeys(paths) if p in volumes]
    if not done:
        return {}
    return {"tetrahedralised": [v.record() for v in done], "meshing_s": sum(v.seconds for v in done)}


def _reported_cells(scene) -> np.ndarray:
    """The cells everything is reported on: the given meshes' where the scene refined them (the
    model and the solver ran on the finer body; the given nodes are its first ones), else the body's."""
    return scene.body.cells if scene.given_cells is None else scene.given_cells


def _write_outputs(folder: Path, scene, cells: np.ndarray, predicted: np.ndarray, truth, frame_dt: float,
                   obstacle_path: np.ndarray | None = None, spread: np.ndarray | None = None) -> None:
    times = frame_dt * np.arange(len(predicted))
    data = {} if spread is None else {"spread": spread}
    if truth is not None:
        data["error"] = np.linalg.norm(predicted - truth[: len(predicted)], axis=-1)
    viz.write_xdmf(folder / "prediction.xdmf", cells, predicted, times, data)
    if truth is not None:
        viz.write_xdmf(folder / "solver.xdmf", cells, truth[: len(predicted)], times)
    obstacles = None
    if scene.obstacle_nodes is not None and len(scene.obstacle_nodes):
        nodes = scene.obstacle_nodes if obstacle_path is None else obstacle_path[: len(predicted)]
        obstacles = (nodes, scene.obstacle_facets)
    viz.rollout_gif(cells, predicted, folder / "prediction.gif", truth=truth, obstacles=obstacles,
                    frame_dt=frame_dt)


def main(argv=None, prog: str = "python -m bsms.infer") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a run folder written by train.py (runs/<name>)")
    parser.add_argument("--mesh", action="append", required=True,
                        help="mesh file (repeat for several bodies); a 3D run also takes a part's closed surface "
                             "(STL, OBJ), tetrahedralised at the model's spacing")
    parser.add_argument("--scene", action="append", default=[], metavar="KEY=VALUE",
                        help="change a scene parameter of the placement (repeatable), e.g. --scene E=2e4")
    parser.add_argument("--steps", type=int, default=None, help="rollout steps (default: the dataset's frames)")
    parser.add_argument("--solver", action="store_true", help="also run the MPM solver and report the error")
    parser.add_argument("--out", default=None, help="output folder (default: RUN_DIR/infer/<mesh name>)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    parser.add_argument("--checkpoint", default="best", choices=["best", "latest"], help="which checkpoint")
    parser.add_argument("--separately", action="store_true",
                        help="each mesh alone in its own scene, all rolled out as one batch (one subfolder each)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.steps is not None and args.steps < 1:
        print("error: --steps must be >= 1", file=sys.stderr)
        return 2
    try:
        summary = infer(args.run_dir, args.mesh, overrides=parse_overrides(args.scene), steps=args.steps,
                        solver=args.solver, out=args.out, device=args.device, which=args.checkpoint,
                        progress=not args.quiet, separately=args.separately)
    except (InferError, CheckpointError, ConfigError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for one in summary.get("rollouts", [summary]):
        for volume in one.get("tetrahedralised", []):
            print(f"{volume['surface']}: tetrahedralised at {volume['size']:.4g} (the model's spacing "
                  f"{volume['spacing']:g} at the family's scale) into {volume['mesh']}: {volume['nodes']} nodes, "
                  f"{volume['cells']} tetrahedra, {volume['seconds']:.3g} s")
        print(_describe(one))
        solver = ", solver.xdmf" if "rmse_all" in one else ""
        print(f"outputs in {one['out']}: prediction.xdmf{solver} (ParaView), prediction.gif, summary.json")
    return 0


def _describe(summary: dict) -> str:
    """One line on one rollout's summary."""
    refined = (f", refined to {summary['body_nodes']} for the model and the solver"
               if summary["body_nodes"] > sum(summary["nodes"]) else "")
    line = (f"{summary['steps']} steps on {sum(summary['nodes'])} nodes{refined} "
            f"({summary['latency_ms']:.1f} ms per frame one at a time, {summary['seconds_per_step'] * 1e3:.1f} "
            f"batched; levels {summary['graph_nodes_per_level']})")
    if "rmse_all" in summary:
        line += (f"; against the solver: RMSE {summary['rmse_all']:.3g} m ({summary['rel_all']:.3g} of the body "
                 f"size; {summary['vs_rest']:.3g} of predicting no motion), speed-up {summary['speedup']:.3g}x end "
                 f"to end ({summary['speedup_throughput']:.3g}x throughput; the solver at CFL "
                 f"{summary['solver_cfl']:g}: {summary['solver_s']:.3g} s against {summary['setup_s']:.3g} s of "
                 f"setup and {summary['learned_s']:.3g} s of rollout; the whole call {summary['call_s']:.3g} s with "
                 f"loading the model, the latency measurement and writing the outputs, the solver's run not counted)")
    if "members" in summary:
        line += (f"; the mean of {summary['members']} members, who disagree by {summary['spread_rel_all']:.3g} "
                 f"of the body size")
    if not summary["finite"]:
        line += "; the rollout went non-finite"
    return line

