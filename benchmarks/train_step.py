"""BSMS-GNN against MeshGraphNets: training and inference time per step and peak memory.

Both models train on the same batches of one dataset family. The family's full config
(``configs/datasets/<family>.yaml``) is kept at its mesh resolution -- mesh size is the point --
but only ``--trajectories`` train trajectories of ``--frames`` frames are generated, into
``<--data>/train_step_<family>_<frames>f/`` (reused when present; ``--param key=value``
overrides a scene parameter such as ``body_size`` and names its own folder). Sample indices are
drawn once with ``--seed`` and handed to both workers, so both see identical graphs (the same
``graph`` options, contact edges included; MeshGraphNets reads level 0 only).

Models: the standard ones of ``bsms.run.build_model`` -- MLPs of 2 hidden layers x
``--latent`` (128), MeshGraphNets with 15 passes, BSMS-GNN with one block per level down and up
plus the bottom block. ``--levels auto`` picks the depth from the meshes: the bi-stride
hierarchy is pooled until a level has fewer than 32 nodes (``bistride_levels(levels="auto")``),
taking the deepest over the trajectories.

Each model runs in fresh subprocesses (``--threads`` torch threads in each): one for time, one
for memory. Both build the batches and the model with AdamW and then run the same sequence:
``--warmup`` training steps (which also feed the normalisers), ``--steps`` training steps with
frozen normalisers, then the same batches as ``no_grad`` forward passes in eval mode.

* train s/step: loss (as ``Trainer.train_step``: squared error summed over free nodes, divided
  by their count), backward, gradient clipping, AdamW step; the median of the timed steps.
* infer s/step: the median of the timed forward passes (the warm-up batches are run first).
* peak memory: the largest increase, over all training steps, of the memory held just before
  the first one (batches, model and optimiser built) -- activations kept for backward,
  gradients and AdamW moments. On CUDA: ``torch.cuda.max_memory_allocated`` after
  ``reset_peak_memory_stats``, minus ``memory_allocated`` then. On CPU: the resident set of the
  memory process, whose high-water mark is reset by writing 5 to ``/proc/self/clear_refs``
  right before the first step; peak = ``VmHWM`` afterwards minus ``VmRSS`` at the reset. That
  process tells glibc (mallopt) to return freed blocks of 64 KiB or more to the OS at once, so
  the resident set follows the live tensors instead of keeping freed ones cached (which would
  also slow it down: that is why time is measured in its own process, with default malloc).
  Without /proc, ``ru_maxrss`` (a lifetime maximum) stands in. The inference peak is
  measured the same way, after the training steps, and reported but not compared.

Prints a table per model and the ratios BSMS/MGN, writes everything to ``--out`` as JSON, and
its last line reads ``BSMS/MGN ratios: train <x>, infer <y>, memory <z>``.

    python benchmarks/train_step.py [--family disks] [--trajectories 2] [--steps 10] [--batch-size 1]
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "datasets"
FAMILIES = ("cantilever", "disks", "glyphs", "wavy_channel")
# Mean graph nodes (body + obstacle) of the first 8 train trajectories of each full config:
# disks 458, glyphs 312, cantilever 289, wavy_channel 254 -- disks has the largest meshes.
DEFAULT_FAMILY = "disks"
MODELS = ("bsms_gnn", "meshgraphnets")
AUTO_MIN_NODES = 32
TRAIN_TARGET, MEMORY_TARGET = 0.5, 0.6


# ----------------------------------------------------------------------------- data (parent)
def _parse_param(text: str) -> tuple[str, object]:
    import yaml

    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"--param must look like key=value (e.g. body_size=0.015), got {text!r}")
    return key, yaml.safe_load(value)


def prepare_data(args) -> Path:
    """The benchmark's dataset folder, generated where trajectories are missing."""
    from datagen.dataset_config import load_dataset_config
    from datagen.generate import generate

    dconfig = load_dataset_config(CONFIGS / f"{args.family}.yaml")
    suffix = "".join(f"_{k}{v}" for k, v in args.param)
    dconfig["dataset"] = f"train_step_{args.family}_{args.frames}f{suffix}"
    dconfig["splits"] = {"train": args.trajectories}
    dconfig["output"] = {**dconfig["output"], "frames": args.frames}
    dconfig["params"] = {**dconfig["params"], **dict(args.param)}
    folder = Path(args.data) / dconfig["dataset"]
    missing = args.trajectories - len(list((folder / "train").glob("*.h5")))
    if missing > 0:
        print(f"generating {missing} trajectories of {args.family} ({args.frames} frames) into {folder} ...",
              flush=True)
    start = time.perf_counter()
    summary = generate(dconfig, out=args.data, workers=max(1, min(2, args.trajectories)), progress=False)
    if any(not r.skipped for r in summary.results):
        print(f"  {summary.describe().splitlines()[0]}; {time.perf_counter() - start:.1f} s", flush=True)
    return folder


