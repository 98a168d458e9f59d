"""A press model on shapes of no split, against the solver: the check behind the README's zero-shot row.

Three bodies no press split draws -- a five-pointed star, an L bracket and a plate with a V notch,
about 11 cm across, meshed by gmsh (``datagen.shapes.polygon``) at ``--size`` -- are each placed
alone by ``bsms.infer`` in the family's setting (the family's box and bonded floor, mid-range
material, a disk pressing straight down; a mesh coarser than the family's bodies subdivided to
their resolution, the outputs on its own nodes) and rolled out by the model and by the MPM solver at
the data's settings, exactly as ``python -m bsms.infer RUN --mesh F --separately --solver`` does.
Prints one row per shape (nodes, the error and the error of predicting no motion as a fraction
of the body size, their ratio ``vs at rest``, the speed-up over the solver timed in this run),
then ends with exactly

    zero-shot: vs at rest star A, L bracket B, notched plate C (max M), speedup S0-S1 x

``--scene KEY=VALUE ...`` changes scene parameters as ``bsms.infer``'s ``--scene`` does (e.g.
``grid_ratio=1.5``: a model trained on one family's data, the solver on another's grid).

    python benchmarks/press_zero_shot.py [RUN] [--size 0.004] [--checkpoint best|latest] [--out DIR]
        [--scene KEY=VALUE ...]
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
    args = parser.parse_args(argv)
    overrides = parse_overrides(args.scene)
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(args.out) if args.out else Path(scratch) / "out"
        names, files = [], []
        for name, ring in outlines().items():
            path = Path(scratch) / f"{name.replace(' ', '_')}.msh"
            shapes.polygon(ring, size=args.size).write(str(path))
            names.append(name)
            files.append(str(path))
        summary = infer(args.run, files, overrides=overrides, solver=True, separately=True, out=out,
                        which=args.checkpoint, progress=False)
    rows = summary["rollouts"]
    print("| shape | nodes (refined) | RMSE all / body size | at rest / body size | vs at rest "
          "| ms per frame (model, solver) | speed-up |")
    print("|---|---|---|---|---|---|---|")
    for name, row in zip(names, rows, strict=True):
        print(f"| {name} | {sum(row['nodes'])} ({row['body_nodes']}) | {100 * row['rel_all']:.3g}% "
              f"| {100 * row['rest_rel_all']:.3g}% "
              f"| {row['vs_rest']:.3g} | {1e3 * row['seconds_per_step']:.3g}, "
              f"{1e3 * row['solver_seconds_per_step']:.3g} | {row['speedup']:.3g}x |")
    skills = [row["vs_rest"] for row in rows]
    speedups = [row["speedup"] for row in rows]
    parts = ", ".join(f"{name} {value:.3g}" for name, value in zip(names, skills, strict=True))
    print(f"zero-shot: vs at rest {parts} (max {max(skills):.3g}), "
          f"speedup {min(speedups):.3g}-{max(speedups):.3g} x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
