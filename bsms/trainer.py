"""Training: typed run configs, the dataset a run needs, and a resumable (multi-process) trainer.

A run lives in ``<runs>/<name>/``: ``config.yaml`` (the resolved config), ``metrics.csv``
(step, loss, lr, seconds, samples_per_s, valid_rmse) and ``checkpoints/{latest,best}.pt``.
Checkpoints hold the model with its normalisers, the optimiser, the scheduler, the step and
the RNG states; they are written atomically and read with ``weights_only=True``.

Determinism: the samples of step ``s`` are a function of (seed, s) only (a per-epoch
permutation), and the training noise of a sample of (seed, s, index), so a resumed run
continues exactly and a batch split over processes sees the same noise as one process.
Launched with ``torchrun --nproc_per_node K``, each process takes every K-th sample of the
global batch; gradients are summed over processes after each process divided its squared
error sum by the free-node count of the whole batch, which makes the update identical to
one process on the whole batch (normaliser statistics are summed over processes too).
"""

from __future__ import annotations

import csv
import json
import math
import os
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.distributed as dist
from torch_geometric.data import Batch

from bsms.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from bsms.config import ConfigError, apply_overrides, build, load, to_dict
from bsms.data import FrameDataset, GraphOptions, NoiseOptions
from bsms.evaluate import EvaluateConfig
from bsms.models.simulator import LearnedSimulator
from datagen.atomic import atomic_path

__all__ = [
    "Config", "DatasetConfig", "ModelConfig", "OptimConfig", "TrainConfig", "Trainer", "build_model",
    "load_config", "prepare_dataset", "split_files", "METRICS_FIELDS",
]

METRICS_FIELDS = ("step", "loss", "lr", "seconds", "samples_per_s", "valid_rmse")


# ----------------------------------------------------------------------------- config
@dataclass
class DatasetConfig:
    """config: the dataset YAML (``configs/datasets/...``); root: folder of datasets;
    generate: generate missing trajectories (resumable) before training; workers: processes
    for that."""

    config: str = ""
    root: str = "data"
    generate: bool = True
    workers: int = 1

    def validate(self, prefix: str) -> None:
        if not self.config:
            raise ConfigError(f"config key '{prefix}.config' is required: the dataset config YAML, "
                              "e.g. configs/datasets/glyphs_quick.yaml")
        if self.workers < 1:
            raise ConfigError(f"config key '{prefix}.workers' must be >= 1, got {self.workers}")


@dataclass
class ModelConfig:
    """name: the core network; latent: width of latents and hidden layers; hidden_layers per
    MLP; passes: message passes of meshgraphnets (bsms_gnn makes one per level)."""

    name: Literal["bsms_gnn", "meshgraphnets"] = "bsms_gnn"
    latent: int = 128
    hidden_layers: int = 2
    passes: int = 15

    def validate(self, prefix: str) -> None:
        for key in ("latent", "hidden_layers", "passes"):
            if getattr(self, key) < 1:
                raise ConfigError(f"config key '{prefix}.{key}' must be >= 1, got {getattr(self, key)}")


@dataclass
class OptimConfig:
    """AdamW with a linear warm-up over ``warmup`` steps, then a cosine decay to
    ``lr * min_lr_ratio`` at the last step; gradients clipped to norm ``grad_clip`` (null: off)."""

    lr: float = 1e-3
    weight_decay: float = 0.0
    warmup: int = 100
    min_lr_ratio: float = 0.01
    grad_clip: float | None = 1.0

    def validate(self, prefix: str) -> None:
        if self.lr <= 0:
            raise ConfigError(f"config key '{prefix}.lr' must be positive, got {self.lr}")
        if self.weight_decay < 0:
            raise ConfigError(f"config key '{prefix}.weight_decay' must be >= 0, got {self.weight_decay}")
        if self.warmup < 0:
            raise ConfigError(f"config key '{prefix}.warmup' must be >= 0, got {self.warmup}")
        if not 0.0 <= self.min_lr_ratio <= 1.0:
            raise ConfigError(f"config key '{prefix}.min_lr_ratio' must lie in [0, 1], got {self.min_lr_ratio}")
        if self.grad_clip is not None and self.grad_clip <= 0:
            raise ConfigError(f"config key '{prefix}.grad_clip' must be positive or null, got {self.grad_clip}")


