"""What the float32 substeps cost in accuracy (``solver.precision: float32``), beside the solver's own
discretisation error.

1. The vibrating bar (the 2D strip: the compiled substeps run in 2D and 3D) in float64 and float32:
   the errors against the closed form (``mpm_verification.bar_errors``) and the largest position
   difference.
2. A press3d trajectory (``--split``/``--index`` of ``--config``, the dataset's own settings) in
   float64 and float32, and two convergence runs in float64: the time step halved (``solver.cfl``
   x 0.5) and the background refined (``params.mesh_size`` x ``--refine``). Each run's positions
   are compared with the float64 run's, frame by frame: the largest distance over the body and the
   frames, relative to the body's size, beside the motion itself (the largest displacement from
   the first frame). float32 is harmless where its gap is far below the convergence gaps.

Ends with exactly
``precision: float32 press3d gap G32 (dt/2 G_dt, refined G_h) of the body size, motion M, bar error change B``
(G: the largest distance / body size; B: the largest relative change of the bar's errors).

    python benchmarks/solver_precision.py [--config configs/datasets/press3d.yaml] [--split test] [--index 0]
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from mpm_verification import bar_errors  # noqa: E402

import datagen  # noqa: E402
from datagen.config import read_yaml  # noqa: E402
from datagen.dataset_config import trajectory_config  # noqa: E402


def bar_study() -> dict:
    """The 2D bar's errors in both precisions and the largest relative change between them."""
    runs = {p: datagen.simulate({"scene": "vibrating_bar", "params": {"dim": 2}, "solver": {"precision": p}})
            for p in ("float64", "float32")}
    errors = {p: bar_errors(t) for p, t in runs.items()}
    change = max(abs(errors["float32"][k] / v - 1.0) for k, v in errors["float64"].items())
    gap = float(np.abs(runs["float64"].positions - runs["float32"].positions).max())
    return {"float64": errors["float64"], "float32": errors["float32"], "max_relative_change": change,
            "max_position_gap_m": gap, "wall_s": {p: t.wall_time for p, t in runs.items()}}


def variants(config: dict, refine: float) -> dict[str, dict]:
    """The trajectory's config in float64 (reference), float32, with half the CFL step, and on a
    background refined by ``refine``."""
    out = {}
    for name in ("float64", "float32", "dt/2", "refined"):
        c = copy.deepcopy(config)
        c.setdefault("solver", {})
        c["solver"]["precision"] = "float32" if name == "float32" else "float64"
        if name == "dt/2":
            c["solver"]["cfl"] = 0.5 * c["solver"].get("cfl", 0.3)
        if name == "refined":
            c["params"]["mesh_size"] = c["params"]["mesh_size"] * refine
        out[name] = c
    return out


def press_study(config: dict, refine: float) -> dict:
    runs, walls = {}, {}
    for name, c in variants(config, refine).items():
        start = time.perf_counter()
        runs[name] = datagen.simulate(c)
        walls[name] = time.perf_counter() - start
        print(f"  {name}: {walls[name]:.1f} s, {runs[name].positions.shape[0]} frames", flush=True)
    ref = runs["float64"].positions
    size = float(np.ptp(ref[0], axis=0).max())
    motion = float(np.linalg.norm(ref - ref[0], axis=-1).max()) / size
    gaps = {name: float(np.linalg.norm(t.positions - ref, axis=-1).max()) / size
            for name, t in runs.items() if name != "float64"}
    return {"body_size_m": size, "nodes": int(ref.shape[1]), "frames": int(ref.shape[0]), "motion": motion,
            "gap": gaps, "wall_s": walls}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", type=Path, default=Path("configs/datasets/press3d.yaml"))
    parser.add_argument("--split", default="test")
    parser.add_argument("--index", type=int, default=0)
    parser.add_argument("--refine", type=float, default=0.75, help="background size factor of the refined run")
    parser.add_argument("--out", type=Path, default=Path("runs/benchmarks/solver_precision.json"))
    args = parser.parse_args()
    print("vibrating bar (2D strip), float64 and float32", flush=True)
    bar = bar_study()
    print(f"  errors float64 {bar['float64']}\n  errors float32 {bar['float32']}\n"
          f"  largest relative change {bar['max_relative_change']:.2e}, "
          f"positions apart {bar['max_position_gap_m']:.2e} m")
    config = trajectory_config(read_yaml(args.config, what="dataset config"), args.split, args.index)
    print(f"{args.config} {args.split} {args.index}: float64, float32, dt/2, background x {args.refine}", flush=True)
    press = press_study(config, args.refine)
    print(f"  body {press['body_size_m']:.3f} m, {press['nodes']} nodes, motion {press['motion']:.2e} of the size; "
          + ", ".join(f"{k} {v:.2e}" for k, v in press["gap"].items()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"bar": bar, "press3d": press, "config": str(args.config), "split": args.split,
                                    "index": args.index}, indent=1))
    g = press["gap"]
    print(f"precision: float32 press3d gap {g['float32']:.2e} (dt/2 {g['dt/2']:.2e}, refined {g['refined']:.2e}) "
          f"of the body size, motion {press['motion']:.2e}, bar error change {bar['max_relative_change']:.2e}")


if __name__ == "__main__":
    main()