def survey(files: list[Path], cache: Path) -> tuple[list[int], list[int], int]:
    """Samples and graph nodes per trajectory, and the ``auto`` depth (deepest over the files)."""
    from bsms.data import GraphOptions, Scenario
    from bsms.graph import bistride_levels
    from datagen.dataset import load

    samples, nodes, depth = [], [], 1
    for path in files:
        trajectory = load(path)
        scenario = Scenario.from_trajectory(trajectory, GraphOptions(levels=1), cache_dir=None)
        options = GraphOptions()
        hierarchy = bistride_levels(scenario.edges, scenario.rest_pos, levels="auto", min_nodes=AUTO_MIN_NODES,
                                    seeding=options.seeding, self_loops=options.self_loops, cache_dir=cache)
        samples.append(len(trajectory.times) - 1)
        nodes.append(scenario.n_nodes)
        depth = max(depth, hierarchy.n_levels)
    return samples, nodes, depth


def pick_batches(n_samples: int, batch_size: int, count: int, seed: int) -> list[list[int]]:
    """``count`` batches of sample indices: consecutive slices of seeded permutations."""
    rng = np.random.default_rng(seed)
    order: list[int] = []
    while len(order) < count * batch_size:
        order += [int(i) for i in rng.permutation(n_samples)]
    return [order[k * batch_size:(k + 1) * batch_size] for k in range(count)]


# ----------------------------------------------------------------------------- worker (child)
def _proc_status() -> dict[str, int] | None:
    try:
        with open("/proc/self/status") as fh:
            return {k: int(v.split()[0]) for k, _, v in (line.partition(":") for line in fh) if k in ("VmRSS", "VmHWM")}
    except OSError:
        return None


class MemoryMeter:
    """Peak memory increase (bytes) over a baseline taken at :meth:`start`."""

    def __init__(self, device):
        self.device = device
        self.method = ""

    def start(self) -> None:
        import torch

        gc.collect()
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.base = torch.cuda.memory_allocated(self.device)
            self.method = "torch.cuda.max_memory_allocated - memory_allocated at the baseline"
            return
        try:
            with open("/proc/self/clear_refs", "w") as fh:
                fh.write("5")  # reset VmHWM to the current VmRSS
            status = _proc_status()
        except OSError:
            status = None
        if status is not None:
            self.base, self.method = status["VmRSS"] * 1024, "VmHWM - VmRSS at the baseline (clear_refs reset)"
        else:
            self.base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)
            self.method = "ru_maxrss after - before (lifetime maximum; may under-count)"

    def peak(self) -> int:
        import torch

        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            return torch.cuda.max_memory_allocated(self.device) - self.base
        status = _proc_status() if self.method.startswith("VmHWM") else None
        if status is not None:
            return status["VmHWM"] * 1024 - self.base
        scale = 1 if sys.platform == "darwin" else 1024
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale - self.base


