"""A press model on shapes of no split, against the solver: the check behind the README's zero-shot row.

Three bodies no press split draws -- a five-pointed star, an L bracket and a plate with a V notch,
about 11 cm across, meshed by gmsh (``datagen.shapes.polygon``) at ``--size`` -- are each placed
alone by ``bsms.infer`` in the family's setting (the family's box and bonded floor, mid-range
material, a disk pressing straight down; a mesh coarser than the family's bodies subdivided to
their resolution, the outputs on its own nodes) and rolled out by the model and by the MPM solver at
the data's settings, one ``bsms.infer.infer`` call per shape, exactly as ``python -m bsms.infer RUN
--mesh F --solver`` does. Prints one row per shape (nodes, the error and the error of predicting no
motion as a fraction of the body size, their ratio ``vs at rest``, the speed-up end to end over
the solver timed in this run, and the whole call as a caller timing ``infer`` sees it: its
``call_s`` -- loading the model, the setup, the rollout, the latency measurement and writing the
outputs, the solver's run not counted -- and the solver's time over it), then ends with exactly

    zero-shot: vs at rest star A, L bracket B, notched plate C (max M), speedup S0-S1 x

``--shapes wide`` takes sixteen shapes instead (``wider_set``: those three and thirteen more -- T,
U channel, arch, disk, trapezoid, hexagon, cross, column, slab, inverted triangle, step, a plate
with a hole, a ring; about 10 minutes) and ends with exactly

    zero-shot: vs at rest mean A on 16 shapes, above 0.5 on K (max M, NAME), speedup S0-S1 x

``--scene KEY=VALUE ...`` changes scene parameters as ``bsms.infer``'s ``--scene`` does (e.g.
``grid_ratio=1.5``: a model trained on one family's data, the solver on another's grid).

    python benchmarks/press_zero_shot.py [RUN] [--size 0.004] [--checkpoint best|latest] [--out DIR]
        [--scene KEY=VALUE ...] [--shapes three|wide]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from bsms.infer import infer, parse_overrides  # noqa: E402
from datagen import shapes  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def outlines() -> dict[str, np.ndarray]:
    """The three outlines (m, counter-clockwise), named as the last line names them."""
    angles = np.pi / 2 + np.arange(10) * np.pi / 5
    radii = np.where(np.arange(10) % 2 == 0, 0.057, 0.024)
    star = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    bracket = np.array([[0.0, 0.0], [0.11, 0.0], [0.11, 0.035], [0.035, 0.035], [0.035, 0.11], [0.0, 0.11]])
    notched = np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.06], [0.07, 0.06], [0.06, 0.032], [0.05, 0.06],
                        [0.0, 0.06]])
    return {"star": star, "L bracket": bracket, "notched plate": notched}


def circle(radius: float, corners: int, center=(0.0, 0.0), start: float = 0.0, stop: float = 2 * np.pi) -> np.ndarray:
    """``corners`` points on the circle from angle ``start`` to ``stop`` (a whole turn: the last
    point before the first again; an arc: both ends included)."""
    angles = np.linspace(start, stop, corners, endpoint=stop - start < 2 * np.pi - 1e-9)
    return np.stack([center[0] + radius * np.cos(angles), center[1] + radius * np.sin(angles)], axis=1)


def wider_set() -> dict[str, tuple[np.ndarray, list[np.ndarray]]]:
    """Sixteen bodies of no split, (outline, holes) by name (m): the three of :func:`outlines`,
    then the shapes of parts a user presses -- T, U channel, arch, disk, trapezoid, hexagon,
    cross, column, slab, inverted triangle, step, a plate with a hole and a ring."""
    arch = np.array([[0.0, 0.0], [0.025, 0.0]] + [[0.055 - 0.03 * np.cos(t), 0.03 * np.sin(t)]
                                                  for t in np.linspace(0.0, np.pi, 15)[1:-1]]
                    + [[0.085, 0.0], [0.11, 0.0], [0.11, 0.06], [0.0, 0.06]])
    rings = {
        **outlines(),
        "T": np.array([[0.035, 0.0], [0.065, 0.0], [0.065, 0.07], [0.11, 0.07], [0.11, 0.1], [-0.01, 0.1],
                       [-0.01, 0.07], [0.035, 0.07]]),
        "U channel": np.array([[0.0, 0.0], [0.11, 0.0], [0.11, 0.09], [0.08, 0.09], [0.08, 0.03], [0.03, 0.03],
                               [0.03, 0.09], [0.0, 0.09]]),
        "arch": arch,
        "disk": circle(0.05, 40),
        "trapezoid": np.array([[0.0, 0.0], [0.12, 0.0], [0.085, 0.07], [0.035, 0.07]]),
        "hexagon": circle(0.055, 6),
        "cross": np.array([[0.035, 0.0], [0.07, 0.0], [0.07, 0.035], [0.105, 0.035], [0.105, 0.07], [0.07, 0.07],
                           [0.07, 0.105], [0.035, 0.105], [0.035, 0.07], [0.0, 0.07], [0.0, 0.035],
                           [0.035, 0.035]]),
        "column": np.array([[0.0, 0.0], [0.035, 0.0], [0.035, 0.11], [0.0, 0.11]]),
        "slab": np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.04], [0.0, 0.04]]),
        "inverted triangle": np.array([[0.05, 0.0], [0.07, 0.0], [0.12, 0.08], [0.0, 0.08]]),
        "step": np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.04], [0.06, 0.04], [0.06, 0.09], [0.0, 0.09]]),
        "plate with hole": np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.09], [0.0, 0.09]]),
        "ring": circle(0.055, 48),
    }
    holes = {"plate with hole": [circle(0.02, 32, (0.06, 0.045))], "ring": [circle(0.03, 40)]}
    return {name: (ring, holes.get(name, [])) for name, ring in rings.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", nargs="?", default=str(ROOT / "pretrained" / "press2d"),
                        help="a press run or pretrained folder (default: pretrained/press2d)")
    parser.add_argument("--size", type=float, default=0.004, help="mesh element size, m (default 0.004)")
    parser.add_argument("--checkpoint", default="best", choices=["best", "latest"])
    parser.add_argument("--out", default=None, help="keep the outputs here (default: a temporary folder)")
    parser.add_argument("--scene", nargs="*", default=[], metavar="KEY=VALUE",
                        help="scene parameters over the family's, as bsms.infer's --scene (e.g. grid_ratio=1.5: "
                             "the solver on another family's grid)")
    parser.add_argument("--shapes", default="three", choices=["three", "wide"],
                        help="the three shapes (default), or sixteen (wider_set: the three and thirteen more)")
    args = parser.parse_args(argv)
    overrides = parse_overrides(args.scene)
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(args.out) if args.out else Path(scratch) / "out"
        names, files = [], []
        bodies = wider_set() if args.shapes == "wide" else {name: (ring, []) for name, ring in outlines().items()}
        for name, (ring, holes) in bodies.items():
            path = Path(scratch) / f"{name.replace(' ', '_')}.msh"
            shapes.polygon(ring, holes, size=args.size).write(str(path))
            names.append(name)
            files.append(str(path))
        rows = [infer(args.run, [file], overrides=overrides, solver=True, out=out / Path(file).stem,
                      which=args.checkpoint, progress=False) for file in files]
    print("| shape | nodes (refined) | RMSE all / body size | at rest / body size | vs at rest "
          "| ms per frame (model batched, one per call, solver) | speed-up end to end | whole call (s) "
          "| solver (s) / whole call |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, row in zip(names, rows, strict=True):
        print(f"| {name} | {sum(row['nodes'])} ({row['body_nodes']}) | {100 * row['rel_all']:.3g}% "
              f"| {100 * row['rest_rel_all']:.3g}% "
              f"| {row['vs_rest']:.3g} | {1e3 * row['seconds_per_step']:.3g}, {row['latency_ms']:.3g}, "
              f"{1e3 * row['solver_seconds_per_step']:.3g} | {row['speedup']:.3g}x | {row['call_s']:.3g} "
              f"| {row['solver_s'] / row['call_s']:.3g}x |")
    skills = [row["vs_rest"] for row in rows]
    speedups = [row["speedup"] for row in rows]
    speed = f"speedup {min(speedups):.3g}-{max(speedups):.3g} x"
    if args.shapes == "wide":
        worst = int(np.argmax(skills))
        print(f"zero-shot: vs at rest mean {np.mean(skills):.3g} on {len(skills)} shapes, above 0.5 on "
              f"{sum(s > 0.5 for s in skills)} (max {skills[worst]:.3g}, {names[worst]}), {speed}")
        return 0
    parts = ", ".join(f"{name} {value:.3g}" for name, value in zip(names, skills, strict=True))
    print(f"zero-shot: vs at rest {parts} (max {max(skills):.3g}), {speed}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
