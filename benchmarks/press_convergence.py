"""Are the press family's solver settings the ones it needs? A convergence check on stored trajectories.

For the first ``--trajectories`` files of a split, re-runs each generating config (one thread)

* with the background mesh 2x finer (``params.mesh_size / 2`` and ``params.grid_ratio / 2``, so
  a background that follows the body's spacing halves too; the body mesh, whose vertices are the
  tracked points, unchanged),
* with the background mesh and the body mesh 2x finer (the body's own mesh subdivided once,
  :func:`datagen.refine.subdivide`, compared at its original nodes): where a body is meshed at
  about the background's spacing, halving the background alone leaves about one particle per
  cell and measures that, not convergence (press_stiff's polygons: 1.5-1.7% of the body size
  against 0.04% with both refined),
* with the other reference configuration: A-ULMPM ``adaptive`` where the data used the plain
  updated-Lagrangian solver (``solver.reference: eulerian``, the family's setting), ``eulerian``
  where it used ``adaptive``,
* with a 3x smaller time step (``solver.cfl / 3``, or ``solver.dt / 3`` where it is fixed): the
  data is made at the largest CFL number the solver takes (1), which is adequate when this
  check stays within a tenth of the target,
* with the body set down half a background cell further along x (the box widened by one cell of
  the background the body had, :func:`datagen.scenes.press.background_spacing`,
  the body and its indenter centred in it; y for a body clamped to the left wall, centred in the
  box's height; compared after shifting back): how much the result
  depends on where the body sits on the grid -- what no model that sees only relative positions
  can learn,

and reports how far each moves the stored rollout: RMSE over all frames and free body nodes,
relative to the body size (the measure the surrogate's accuracy target uses), beside the at-rest
error of the data and of the check's run (how much each deforms: a finer grid that deforms a
thin body more shows there). The data's
settings are adequate when the finer mesh stays below the target. Ends with exactly
``press convergence: finer mesh rel A (max B), finer mesh and body rel C (max D), <other
reference> rel E (max F), smaller step rel G (max H), grid shift rel I (max J), target T``
(``--checks`` runs some of them; the line then names only those).

    python benchmarks/press_convergence.py [--data data/press_bonded] [--split test] [--trajectories 2]
        [--checks "finer mesh" ...]
"""

from __future__ import annotations

import argparse
import copy
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from bsms.rollouts.motion import motion_parts  # noqa: E402
from bsms.rollouts.rollout import body_size, rollout_metrics  # noqa: E402
from bsms.rollouts.solver_runs import free_nodes  # noqa: E402
from datagen import simulate  # noqa: E402
from datagen.dataset import load  # noqa: E402
from datagen.refine import subdivide  # noqa: E402
from datagen.scenes import get_scene  # noqa: E402
from datagen.scenes.press import background_spacing  # noqa: E402

