"""Dataset generation throughput: the press family's solver frame before and after the compiled
substeps, and trajectories per hour per family.

**Press frames** (``--press``, a dataset config of the press family; default press_kinds, whose
settings every press dataset shares): for its first ``--press-trajectories`` train trajectories,
the scene is built and settled once, then ``--press-frames`` frames are run twice from the same
state on one thread: *before*, one Python step per substep (the compiled kernels between torch
operators, ``BSMS_FUSED=0``) and *now*, each frame's substeps in one compiled call
(:mod:`datagen.mpm.fused`); the two runs' positions must agree to round-off. Reported: seconds
and frames per second per core, and the whole generation (meshing, settling, 40 frames, writing)
of ``--press-generate`` trajectories each way, from which the family's 192 train trajectories on
two cores follow (192 x seconds per trajectory / 2). Ends with exactly
``press frame: before B s, now N s`` (mean seconds per frame over the trajectories timed).

**Families** (``--families``, none by default): each family's default config
(``configs/datasets/<family>.yaml``) generates its first ``--trajectories`` train trajectories into
a fresh folder, once per worker count (``--workers``); the wall time includes meshing, solving and
writing. Results go to ``--out/results.json``.

    python benchmarks/datagen_throughput.py [--press-trajectories 4] [--press-frames 5]
        [--families disks glyphs] [--trajectories 4] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.families import FAMILIES
from datagen.generate import generate
from datagen.mpm import advance
from datagen.simulation import build_simulation, settle

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "datasets"


def measure(family: str, trajectories: int, workers: int) -> dict:
    """Generate ``trajectories`` train files of ``family`` with ``workers`` processes; rates and sizes."""
    dconfig = load_dataset_config(CONFIGS / f"{family}.yaml")
    dconfig["splits"] = {"train": trajectories}
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        summary = generate(dconfig, out=out, workers=workers, progress=False)
        seconds = time.perf_counter() - start
        sizes = [p.stat().st_size for p in Path(out).rglob("*.h5")]
    made = [r for r in summary.results if not r.skipped]
    frames = sum(r.frames for r in made)
    return {
        "family": family, "workers": workers, "trajectories": len(made), "seconds": seconds,
        "trajectories_per_hour": 3600 * len(made) / seconds,
        "solver_ms_per_frame": 1e3 * sum(r.solver_seconds for r in made) / max(frames, 1),
        "mean_nodes": sum(r.nodes for r in made) / max(len(made), 1), "mean_file_kb": sum(sizes) / len(sizes) / 1024,
    }


@contextmanager
def python_steps(on: bool):
    """Within the block, one Python step per substep (``BSMS_FUSED=0``) when ``on``."""
    before = os.environ.get("BSMS_FUSED")
    os.environ["BSMS_FUSED"] = "0" if on else "1"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("BSMS_FUSED", None)
        else:
            os.environ["BSMS_FUSED"] = before


def press_frames(dconfig: dict, index: int, frames: int) -> dict:
    """Seconds per frame of train trajectory ``index`` before and now, from the same settled state."""
    sim = build_simulation(trajectory_config(dconfig, "train", index))
    start = settle(sim)
    out = {"index": index, "particles": len(start.x), "substeps": sim.substeps}
    ends = {}
    for name, python in (("before", True), ("now", False)):
        with python_steps(python):
            state, begin = start, time.perf_counter()
            for _ in range(frames):
                state = advance(sim.model, state, sim.dt, sim.substeps)
            out[name] = (time.perf_counter() - begin) / frames
            ends[name] = state.x
    out["position_gap_m"] = float((ends["before"] - ends["now"]).abs().max())
    return out


def press_generation(dconfig: dict, trajectories: int, python: bool) -> float:
    """Seconds per train trajectory, the whole job (meshing, settling, frames, writing), one worker."""
    dconfig = {**dconfig, "splits": {"train": trajectories}}
    with tempfile.TemporaryDirectory() as out, python_steps(python):
        start = time.perf_counter()
        generate(dconfig, out=out, workers=1, progress=False)
        return (time.perf_counter() - start) / trajectories


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--press", type=Path, default=CONFIGS / "press_kinds.yaml")
    parser.add_argument("--press-trajectories", type=int, default=4)
    parser.add_argument("--press-frames", type=int, default=5)
    parser.add_argument("--press-generate", type=int, default=2)
    parser.add_argument("--families", nargs="*", default=[], choices=sorted(FAMILIES))
    parser.add_argument("--trajectories", type=int, default=4)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--out", type=Path, default=Path("runs/datagen_throughput"))
    args = parser.parse_args(argv)
    rows = [measure(f, args.trajectories, w) for f in args.families for w in args.workers]
    if rows:
        print(f"{'family':<14}{'workers':>8}{'traj/h':>10}{'s/traj':>9}{'ms/frame':>10}{'nodes':>8}{'kB/file':>9}")
    for r in rows:
        print(f"{r['family']:<14}{r['workers']:>8}{r['trajectories_per_hour']:>10.0f}"
              f"{r['seconds'] / r['trajectories']:>9.1f}{r['solver_ms_per_frame']:>10.1f}{r['mean_nodes']:>8.0f}"
              f"{r['mean_file_kb']:>9.0f}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        dconfig = load_dataset_config(args.press)
        press = [press_frames(dconfig, i, args.press_frames) for i in range(args.press_trajectories)]
        for p in press:
            print(f"press train {p['index']}: {p['particles']} particles, {p['substeps']} substeps per frame: "
                  f"before {p['before']:.3f} s, now {p['now']:.3f} s per frame ({p['before'] / p['now']:.2f}x); "
                  f"positions {p['position_gap_m']:.1e} m apart")
        generation = {name: press_generation(dconfig, args.press_generate, python)
                      for name, python in (("before", True), ("now", False))}
    finally:
        torch.set_num_threads(threads)
    before, now = (float(np.mean([p[k] for p in press])) for k in ("before", "now"))
    print(f"press frames per second per core: before {1 / before:.2f}, now {1 / now:.2f} ({before / now:.2f}x)")
    print(f"press trajectory, generated whole ({args.press_generate} each way, one core): before "
          f"{generation['before']:.1f} s, now {generation['now']:.1f} s; 192 train trajectories on two cores: before "
          f"{192 * generation['before'] / 2 / 60:.0f} min, now {192 * generation['now'] / 2 / 60:.0f} min")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"families": rows, "press": press, "generation": generation},
                                                      indent=1))
    print(f"press frame: before {before:.3f} s, now {now:.3f} s")


if __name__ == "__main__":
    main()