@dataclass
class TrainConfig:
    """steps and batch_size (graphs per step, over all processes); normalizer_steps: batches
    the normalisers learn from before they freeze; log/valid/checkpoint cadence in steps;
    valid_samples: validation samples (evenly spread over the split); device: auto, cpu, cuda
    or cuda:N; amp: bfloat16 autocast (CUDA only); workers: data-loading processes."""

    steps: int = 10_000
    batch_size: int = 2
    seed: int = 0
    normalizer_steps: int = 1000
    log_every: int = 50
    valid_every: int = 500
    valid_samples: int = 200
    checkpoint_every: int = 500
    device: str = "auto"
    amp: bool = False
    workers: int = 0
    progress: bool = True

    def validate(self, prefix: str) -> None:
        for key in ("steps", "batch_size", "normalizer_steps", "log_every", "valid_every", "valid_samples",
                    "checkpoint_every"):
            if getattr(self, key) < 1:
                raise ConfigError(f"config key '{prefix}.{key}' must be >= 1, got {getattr(self, key)}")
        if self.seed < 0 or self.workers < 0:
            key = "seed" if self.seed < 0 else "workers"
            raise ConfigError(f"config key '{prefix}.{key}' must be >= 0, got {getattr(self, key)}")
        if self.device != "auto" and self.device != "cpu" and not self.device.startswith("cuda"):
            raise ConfigError(f"config key '{prefix}.device' must be auto, cpu, cuda or cuda:N, got {self.device!r}")


@dataclass
class Config:
    """A training run: what data, which graphs, which model, how to optimise and train."""

    name: str = ""
    runs: str = "runs"
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    graph: GraphOptions = field(default_factory=GraphOptions)
    noise: NoiseOptions = field(default_factory=NoiseOptions)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    evaluate: EvaluateConfig = field(default_factory=EvaluateConfig)

    def validate(self, prefix: str = "") -> None:
        if not self.name or "/" in self.name or self.name.startswith("."):
            raise ConfigError(f"config key 'name' must be a run folder name (no '/'), got {self.name!r}")

    @property
    def run_dir(self) -> Path:
        return Path(self.runs) / self.name


def load_config(source, overrides: list[str] = ()) -> Config:
    """A checked :class:`Config` from a YAML path or a mapping, with ``key=value`` overrides."""
    data = load(source) if isinstance(source, (str, Path)) else dict(source)
    return build(Config, apply_overrides(data, list(overrides)))


# These may change when a run is resumed; anything else must match the run's saved config.
_OPERATIONAL = {"train.progress", "train.workers", "train.device", "dataset.workers", "dataset.generate"}


