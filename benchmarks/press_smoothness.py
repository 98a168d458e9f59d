"""How smooth are a press dataset's frames? What a quasi-static surrogate can and cannot predict.

Dataset part: over the first ``--trajectories`` files of ``--split``, the per-frame RMS body
velocity (frame-to-frame displacement over the frame interval, RMS over the nodes), its
percentiles, and the share of the summed squared velocity that sits in frames faster than
``--fast`` m/s (ringing and snaps concentrate there).

Re-run part (``--rerun NAME ...``, files of the split): each trajectory re-simulated from its
generating config with the scene parameter changes of ``--set KEY=VALUE`` (e.g.
``damping=200``, ``indenter_friction=0``) and as stored, printing per re-run its RMS body velocity
per frame, the smoothness ratio (RMS of the frame-to-frame velocity change over the RMS velocity:
small for motion the frames resolve) and the error of predicting no motion (relative to the body
size). Ends with exactly ``press smoothness: fast-frame share S, median frame V m/s``.

    python benchmarks/press_smoothness.py [--data data/press_bonded] [--split train] [--trajectories 96]
        [--rerun 00005 00094 --set damping=200]
"""

from __future__ import annotations

import argparse
import copy
import os
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from bsms.rollouts.motion import motion_parts  # noqa: E402
from bsms.rollouts.rollout import body_size  # noqa: E402
from datagen import simulate  # noqa: E402
from datagen.dataset import load  # noqa: E402


def frame_speeds(positions: np.ndarray, dt: float) -> np.ndarray:
    """(T-1,) RMS over nodes of each frame's velocity (m/s)."""
    velocity = np.diff(positions, axis=0) / dt
    return np.sqrt(np.mean(np.sum(velocity**2, axis=-1), axis=-1))


def smoothness(positions: np.ndarray, dt: float) -> float:
    """RMS frame-to-frame velocity change over RMS velocity."""
    velocity = np.diff(positions, axis=0) / dt
    change = np.diff(velocity, axis=0)
    return float(np.sqrt(np.mean(np.sum(change**2, -1))) / np.sqrt(np.mean(np.sum(velocity**2, -1))))


def describe(name: str, trajectory) -> str:
    dt = float(trajectory.times[1] - trajectory.times[0])
    x = trajectory.positions
    rest = motion_parts(x, np.ones(x.shape[1], bool), body_size(trajectory.mesh.nodes))["rest_rel_all"]
    speeds = ", ".join(f"{v:.3f}" for v in frame_speeds(x, dt))
    return f"{name}: smoothness {smoothness(x, dt):.2f}, at rest {100 * rest:.2f}%, RMS velocity per frame [{speeds}]"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data/press_bonded"))
    parser.add_argument("--split", default="train")
    parser.add_argument("--trajectories", type=int, default=96)
    parser.add_argument("--fast", type=float, default=0.08, help="a fast frame's RMS velocity (m/s)")
    parser.add_argument("--rerun", nargs="*", default=[], help="file stems of the split to re-simulate")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene parameter change")
    args = parser.parse_args(argv)
    files = sorted((args.data / args.split).glob("*.h5"))[: args.trajectories]
    if not files:
        raise SystemExit(f"no trajectories in {args.data / args.split}; generate them with python -m datagen")
    speeds = []
    for path in files:
        trajectory = load(path)
        speeds.append(frame_speeds(trajectory.positions, float(trajectory.times[1] - trajectory.times[0])))
    speeds = np.concatenate(speeds)
    share = float(np.sum(speeds[speeds > args.fast] ** 2) / np.sum(speeds**2))
    p50, p90, p99 = np.percentile(speeds, [50, 90, 99])
    print(f"{len(files)} trajectories, {len(speeds)} frames: RMS velocity per frame median {p50:.4f}, 90% {p90:.4f}, "
          f"99% {p99:.4f}, max {speeds.max():.4f} m/s; frames above {args.fast} m/s: "
          f"{100 * np.mean(speeds > args.fast):.1f}% of the frames, {100 * share:.1f}% of the squared velocity")
    changes = {}
    for item in args.set:
        key, _, text = item.partition("=")
        changes[key] = yaml.safe_load(text)
    for stem in args.rerun:
        stored = load(args.data / args.split / f"{stem}.h5")
        print(describe(f"{stem} as stored", stored))
        if changes:
            config = copy.deepcopy(stored.config)
            config["params"].update(changes)
            config["solver"]["threads"] = 1
            print(describe(f"{stem} with {changes}", simulate(config)))
    print(f"press smoothness: fast-frame share {share:.3g}, median frame {p50:.3g} m/s")


if __name__ == "__main__":
    main()
