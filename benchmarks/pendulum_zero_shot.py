"""A pendulum model on plates of no split, against the solver: the zero-shot check of issue 67.

Six plates no pendulum split draws -- an arch, a plate with a V notch, a step, a trapezoid, a
hexagon and a crescent -- each with a round hole for the pin (6.75 mm, the family's mid-range pin,
away from the centroid), are meshed the way the family meshes its plates (``datagen.scenes.pendulum.plate``:
2.5 mm, the hole a polygon of nodes on its circle, 9.5 cm across) and hung alone by ``bsms.infer``
in the family's setting (``datagen.families.pendulum.place``: mid-range material, 55 degrees of
swing, started straight down), rolled out by the model and by the MPM solver at the data's
settings, one ``bsms.infer.infer`` call per plate, as ``python -m bsms.infer RUN --mesh F --solver``
does. Prints one row per plate (nodes, the model's error and the error of predicting no motion as
fractions of the body size, their ratio ``vs at rest``, ms per frame of the model one frame per
call and of the solver, the speed-up end to end), then ends with exactly

    zero-shot: vs at rest mean A on N plates, above 0.5 on K (max M, NAME), speedup S0-S1 x

    python benchmarks/pendulum_zero_shot.py [RUN] [--checkpoint best|latest] [--out DIR] [--scene KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from press_zero_shot import circle  # noqa: E402

from bsms.infer import infer, parse_overrides  # noqa: E402
from datagen.scenes import get_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SIZE, PIN, SPACING = 0.095, 0.00675, 0.0025  # m: the family's mid-range plate and pin, its plates' mesh size


def plates() -> dict[str, tuple[np.ndarray, tuple[float, float]]]:
    """(outline, pivot) by name, in the outline's own units (scaled to 9.5 cm when meshed)."""
    arch = np.concatenate([[[0.0, 0.0], [0.025, 0.0]],
                           circle(0.03, 15, (0.055, 0.0), np.pi, 0.0)[1:-1],
                           [[0.085, 0.0], [0.11, 0.0], [0.11, 0.06], [0.0, 0.06]]])
    # the disk of radius 0.05 less the disk of radius 0.04 about (0.03, 0): they cross at (0.03, +-0.04)
    horn = np.arctan2(0.04, 0.03)
    crescent = np.concatenate([circle(0.05, 40, (0.0, 0.0), horn, 2 * np.pi - horn),
                               circle(0.04, 30, (0.03, 0.0), 1.5 * np.pi, 0.5 * np.pi)[1:-1]])
    return {
        "arch": (arch, (0.0125, 0.045)),
        "notched plate": (np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.06], [0.07, 0.06], [0.06, 0.032],
                                    [0.05, 0.06], [0.0, 0.06]]), (0.02, 0.04)),
        "step": (np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.04], [0.06, 0.04], [0.06, 0.09], [0.0, 0.09]]),
                 (0.03, 0.07)),
        "trapezoid": (np.array([[0.0, 0.0], [0.12, 0.0], [0.085, 0.07], [0.035, 0.07]]), (0.06, 0.05)),
        "hexagon": (circle(0.055, 6), (0.0, 0.03)),
        "crescent": (crescent, (-0.025, 0.03)),
    }


def write_plates(folder: Path) -> dict[str, Path]:
    """Each plate of :func:`plates` meshed as the family meshes its own, as a .msh file in ``folder``."""
    scene = get_scene("pendulum")
    files = {}
    for name, (outline, pivot) in plates().items():
        p = scene.params({"polygon": outline.tolist(), "pivot": list(pivot), "size": SIZE,
                          "pin_radius": PIN, "body_size": SPACING})
        mesh, _ = scene.plate(p)
        path = folder / f"{name.replace(' ', '_')}.msh"
        mesh.write(str(path))
        files[name] = path
    return files


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", nargs="?", default=str(ROOT / "pretrained" / "pendulum2d"),
                        help="a pendulum run or pretrained folder (default: pretrained/pendulum2d)")
    parser.add_argument("--checkpoint", default="best", choices=["best", "latest"])
    parser.add_argument("--out", default=None, help="keep the outputs here (default: a temporary folder)")
    parser.add_argument("--scene", nargs="*", default=[], metavar="KEY=VALUE",
                        help="scene parameters over the placement's, as bsms.infer's --scene (e.g. E=2e8)")
    args = parser.parse_args(argv)
    overrides = parse_overrides(args.scene)
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(args.out) if args.out else Path(scratch) / "out"
        files = write_plates(Path(scratch))
        rows = {name: infer(args.run, [str(path)], overrides=overrides, solver=True, out=out / path.stem,
                            which=args.checkpoint, progress=False) for name, path in files.items()}
    print("| plate | nodes | RMSE all / body size | at rest / body size | vs at rest "
          "| ms per frame (model one per call, solver) | speed-up end to end |")
    print("|---|---|---|---|---|---|---|")
    for name, row in rows.items():
        print(f"| {name} | {row['body_nodes']} | {100 * row['rel_all']:.3g}% | {100 * row['rest_rel_all']:.3g}% "
              f"| {row['vs_rest']:.3g} | {row['latency_ms']:.3g}, {1e3 * row['solver_seconds_per_step']:.3g} "
              f"| {row['speedup']:.3g}x |")
    names = list(rows)
    skills = np.array([rows[n]["vs_rest"] for n in names])
    speedups = [rows[n]["speedup"] for n in names]
    worst = int(np.argmax(skills))
    print(f"zero-shot: vs at rest mean {skills.mean():.3g} on {len(names)} plates, above 0.5 on "
          f"{int(np.sum(skills > 0.5))} (max {skills[worst]:.3g}, {names[worst]}), "
          f"speedup {min(speedups):.3g}-{max(speedups):.3g} x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
