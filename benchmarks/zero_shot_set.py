"""The sixteen shapes of no split as a stored test set, solved once, so that any number of press
models can be scored on them without running the solver again.

Each body of ``press_zero_shot.wider_set`` (the star, L bracket and notched plate of
``press_zero_shot.py`` and thirteen more), meshed by gmsh at ``--size``, is placed in the family's
setting exactly as ``bsms.infer`` places a user's mesh (``datagen.families.place``: the family's
box and bonded floor, mid-range material, a disk straight down over the body's centre, the mesh
subdivided to the family's resolution) and run by the MPM solver at the data's settings
(``bsms.infer.simulate_stable``); each trajectory is written to ``OUT/test/NN_name.h5``, a
dataset folder ``python benchmarks/ensemble.py RUN ... --data OUT`` scores runs on (on every node
of the subdivided mesh; ``press_zero_shot.py --shapes wide`` reports on the given mesh's nodes,
with the speed-up). Generation resumes: a shape whose file exists is skipped; ``--shard I/N``
runs every N-th shape from I. Ends with exactly

    zero-shot set: N shapes in OUT/test, K solved here, S s of solver time per frame

    python benchmarks/zero_shot_set.py --out data/zeroshot [--run pretrained/press2d] [--size 0.004]
        [--shard I/N] [--scene KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from press_zero_shot import wider_set  # noqa: E402

from bsms.infer import parse_overrides, simulate_stable  # noqa: E402
from bsms.run import load_model, run_dataset_config  # noqa: E402
from datagen import shapes  # noqa: E402
from datagen.dataset import save  # noqa: E402
from datagen.families import place  # noqa: E402
from datagen.generate import parse_shard  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def file_name(k: int, name: str) -> str:
    return f"{k:02d}_{name.replace(' ', '_')}.h5"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="the dataset folder to write (OUT/test/*.h5)")
    parser.add_argument("--run", default=str(ROOT / "pretrained" / "press2d"),
                        help="a press run or pretrained folder whose family places the shapes (default: "
                             "pretrained/press2d)")
    parser.add_argument("--size", type=float, default=0.004, help="mesh element size, m (default 0.004)")
    parser.add_argument("--shard", default="0/1", help="I/N: every N-th shape from I (default 0/1: all)")
    parser.add_argument("--scene", nargs="*", default=[], metavar="KEY=VALUE",
                        help="scene parameters over the family's, as bsms.infer's --scene")
    args = parser.parse_args(argv)
    first, count = parse_shard(args.shard)
    overrides = parse_overrides(args.scene)
    _, config, _ = load_model(args.run, "best")
    dconfig = run_dataset_config(args.run, config)
    folder = args.out / "test"
    folder.mkdir(parents=True, exist_ok=True)
    bodies = list(wider_set().items())
    solved, seconds = 0, []
    with tempfile.TemporaryDirectory() as scratch:
        for k, (name, (ring, holes)) in enumerate(bodies):
            dest = folder / file_name(k, name)
            if k % count != first or dest.exists():
                continue
            mesh = Path(scratch) / f"{k:02d}.msh"
            shapes.polygon(ring, holes, size=args.size).write(str(mesh))
            trajectory, cfl = simulate_stable(place(dconfig["family"], [str(mesh)], dconfig, overrides))
            save(dest, trajectory)
            solved += 1
            seconds.append(trajectory.wall_time / (len(trajectory.positions) - 1))
            print(f"{name}: {trajectory.mesh.n_nodes} nodes, CFL {cfl:g}, {seconds[-1]:.3g} s per frame", flush=True)
    present = len(list(folder.glob("*.h5")))
    per_frame = f"{np.mean(seconds):.3g}" if seconds else "0"
    print(f"zero-shot set: {present} shapes in {folder}, {solved} solved here, {per_frame} s of solver time per frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