CHECKS = {
    "finer mesh": lambda c, t: finer_grid(c["params"]),
    "finer mesh and body": lambda c, t: finer_body(c, t),
    "other reference": lambda c, t: c["solver"].update(reference=other_reference(c)),
    "smaller step": lambda c, t: smaller_step(c["solver"]),
    "grid shift": lambda c, t: c["params"].update(box=widened(c["params"])),
}
# where a check's run stands against the data's: "grid shift" sets the body down half a cell on
SHIFTS = {"grid shift": lambda c: np.eye(len(c["params"]["box"]) // 2)[_axis(c["params"])] * spacing(c["params"]) / 2}


def spacing(params: dict) -> float:
    """The background spacing a press config ran with: ``mesh_size``, finer where ``grid_ratio``
    times the body's own spacing is."""
    return background_spacing(get_scene("press").params(params))


def finer_grid(params: dict) -> None:
    """The background twice as fine: ``mesh_size`` and ``grid_ratio`` (where set) halved."""
    params.update(mesh_size=params["mesh_size"] / 2)
    if params.get("grid_ratio"):
        params.update(grid_ratio=params["grid_ratio"] / 2)


def _axis(params: dict) -> int:
    """The axis along which the scene centres its body in the box: x on the floor, y for a body
    clamped to the left wall (centred in the box's height)."""
    return 1 if params.get("base") == "clamped" else 0


def widened(params: dict) -> list:
    """The box one background cell larger along :func:`_axis`: the body, centred along it, moves
    half a cell against the grid, which starts at the box's lower corner."""
    box = list(params["box"])
    box[len(box) // 2 + _axis(params)] += spacing(params)
    return box


def finer_body(config: dict, trajectory) -> None:
    """The background mesh 2x finer and the body the trajectory's own mesh subdivided once (its
    nodes first, so the stored ones are compared), given inline (``params.mesh``): where it
    stands and how it is posed already (press scenes set a given mesh down as they set any body)."""
    fine = subdivide(trajectory.mesh)
    params = config["params"]
    params.pop("char", None)
    finer_grid(params)  # before the body is given inline: the spacing that follows it stays its own
    params.update(polygon=None, mesh={"nodes": fine.nodes.tolist(), "cells": fine.cells.tolist()})


def smaller_step(solver: dict) -> None:
    """A 3x smaller time step: solver.dt / 3 where the data fixed it, else solver.cfl / 3."""
    if solver.get("dt"):
        solver["dt"] = solver["dt"] / 3
    else:
        solver["cfl"] = solver.get("cfl", 0.3) / 3


def other_reference(config: dict) -> str:
    """The reference configuration compared with the data's: adaptive for eulerian data, else eulerian."""
    return "adaptive" if config["solver"].get("reference", "eulerian") == "eulerian" else "eulerian"


def label(name: str, config: dict) -> str:
    """A check's name as reported: the other reference's own name for ``other reference``."""
    return other_reference(config) if name == "other reference" else name


def check(trajectory, name: str) -> dict:
    config = copy.deepcopy(trajectory.config)
    config["solver"]["threads"] = 1
    config["output"]["step_diagnostics"] = False
    CHECKS[name](config, trajectory)
    start = time.perf_counter()
    other = simulate(config)
    n = trajectory.mesh.n_nodes  # a refined body's own nodes come first
    shift = SHIFTS[name](trajectory.config) if name in SHIFTS else 0.0
    moved = other.positions[:, :n] - shift
    metrics = rollout_metrics(moved, trajectory.positions, free_nodes(trajectory), body_size(trajectory.mesh.nodes))
    return {"rel_all": metrics["rel_all"], "rest_rel_all": at_rest(moved, trajectory),
            "seconds": time.perf_counter() - start, "substeps": other.substeps}


def at_rest(positions: np.ndarray, trajectory) -> float:
    """The at-rest error of ``positions`` (T, N, d) of ``trajectory``'s body (the error of
    predicting frame 0 throughout, relative to the body size: how much it deforms, the yardstick
    ``vs at rest`` divides by; :func:`bsms.rollouts.motion.motion_parts`)."""
    return motion_parts(positions, free_nodes(trajectory), body_size(trajectory.mesh.nodes))["rest_rel_all"]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data/press_bonded"),
                        help="dataset folder (default data/press_bonded, configs/datasets/press.yaml's)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--trajectories", type=int, default=2)
    parser.add_argument("--target", type=float, default=0.005, help="accuracy target, relative (default 0.005)")
    parser.add_argument("--checks", nargs="+", choices=list(CHECKS), default=list(CHECKS), metavar="CHECK",
                        help=f"which checks to run (default all: {', '.join(CHECKS)})")
    args = parser.parse_args(argv)
    files = sorted((args.data / args.split).glob("*.h5"))[: args.trajectories]
    if not files:
        raise SystemExit(f"no trajectories in {args.data / args.split}; generate them with python -m datagen")
    results = {name: [] for name in args.checks}
    print("| trajectory | E (MPa) | data substeps/frame | data at rest | check | substeps/frame | rel RMSE all "
          "| check's at rest | solver s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for path in files:
        trajectory = load(path)
        for name in args.checks:
            r = check(trajectory, name)
            results[name].append(r["rel_all"])
            print(f"| {path.name} | {trajectory.config['params']['E'] / 1e6:.2f} | {trajectory.substeps} "
                  f"| {at_rest(trajectory.positions, trajectory):.3g} | {label(name, trajectory.config)} "
                  f"| {r['substeps']} | {r['rel_all']:.3g} | {r['rest_rel_all']:.3g} | {r['seconds']:.0f} |",
                  flush=True)
    parts = [f"{label(name, trajectory.config)} rel {np.mean(values):.3g} (max {np.max(values):.3g})"
             for name, values in results.items()]
    print(f"press convergence: {', '.join(parts)}, target {args.target:g}")


if __name__ == "__main__":
    main()
