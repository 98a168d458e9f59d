"""How far the body's linear-elastic answer goes alone: ``graph.elastic``'s input as a predictor.

For each trajectory of a split, every frame is predicted as the rest shape plus the input
``graph.elastic`` gives a model (:mod:`bsms.physics.elastic`: linear elasticity on the rest mesh,
held where it touches the container, pushed along the penetration vectors of the indenter at
that frame as a frictionless contact) -- no learning. It is the trivial answer a model with that
input has to beat, scored as learned rollouts are (``vs at rest``: RMSE over all steps over the
at-rest RMSE; RMSE all relative to the body size). One row per hold distance (in median rest
edges; the first is the input's). ``--scale`` adds a table of the factor that best scales each
trajectory's answer to its data (1: the answer's size is right). Ends with exactly (for the
first hold)

    elastic answer: vs at rest E on N trajectories (hold H edges), P ms per frame

    python benchmarks/elastic_answer.py --data data/press_stiff [--split test] [--hold 1.0 0.05 0.5] [--scale]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from ensemble import row, score  # noqa: E402

from bsms.config import ConfigError  # noqa: E402
from bsms.data import Scenario  # noqa: E402
from bsms.fields import FieldSpec, world_positions  # noqa: E402
from bsms.options import GraphOptions  # noqa: E402
from bsms.physics.elastic import HOLD, ElasticResponse  # noqa: E402
from bsms.rollouts.solver_runs import free_nodes  # noqa: E402
from bsms.run import split_files  # noqa: E402
from datagen.dataset import load  # noqa: E402


def answers(trajectory, hold: float) -> tuple[np.ndarray, float]:
    """(T, N, d) the rest shape plus the elastic answer at every frame, and the seconds per frame
    it took (penetration and solve, all frames together as a rollout builds them; the
    factorisation, once per mesh, not counted)."""
    options = GraphOptions(levels=1, from_rest=True, penetration=True)
    scenario = Scenario.from_trajectory(trajectory, options)
    n = scenario.n_body
    elastic = ElasticResponse(scenario.rest_pos, scenario.obstacle_geometry.facets + n, n, scenario.cells,
                              trajectory.config["params"].get("nu"), float(np.median(trajectory.mesh.edge_lengths)),
                              hold)
    free = np.arange(scenario.n_nodes) < n
    out = np.empty_like(trajectory.positions)
    start = time.perf_counter()
    loads = []
    for obstacles in trajectory.obstacle_positions:
        pos = scenario.positions(scenario.rest_pos[:n], obstacles)
        loads.append(scenario.penetration(pos, pos, free))
    # as a rollout of a model predicting from rest builds its frames: all of them at once
    out[:] = scenario.rest_pos[:n] + np.stack(elastic.many(loads))[:, :n]
    return out, (time.perf_counter() - start) / len(out)


def best_scale(predicted: np.ndarray, trajectory, spec) -> float:
    """The factor s that brings the answer's displacements u (``predicted`` less the rest mesh)
    closest to the data's d from its first frame (least squares over the free nodes of every
    frame): s = sum d.u / sum u.u; 1 where the answer's size is right, above 1 where the body
    moves further than the answer says (nan if it never moves)."""
    truth = world_positions(spec, trajectory)[: len(predicted)]
    free = free_nodes(trajectory)
    d, u = (truth - truth[:1])[:, free], (predicted - trajectory.mesh.nodes)[:, free]
    norm = float((u * u).sum())
    return float((d * u).sum()) / norm if norm > 0 else float("nan")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, type=Path, help="a dataset folder of a driven family (press, bracket)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--trajectories", type=int, default=None, help="at most this many (default: all)")
    parser.add_argument("--hold", type=float, nargs="+", default=[HOLD],
                        help=f"hold distances in median rest edges, the first reported last (default: {HOLD})")
    parser.add_argument("--scale", action="store_true",
                        help="also print, per row, the factor that best scales the answer to the data per trajectory")
    args = parser.parse_args(argv)
    try:
        files = split_files(args.data, args.split)[: args.trajectories]
    except ConfigError as exc:
        parser.error(str(exc))
    trajectories = [load(path) for path in files]
    if any(t.obstacle_positions is None for t in trajectories):
        parser.error(f"{args.data}: the elastic answer needs moving obstacles (an indenter) to load the body")
    spec = FieldSpec.lagrangian(trajectories[0].mesh.dim)
    print("| hold (median edges) | vs at rest (per trajectory) | RMSE all / body size |")
    print("|---|---|---|")
    summary, scales = None, []
    for hold in args.hold:
        scored, seconds, factors = [], [], []
        for trajectory in trajectories:
            predicted, per_frame = answers(trajectory, hold)
            scored.append(score(predicted, trajectory, spec))
            seconds.append(per_frame)
            factors.append(best_scale(predicted, trajectory, spec))
        label = f"{hold:g}"
        print(row(label, scored), flush=True)
        scales.append(f"| {label} | {np.median(factors):.3g} ({', '.join(f'{f:.2f}' for f in factors)}) |")
        if summary is None:
            summary = (np.mean([m["vs_rest"] for m in scored]), hold, 1e3 * np.mean(seconds))
    if args.scale:
        print("\n| hold (median edges) | data / answer, median (per trajectory) |")
        print("|---|---|")
        print("\n".join(scales))
    vs, hold, ms = summary
    print(f"elastic answer: vs at rest {vs:.3g} on {len(trajectories)} trajectories (hold {hold:g} edges), "
          f"{ms:.3g} ms per frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
