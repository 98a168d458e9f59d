"""Where a press solver substep's time goes: the compiled kernels against torch ops and Python.

For press_deep test trajectories (``--trajectories``, the data's settings, one thread): after
two warm-up frames, ``--frames`` frames of substeps are timed, with the calls into the compiled
UMLS kernels (:mod:`datagen.mpm.native`: weights, P2G, G2P, point location, patch averages)
timed apart; the rest of a substep is torch operators and the Python between them. A profiled
stretch of 20 substeps counts the top-level torch operators per substep. Ends with exactly
``substep: compiled C%, torch and Python T%, K torch ops per substep``.

    python benchmarks/substep_overhead.py [--trajectories 0 3] [--frames 3]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

from datagen.dataset_config import load_dataset_config, trajectory_config  # noqa: E402
from datagen.mpm import native  # noqa: E402
from datagen.mpm.step import step  # noqa: E402
from datagen.simulation import build_simulation, settle  # noqa: E402

KERNELS = ("umls_weights", "p2g", "g2p", "locate_guess", "patch_average")


def _timed_kernels(spent: list[float]) -> None:
    for name in KERNELS:
        function = getattr(native, name)

        def wrapped(*args, _function=function, **kwargs):
            start = time.perf_counter()
            try:
                return _function(*args, **kwargs)
            finally:
                spent[0] += time.perf_counter() - start

        setattr(native, name, wrapped)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="configs/datasets/press_deep.yaml")
    parser.add_argument("--trajectories", type=int, nargs="+", default=[0, 3])
    parser.add_argument("--frames", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if not native.available():
        raise SystemExit("the compiled kernels are not available here (no C compiler?): nothing to compare")
    spent = [0.0]
    _timed_kernels(spent)
    dconfig = load_dataset_config(args.dataset)
    shares, ops = [], []
    for index in args.trajectories:
        sim = build_simulation(trajectory_config(dconfig, "test", index))
        state = settle(sim)
        for _ in range(2 * sim.substeps):
            state = step(sim.model, state, sim.dt)
        n, spent[0] = args.frames * sim.substeps, 0.0
        start = time.perf_counter()
        for _ in range(n):
            state = step(sim.model, state, sim.dt)
        total = time.perf_counter() - start
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(20):
                state = step(sim.model, state, sim.dt)
        count = sum(e.cpu_parent is None for e in prof.events()) / 20
        shares.append(spent[0] / total)
        ops.append(count)
        print(f"test {index}: {len(state.x)} particles, {sim.substeps} substeps per frame, "
              f"{1e3 * total / n:.3f} ms per substep: compiled {1e3 * spent[0] / n:.3f} ms ({100 * shares[-1]:.0f}%), "
              f"torch and Python {1e3 * (total - spent[0]) / n:.3f} ms; {count:.0f} torch ops per substep; "
              f"{total / args.frames:.3f} s per frame")
    share = sum(shares) / len(shares)
    print(f"substep: compiled {100 * share:.0f}%, torch and Python {100 * (1 - share):.0f}%, "
          f"{sum(ops) / len(ops):.0f} torch ops per substep")


if __name__ == "__main__":
    main()
