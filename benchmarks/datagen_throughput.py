"""Dataset generation throughput: trajectories per hour per family, with 1 and 2 workers.

Each family's default config (``configs/datasets/<family>.yaml``, default mesh sizes and frame
counts) generates its first ``--trajectories`` train trajectories into a fresh folder, once
per worker count; the wall time includes meshing, solving and writing. Results go to
``--out/results.json`` and a table on stdout.

    python benchmarks/datagen_throughput.py [--families disks glyphs] [--trajectories 4] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from datagen.dataset_config import load_dataset_config
from datagen.families import FAMILIES
from datagen.generate import generate

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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--families", nargs="+", default=sorted(FAMILIES), choices=sorted(FAMILIES))
    parser.add_argument("--trajectories", type=int, default=4)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--out", type=Path, default=Path("runs/datagen_throughput"))
    args = parser.parse_args(argv)
    rows = [measure(f, args.trajectories, w) for f in args.families for w in args.workers]
    print(f"{'family':<14}{'workers':>8}{'traj/h':>10}{'s/traj':>9}{'ms/frame':>10}{'nodes':>8}{'kB/file':>9}")
    for r in rows:
        print(f"{r['family']:<14}{r['workers']:>8}{r['trajectories_per_hour']:>10.0f}"
              f"{r['seconds'] / r['trajectories']:>9.1f}{r['solver_ms_per_frame']:>10.1f}{r['mean_nodes']:>8.0f}"
              f"{r['mean_file_kb']:>9.0f}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
