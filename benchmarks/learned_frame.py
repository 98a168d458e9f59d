"""Where a learned frame's time goes: building the frame's graph against the network.

For each run given (its latest checkpoint, or ``--checkpoint``), the first ``--trajectories``
trajectories of its dataset's ``--split`` are rolled out from frame 0 exactly as ``bsms.evaluate``
does (:func:`bsms.rollouts.learned_rollouts.learned_rollouts`: a model that predicts from rest gets every
frame of the known drive at once), on one thread, ``--repeats`` times after one untimed pass; the
runs alternate (A B C A B C ...) so that load drift hits all alike, and each figure is the
median over repeats. Timers wrap, per call, the stages of a frame's graph -- the obstacles within
reach and the contacts (``reach``), contact edges carried to every level (``contacts``), the
penetration, clearance and elastic inputs -- the whole frame's arrays (``frame arrays``), the network
(``network``: :meth:`~bsms.models.simulator.LearnedSimulator.velocity_change` on the joined graph
of a call, its features included) and the rollout as a whole (``total``, per frame; what the
evaluation's speed-up divides by). Frame arrays minus its stages is the rest of the graph's
bookkeeping; total minus frame arrays and network is joining the frames and integrating. The
stages also count the rollout's warm-up call (one frame per trajectory), the total does not.

Prints one row per run, then ends with exactly

    learned frame: FIRST T0 ms (graph G0, network N0), LAST T1 ms (graph G1, network N1): S x faster

(ms per frame; S = T0 / T1, the first run given as the baseline). ``--without-compiled`` adds,
before the runs, the first run again with the compiled loops off (``RUN, torch``: the message
sums, edge inputs and contact edges of :mod:`bsms.models.native` and :mod:`bsms.graph.native` in
torch and numpy, as ``BSMS_NATIVE=0`` runs them), timed in the same alternation: the baseline
the compiled loops are measured against.

    python benchmarks/learned_frame.py RUN [RUN ...] [--split test] [--trajectories 4] [--repeats 3] \
        [--without-compiled]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bsms.data import Scenario  # noqa: E402
from bsms.graph import native as graph_native  # noqa: E402
from bsms.models import native as model_native  # noqa: E402
from bsms.rollouts.learned_rollouts import learned_rollouts  # noqa: E402
from bsms.run import dataset_folder, load_model, split_files  # noqa: E402
from datagen.dataset import load  # noqa: E402

STAGES = ("reach", "contacts", "penetration", "clearance", "elastic", "frame arrays", "network")


TOTALS: dict = defaultdict(float)  # seconds per stage of the pass under way


class _Timed:
    """A callable that adds the seconds of each call to ``TOTALS[name]``."""

    def __init__(self, function, name: str):
        self.function, self.name = function, name

    def __getattr__(self, attribute):  # the object's other methods (ElasticResponse.many), timed alike
        value = getattr(self.function, attribute)
        return _Timed(value, self.name) if callable(value) else value

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self.function(*args, **kwargs)
        finally:
            TOTALS[self.name] += time.perf_counter() - start


class _TimedScenario:
    """A scenario whose frame building is timed stage by stage (wraps the scenario's own parts)."""

    def __init__(self, scenario: Scenario):
        self._scenario = scenario
        scenario.reach.frame = _Timed(scenario.reach.frame, "reach")
        scenario.levels.contacts = _Timed(scenario.levels.contacts, "contacts")
        for name in ("penetration", "clearance", "elastic"):
            if getattr(scenario, name) is not None:
                setattr(scenario, name, _Timed(getattr(scenario, name), name))
        self.frame = _Timed(scenario.frame, "frame arrays")
        self.frames = _Timed(scenario.frames, "frame arrays")  # a rollout's frames of one track at once

    def __getattr__(self, name):
        if name == "_scenario" or name.startswith("__"):  # while copy.copy builds a twin (a strided rollout's)
            raise AttributeError(name)
        return getattr(self._scenario, name)


def _prepare(run: Path, split: str, n: int, which: str, cache: Path):
    model, config, _ = load_model(run, which)
    folder, _ = dataset_folder(run, config)
    trajectories = [load(f) for f in split_files(folder, split)[:n]]
    if not trajectories:
        raise SystemExit(f"learned_frame: {run} has no {split} trajectories in {folder}; generate them first")
    scenarios = [_TimedScenario(Scenario.from_trajectory(t, config.graph, cache, spec=model.spec))
                 for t in trajectories]
    model.velocity_change = _Timed(model.velocity_change, "network")
    return model.eval(), config, trajectories, scenarios


def _compiled(on: bool) -> None:
    """Switch the compiled loops of inference on or off (``BSMS_NATIVE``, read when they load)."""
    if on:
        os.environ.pop("BSMS_NATIVE", None)
    else:
        os.environ["BSMS_NATIVE"] = "0"
    graph_native.library.cache_clear()
    model_native.library.cache_clear()


def _time(model, config, trajectories, scenarios, cache: Path) -> dict:
    """Seconds per frame of each stage and of the whole rollout, one pass."""
    TOTALS.clear()
    frames = [len(t.times) - 1 for t in trajectories]
    results = learned_rollouts(model, config.graph, trajectories, cache, frames, scenarios=scenarios)
    count = sum(frames) + len(frames)  # + the warm-up call's frames (one per trajectory), also timed
    per_frame = {name: TOTALS[name] / count for name in STAGES}
    per_frame["total"] = float(np.mean([m["seconds_per_step"] for m, _ in results]))
    return per_frame


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--split", default="test")
    parser.add_argument("--trajectories", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--checkpoint", default="latest", choices=["latest", "best"])
    parser.add_argument("--without-compiled", action="store_true",
                        help="first time the first run with the compiled loops off (BSMS_NATIVE=0) as the baseline")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    entries = [(f"{run.name}, torch", run, False) for run in args.runs[:1] if args.without_compiled]
    entries += [(run.name, run, True) for run in args.runs]
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp)
        prepared = {label: _prepare(run, args.split, args.trajectories, args.checkpoint, cache)
                    for label, run, _ in entries}
        for label, _, compiled in entries:  # untimed: caches, allocator
            _compiled(compiled)
            _time(*prepared[label], cache)
        samples = defaultdict(list)
        for _ in range(args.repeats):
            for label, _, compiled in entries:
                _compiled(compiled)
                samples[label].append(_time(*prepared[label], cache))
        _compiled(True)
    rows = {label: {k: 1e3 * float(np.median([s[k] for s in samples[label]])) for k in (*STAGES, "total")}
            for label, _, _ in entries}
    print(f"{'run':28s} " + " ".join(f"{k:>12s}" for k in (*STAGES, "total")) + "   (ms per frame)")
    for label, row in rows.items():
        print(f"{label:28s} " + " ".join(f"{row[k]:12.2f}" for k in (*STAGES, "total")))
    first, last = entries[0][0], entries[-1][0]
    a, b = rows[first], rows[last]
    print(f"learned frame: {first} {a['total']:.2f} ms (graph {a['frame arrays']:.2f}, network "
          f"{a['network']:.2f}), {last} {b['total']:.2f} ms (graph {b['frame arrays']:.2f}, network "
          f"{b['network']:.2f}): {a['total'] / b['total']:.2f} x faster")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