def _flat(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        out.update(_flat(value, name + ".") if isinstance(value, dict) else {name: value})
    return out


# ----------------------------------------------------------------------------- data
def _dataset_config_path(config: Config, base: Path | None) -> Path:
    path = Path(config.dataset.config)
    if not path.is_file() and base is not None and (base / path).is_file():
        path = base / path
    if not path.is_file():
        raise ConfigError(f"config key 'dataset.config': dataset config {config.dataset.config} does not exist "
                          "(give a path relative to the working folder, e.g. configs/datasets/glyphs_quick.yaml)")
    return path


def prepare_dataset(config: Config, base: Path | None = None, progress: bool = True) -> Path:
    """The dataset folder of ``config``, generated first where trajectories are missing.

    base: folder that a relative ``dataset.config`` may also be relative to (the config file's).
    """
    from datagen.generate import generate, jobs, load_dataset_config, trajectory_path
    from datagen.metadata import write_metadata

    path = _dataset_config_path(config, base)
    dconfig = load_dataset_config(path)
    root = Path(config.dataset.root)
    missing = [(s, k) for s, k in jobs(dconfig) if not trajectory_path(root, dconfig, s, k).is_file()]
    if missing and not config.dataset.generate:
        raise ConfigError(f"dataset {dconfig['dataset']} lacks {len(missing)} trajectory files under {root}; "
                          f"generate them with python -m datagen {path} --out {root}, or set dataset.generate: true")
    if missing:
        generate(path, out=root, workers=config.dataset.workers, progress=progress)
    folder = root / dconfig["dataset"]
    if not (folder / "metadata.json").is_file():
        write_metadata(folder, dconfig)
    return folder


def run_dataset_config(run_dir, config: Config) -> dict:
    """The generating dataset config of a run: its ``dataset.json``, else ``config.dataset.config``."""
    from bsms.checkpoint import CheckpointError
    from datagen.generate import load_dataset_config

    saved = Path(run_dir) / "dataset.json"
    if saved.is_file():
        return json.loads(saved.read_text())
    try:
        return load_dataset_config(config.dataset.config)
    except ConfigError as exc:
        raise CheckpointError(f"run folder {run_dir} has no dataset.json and its dataset config cannot be read "
                              f"({exc}); run from the folder train.py ran in") from None


def split_files(folder: Path, split: str) -> list[Path]:
    files = sorted((Path(folder) / split).glob("*.h5"))
    if not files:
        raise ConfigError(f"dataset folder {folder} has no {split} trajectories; its config must give "
                          f"splits.{split} > 0")
    return files


# ----------------------------------------------------------------------------- model and schedule
def build_model(config: Config, dim: int) -> LearnedSimulator:
    """The learned simulator a config describes, for dimension ``dim`` (untrained)."""
    return LearnedSimulator(
        config.model.name, dim, n_levels=config.graph.levels, contact=config.graph.contact,
        n_constants=len(config.graph.constants), latent=config.model.latent, n_passes=config.model.passes,
        hidden_layers=config.model.hidden_layers, max_accumulations=config.train.normalizer_steps,
    )


def lr_factor(step: int, warmup: int, total: int, min_ratio: float) -> float:
    """Learning-rate multiplier at ``step``: linear warm-up to 1, then cosine to ``min_ratio``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


def _rng_state() -> dict:
    kind, keys, pos, has_gauss, gauss = np.random.get_state()  # noqa: NPY002 (the legacy global RNG)
    return {
        "torch": torch.get_rng_state(), "numpy_keys": torch.from_numpy(keys.astype(np.int64)),
        "numpy_rest": [int(pos), int(has_gauss), float(gauss)], "python": list(random.getstate()[1]),
        "python_gauss": random.getstate()[2],
    }


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    pos, has_gauss, gauss = state["numpy_rest"]
    keys = state["numpy_keys"].numpy().astype(np.uint32)
    np.random.set_state(("MT19937", keys, pos, has_gauss, gauss))  # noqa: NPY002 (the legacy global RNG)
    random.setstate((3, tuple(state["python"]), state["python_gauss"]))


# ----------------------------------------------------------------------------- trainer
def _collate(graphs):
    return Batch.from_data_list(graphs)


class Trainer:
    """Trains the model of ``config`` on its dataset, writing the run folder (rank 0 only).

    Args:
        config: the run's :class:`Config`.
        resume: continue from ``<run>/checkpoints/latest.pt``; without it a run folder that
            already holds a checkpoint is an error (nothing is overwritten).
        dataset_folder: the dataset (default: prepared from ``config.dataset``).
        base: folder a relative ``dataset.config`` may be relative to.
    """

    def __init__(self, config: Config, *, resume: bool = False, dataset_folder=None, base: Path | None = None):
        self.config = config
        self.rank, self.world = self._init_distributed()
        self.device = self._device()
        if config.train.amp and self.device.type != "cuda":
            raise ConfigError("config key 'train.amp' needs a CUDA device (bfloat16 autocast); set train.amp: false "
                              "on CPU")
        if config.train.batch_size < self.world:
            raise ConfigError(f"config key 'train.batch_size' ({config.train.batch_size}) must be at least the "
                              f"number of processes ({self.world})")
        self.run_dir = config.run_dir
        self.latest = self.run_dir / "checkpoints" / "latest.pt"
        self.best_path = self.run_dir / "checkpoints" / "best.pt"
        if not resume and self.latest.exists():
            raise ConfigError(f"run folder {self.run_dir} already holds a checkpoint; pass --resume to continue it, "
                              f"or choose another name (name=...)")
        if resume and not self.latest.exists():
            raise ConfigError(f"cannot resume: {self.latest} does not exist; start the run without --resume")
        progress = config.train.progress and self.rank == 0
        if dataset_folder is None:
            dataset_folder = prepare_dataset(config, base, progress) if self.rank == 0 else None
            if self.world > 1:
                holder = [str(dataset_folder)]
                dist.broadcast_object_list(holder, src=0)
                dataset_folder = holder[0]
        self.dataset_folder = Path(dataset_folder)
        cache = self.dataset_folder / "hierarchies"
        self.train_set = FrameDataset(split_files(self.dataset_folder, "train"), config.graph, config.noise,
                                      cache_dir=cache, progress=progress)
        self.valid_set = FrameDataset(split_files(self.dataset_folder, "valid"), config.graph, cache_dir=cache,
                                      progress=progress)
        if len(self.train_set) < config.train.batch_size:
            raise ConfigError(f"config key 'train.batch_size' ({config.train.batch_size}) exceeds the "
                              f"{len(self.train_set)} training samples of {self.dataset_folder}")
        torch.manual_seed(config.train.seed)
        self.model = build_model(config, self.train_set.dim).to(self.device)
        if self.world > 1:
            for tensor in [*self.model.parameters(), *self.model.buffers()]:
                dist.broadcast(tensor.data, src=0)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=config.optim.lr,
                                           weight_decay=config.optim.weight_decay)
        o = config.optim
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: lr_factor(s, o.warmup, config.train.steps, o.min_lr_ratio))
        self.step, self.best_valid, self.seconds = 0, math.inf, 0.0
        if resume:
            self._check_resumable()
            self._restore(load_checkpoint(self.latest))
        elif self.rank == 0:
            self._start_run_folder()

    # -- setup
    @staticmethod
    def _init_distributed() -> tuple[int, int]:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world > 1 and not dist.is_initialized():
            backend = "nccl" if torch.cuda.is_available() and os.environ.get("BSMS_BACKEND") != "gloo" else "gloo"
            dist.init_process_group(backend)
        if dist.is_available() and dist.is_initialized():
            return dist.get_rank(), dist.get_world_size()
        return 0, 1

    def _device(self) -> torch.device:
        name = self.config.train.device
        if name == "auto":
            name = "cuda" if torch.cuda.is_available() else "cpu"
        if name.startswith("cuda"):
            if not torch.cuda.is_available():
                raise ConfigError(f"config key 'train.device' is {name!r} but CUDA is not available; use cpu or auto")
            if name == "cuda" and self.world > 1:
                name = f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
            torch.cuda.set_device(torch.device(name))
        return torch.device(name)

    def _start_run_folder(self) -> None:
        import yaml

        self.run_dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.run_dir / "config.yaml") as tmp:
            tmp.write_text(yaml.safe_dump(to_dict(self.config), sort_keys=False))
        with atomic_path(self.run_dir / "metrics.csv") as tmp:
            tmp.write_text(",".join(METRICS_FIELDS) + "\n")
        metadata = self.dataset_folder / "metadata.json"
        if metadata.is_file():  # the dataset's generating config, so the run folder stands alone
            with atomic_path(self.run_dir / "dataset.json") as tmp:
                tmp.write_text(json.dumps(json.loads(metadata.read_text())["config"], indent=1))

    def _check_resumable(self) -> None:
        saved_path = self.run_dir / "config.yaml"
        if not saved_path.is_file():
            return
        saved, now = _flat(load(saved_path)), _flat(to_dict(self.config))
        changed = sorted(k for k in set(saved) | set(now) if k not in _OPERATIONAL and saved.get(k) != now.get(k))
        if changed:
            key = changed[0]
            raise ConfigError(f"cannot resume {self.run_dir}: config key '{key}' changed from {saved.get(key)!r} to "
                              f"{now.get(key)!r}; resume with the run's own config.yaml or start a new run name")

    def _restore(self, checkpoint: dict) -> None:
        try:
            self.model.load_state_dict(checkpoint["model"])
            self.optimizer.load_state_dict(checkpoint["optimizer"])
            self.scheduler.load_state_dict(checkpoint["scheduler"])
        except (KeyError, RuntimeError, ValueError) as exc:
            raise CheckpointError(f"checkpoint {self.latest} does not fit this config ({exc}); resume with the "
                                  "run's own config.yaml") from None
        self.step, self.best_valid = int(checkpoint["step"]), float(checkpoint["best_valid"])
        self.seconds = float(checkpoint["seconds"])
        _set_rng_state(checkpoint["rng"])
        if self.rank == 0:
            self._truncate_metrics()

    def _truncate_metrics(self) -> None:
        path = self.run_dir / "metrics.csv"
        rows = []
        if path.is_file():
            with open(path, newline="") as fh:
                rows = [r for r in csv.DictReader(fh) if int(r["step"]) <= self.step]
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, METRICS_FIELDS)
            writer.writeheader()
            writer.writerows(rows)

    # -- checkpoints
    def state(self) -> dict:
        return {
            "format": 1, "config": to_dict(self.config), "dim": self.train_set.dim, "step": self.step,
            "best_valid": self.best_valid, "seconds": self.seconds, "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(), "rng": _rng_state(),
        }

    def save(self, path: Path) -> None:
        if self.rank == 0:
            save_checkpoint(path, self.state())

    # -- batches
    def global_batch(self, step: int) -> list[int]:
        """Sample indices of ``step`` (all processes): a slice of a per-epoch permutation."""
        n, size = len(self.train_set), self.config.train.batch_size
        per_epoch = n // size
        epoch, k = divmod(step, per_epoch)
        order = np.random.default_rng([self.config.train.seed, epoch]).permutation(n)
        return [int(i) for i in order[k * size:(k + 1) * size]]

    def _keys(self, step: int) -> list[tuple[int, tuple[int, int, int]]]:
        return [(i, (self.config.train.seed, step, i)) for i in self.global_batch(step)[self.rank::self.world]]

    def _loader(self, start: int, stop: int):
        keys = [self._keys(s) for s in range(start, stop)]
        return torch.utils.data.DataLoader(
            self.train_set, batch_sampler=keys, collate_fn=_collate, num_workers=self.config.train.workers,
            persistent_workers=False,
        )

    # -- one step
    def train_step(self, batch) -> float:
        """One optimiser step on this process's part of the batch; returns the batch's loss."""
        self.model.train()
        batch = batch.to(self.device)
        count = batch.loss_mask.sum().to(torch.float64)
        if self.world > 1:
            dist.all_reduce(count)
        accumulate = self.step < self.config.train.normalizer_steps
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.config.train.amp):
            loss = self.model.loss(batch, accumulate=accumulate, reduction="sum") / count.clamp(min=1).float()
        self.optimizer.zero_grad(set_to_none=False)
        loss.backward()
        if self.world > 1:
            grads = [p.grad for p in self.model.parameters()]
            flat = torch.cat([g.reshape(-1) for g in grads])
            dist.all_reduce(flat)
            torch.nn.utils.vector_to_parameters(flat, grads)
            reduced = loss.detach().clone()
            dist.all_reduce(reduced)
            value = float(reduced)
        else:
            value = float(loss.detach())
        if self.config.optim.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.optim.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        return value

    @torch.no_grad()
    def validate(self) -> float:
        """One-step RMSE (m) of the next position of free nodes over the validation samples."""
        self.model.eval()
        n = len(self.valid_set)
        picks = np.unique(np.linspace(0, n - 1, min(n, self.config.train.valid_samples)).round().astype(int))
        squared, count = 0.0, 0
        size = self.config.train.batch_size
        for start in range(0, len(picks), size):
            batch = Batch.from_data_list([self.valid_set[int(i)] for i in picks[start:start + size]]).to(self.device)
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.config.train.amp):
                change = self.model.output_normalizer.inverse(self.model(batch).float())
            error = (change - batch.target) * batch.frame_dt[:, None]
            squared += float(error[batch.loss_mask].square().sum())
            count += int(batch.loss_mask.sum())
        return math.sqrt(squared / max(count, 1))

    # -- the loop
    def _log(self, row: dict) -> None:
        with open(self.run_dir / "metrics.csv", "a", newline="") as fh:
            csv.DictWriter(fh, METRICS_FIELDS).writerow(row)

    def fit(self, stop_at: int | None = None) -> dict:
        """Train until ``train.steps`` (or ``stop_at``, then save as if interrupted).

        Returns a summary: steps, final loss, best validation RMSE, seconds.
        """
        from tqdm import tqdm

        t = self.config.train
        stop = t.steps if stop_at is None else min(stop_at, t.steps)
        bar = tqdm(total=t.steps, initial=self.step, desc=self.config.name, unit="step",
                   disable=not (t.progress and self.rank == 0))
        losses, window_start, window_steps = [], time.perf_counter(), 0
        last_loss = math.nan
        try:
            for batch in self._loader(self.step, stop):
                start = time.perf_counter()
                last_loss = self.train_step(batch)
                self.seconds += time.perf_counter() - start
                losses.append(last_loss)
                window_steps += 1
                bar.update()
                bar.set_postfix(loss=f"{last_loss:.3g}")
                validate = self.step % t.valid_every == 0 or self.step == t.steps
                row = None
                if self.step % t.log_every == 0 or validate:
                    elapsed = time.perf_counter() - window_start
                    row = {"step": self.step, "loss": f"{np.mean(losses):.6g}",
                           "lr": f"{self.scheduler.get_last_lr()[0]:.6g}", "seconds": f"{self.seconds:.3f}",
                           "samples_per_s": f"{window_steps * t.batch_size / max(elapsed, 1e-9):.3f}",
                           "valid_rmse": ""}
                    losses, window_start, window_steps = [], time.perf_counter(), 0
                if validate:
                    if self.rank == 0:
                        rmse = self.validate()
                        row["valid_rmse"] = f"{rmse:.6g}"
                        bar.set_postfix(loss=f"{last_loss:.3g}", valid=f"{rmse:.3g}")
                        if rmse < self.best_valid:
                            self.best_valid = rmse
                            self.save(self.best_path)
                    if self.world > 1:
                        holder = [self.best_valid]
                        dist.broadcast_object_list(holder, src=0)
                        self.best_valid = holder[0]
                if row is not None and self.rank == 0:
                    self._log(row)
                if self.step % t.checkpoint_every == 0 or self.step == stop:
                    self.save(self.latest)
        except KeyboardInterrupt:
            self.save(self.latest)
            bar.close()
            raise
        bar.close()
        if self.step == stop:
            self.save(self.latest)
        return {"steps": self.step, "loss": last_loss, "best_valid_rmse": self.best_valid, "seconds": self.seconds}