def release_freed_memory() -> bool:
    """Make glibc return freed blocks of 64 KiB or more to the OS at once (mallopt), so that the
    resident set follows the live allocations; False where that is unavailable."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(libc.mallopt(m_mmap_threshold, 1 << 16)) and bool(libc.mallopt(m_trim_threshold, 1 << 17))


def worker(spec: dict) -> dict:
    """Phase ``time`` or ``memory`` of one model on the given batches; returns the measurements."""
    released = spec["phase"] == "memory" and spec["device"] == "cpu" and release_freed_memory()
    import torch
    from torch_geometric.data import Batch

    from bsms.data import FrameDataset
    from bsms.run import build_model, load_config

    torch.set_num_threads(spec["threads"])
    device = torch.device(spec["device"])
    config = load_config({
        "name": "train_step", "dataset": {"config": "unused"}, "graph": {"levels": spec["levels"]},
        "model": {"name": spec["model"], "latent": spec["latent"], "hidden_layers": 2, "passes": spec["passes"]},
        "train": {"device": spec["device"], "normalizer_steps": spec["warmup"], "seed": spec["seed"]},
    })
    dataset = FrameDataset(spec["files"], config.graph, cache_dir=spec["cache"])
    batches = [Batch.from_data_list([dataset[i] for i in keys]).to(device) for keys in spec["batches"]]
    torch.manual_seed(config.train.seed)
    model = build_model(config, dataset.dim).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.optim.lr, weight_decay=config.optim.weight_decay)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def train_step(batch, accumulate: bool) -> float:
        model.train()
        count = batch.loss_mask.sum().clamp(min=1).float()
        loss = model.loss(batch, accumulate=accumulate, reduction="sum") / count
        optimizer.zero_grad(set_to_none=False)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.optim.grad_clip)
        optimizer.step()
        return float(loss.detach())

    def timed(run) -> float:
        sync()
        start = time.perf_counter()
        run()
        sync()
        return time.perf_counter() - start

    n_warm = spec["warmup"]
    train_meter, infer_meter = MemoryMeter(device), MemoryMeter(device)
    losses = []
    train_meter.start()
    train_times = [timed(lambda b=b, k=k: losses.append(train_step(b, accumulate=k < n_warm)))
                   for k, b in enumerate(batches)][n_warm:]
    train_peak = train_meter.peak()
    model.eval()
    optimizer.zero_grad(set_to_none=True)
    infer_meter.start()
    with torch.no_grad():
        infer_times = [timed(lambda b=b: model(b)) for b in batches][n_warm:]
    infer_peak = infer_meter.peak()

    result = {"model": spec["model"], "phase": spec["phase"]}
    if spec["phase"] == "memory":
        method = train_meter.method + (", freed blocks >= 64 KiB returned to the OS" if released else "")
        return {**result, "train_peak_bytes": int(train_peak), "infer_peak_bytes": int(infer_peak),
                "memory_method": method}
    sizes = [{
        "nodes": float(np.mean([b.level_size(l) for b in batches])),
        "edges": float(np.mean([b[f"edge_index_{l}"].shape[1] for b in batches])),
        "contacts": float(np.mean([b[f"contact_index_{l}"].shape[1] for b in batches]))
        if config.graph.contact else 0.0,
    } for l in range(model.n_levels)]
    return {
        **result, "levels_used": model.n_levels, "level_sizes": sizes,
        "params": sum(p.numel() for p in model.parameters()),
        "train_s": float(np.median(train_times)), "train_s_all": train_times,
        "infer_s": float(np.median(infer_times)), "infer_s_all": infer_times,
        "final_loss": losses[-1], "threads": torch.get_num_threads(), "torch": torch.__version__,
    }


def measure(spec: dict) -> dict:
    """Timing, then memory, of one model, each phase in a fresh interpreter."""
    timing = run_worker({**spec, "phase": "time"})
    memory = run_worker({**spec, "phase": "memory"})
    return {**timing, **memory, "phase": "time+memory"}


def run_worker(spec: dict) -> dict:
    """One model in a fresh interpreter; its JSON result is the last line of its stdout."""
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        sys.stderr.write(done.stderr)
        raise SystemExit(f"the {spec['model']} worker failed (exit {done.returncode})")
    return json.loads(done.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- report
def _table(result: dict) -> str:
    name = {"bsms_gnn": "BSMS-GNN", "meshgraphnets": "MeshGraphNets"}[result["model"]]
    lines = [f"{name}: {result['params']:,} parameters, {result['levels_used']} level(s); per batch (mean):",
             f"  {'level':>5}{'nodes':>9}{'edges':>9}{'contacts':>10}"]
    for l, size in enumerate(result["level_sizes"]):
        lines.append(f"  {l:>5}{size['nodes']:>9.0f}{size['edges']:>9.0f}{size['contacts']:>10.0f}")
    lines.append(f"  train {result['train_s'] * 1e3:.1f} ms/step, infer {result['infer_s'] * 1e3:.1f} ms/step, "
                 f"peak +{result['train_peak_bytes'] / 2**20:.1f} MB training "
                 f"(+{result['infer_peak_bytes'] / 2**20:.1f} MB inference)")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--family", default=DEFAULT_FAMILY, choices=FAMILIES,
                        help=f"dataset family, full resolution (default {DEFAULT_FAMILY}: the largest meshes)")
    parser.add_argument("--trajectories", type=int, default=2, help="train trajectories generated (default 2)")
    parser.add_argument("--frames", type=int, default=10, help="frames per trajectory (default 10)")
    parser.add_argument("--param", type=_parse_param, action="append", default=[], metavar="KEY=VALUE",
                        help="override a scene parameter of the family, e.g. body_size=0.015 (repeatable)")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per model (default 10)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed steps first (default 3)")
    parser.add_argument("--batch-size", type=int, default=1, help="graphs per batch (default 1)")
    parser.add_argument("--levels", default="auto", help="BSMS levels, the mesh included, or auto (default)")
    parser.add_argument("--latent", type=int, default=128, help="latent and hidden width (default 128)")
    parser.add_argument("--passes", type=int, default=15, help="MeshGraphNets message passes (default 15)")
    parser.add_argument("--threads", type=int, default=2,
                        help="torch threads in each worker (default 2; 1 is steadier on a busy machine)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the batches and of the weights")
    parser.add_argument("--data", default="data", help="root folder of datasets (default data)")
    parser.add_argument("--out", type=Path, default=Path("runs/benchmarks/train_step.json"))
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    for key in ("trajectories", "frames", "steps", "batch_size", "latent", "passes", "threads"):
        if getattr(args, key) < 1:
            parser.error(f"--{key.replace('_', '-')} must be >= 1")
    if args.warmup < 0:
        parser.error("--warmup must be >= 0")
    if args.levels != "auto" and not (args.levels.isdigit() and 1 <= int(args.levels) <= 16):
        parser.error(f"--levels must be auto or an integer from 1 to 16, got {args.levels!r}")

    folder = prepare_data(args)
    files = sorted((folder / "train").glob("*.h5"))[:args.trajectories]
    cache = folder / "hierarchies"
    samples, nodes, depth = survey(files, cache)
    levels = depth if args.levels == "auto" else int(args.levels)
    batches = pick_batches(sum(samples), args.batch_size, args.warmup + args.steps, args.seed)
    print(f"{args.family}: {len(files)} trajectories, {sum(samples)} samples, graph nodes per mesh "
          f"{'/'.join(map(str, nodes))}; BSMS levels {levels} ({args.levels}); batch {args.batch_size}, "
          f"{args.warmup} warm-up + {args.steps} timed steps, {args.threads} threads, {args.device}", flush=True)
    spec = {"files": [str(f) for f in files], "cache": str(cache), "batches": batches, "levels": levels,
            "latent": args.latent, "passes": args.passes, "threads": args.threads, "device": args.device,
            "warmup": args.warmup, "seed": args.seed}
    results = {}
    for model in MODELS:
        results[model] = measure({**spec, "model": model})
        print(_table(results[model]), flush=True)
    bsms, mgn = results["bsms_gnn"], results["meshgraphnets"]
    ratios = {"train": bsms["train_s"] / mgn["train_s"], "infer": bsms["infer_s"] / mgn["infer_s"],
              "memory": bsms["train_peak_bytes"] / max(mgn["train_peak_bytes"], 1)}
    report = {
        "family": args.family, "dataset": str(folder), "files": spec["files"], "nodes_per_mesh": nodes,
        "params_override": dict(args.param), "levels": levels, "levels_option": args.levels,
        "batch_size": args.batch_size, "batches": batches, "warmup": args.warmup, "steps": args.steps,
        "threads": args.threads, "device": args.device, "machine": platform.processor() or platform.machine(),
        "results": results, "ratios": ratios,
        "targets": {"train": TRAIN_TARGET, "memory": MEMORY_TARGET},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    verdict = [f"train <= {TRAIN_TARGET} {'met' if ratios['train'] <= TRAIN_TARGET else 'MISSED'}",
               f"memory <= {MEMORY_TARGET} {'met' if ratios['memory'] <= MEMORY_TARGET else 'MISSED'}"]
    print(f"targets (thesis Tables 4.5-4.6): {', '.join(verdict)}; written to {args.out}")
    print(f"BSMS/MGN ratios: train {ratios['train']:.2f}, infer {ratios['infer']:.2f}, memory {ratios['memory']:.2f}")


if __name__ == "__main__":
    main()
