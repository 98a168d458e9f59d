"""Training: a resumable, interruptible, multi-process trainer of the model a run config
describes.

The run folder (:mod:`bsms.run`) gains ``metrics.csv`` (step, loss, lr, seconds, samples_per_s,
valid_rmse; valid_vs_rest with rollout validation; and TensorBoard event files with
``train.tensorboard``: :mod:`bsms.training.training_log`) and ``checkpoints/{latest,best}.pt``.
Checkpoints hold the model with its normalisers, the optimiser, the scheduler, the step and the
RNG states; they are written atomically and read with ``weights_only=True``. Ctrl-C (SIGINT)
stops training after the step under way, with ``latest.pt`` saved at that step; a second Ctrl-C
stops at once.

Determinism: the samples of step ``s`` are a function of (seed, s) only (a per-epoch
permutation, :mod:`bsms.training.batches`), and the training noise of a sample of (seed, s, index), so a
resumed run continues exactly and a batch split over processes sees the same noise as one
process. Launched with ``torchrun --nproc_per_node K``, each process takes every K-th sample of
the global batch (or, with ``train.shard``, holds a K-th of the training trajectories and draws
its part of the batch from them); gradients are summed over processes after each process
divided its squared error sum by the free-node count of the whole batch, which makes the update
identical to one process on the whole batch (normaliser statistics are summed over processes
too). Multi-step training
(``train.unroll``) unrolls each sample over several model steps (:mod:`bsms.training.unroll`); the
validation RMSE stays one-step.
"""

from __future__ import annotations

import math
import os
import random
import signal
import threading
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import yaml
from tqdm import tqdm

from bsms.checkpoint import FORMAT, CheckpointError, load_checkpoint, save_checkpoint
from bsms.config import ConfigError, load, to_dict, without_retired
from bsms.data import FrameDataset
from bsms.models.precision import cpu_has_bf16
from bsms.options import GraphOptions
from bsms.run import (
    Config,
    build_model,
    checkpoint_path,
    prepare_dataset,
    resolve_device,
    split_files,
    write_run_files,
)
from bsms.training.batches import Batches, shard_of
from bsms.training.training_log import METRICS_FIELDS, TrainingLog, require_tensorboard
from bsms.training.unroll import UnrollBatch, UnrollSamples, collate, unrolled_loss
from bsms.training.validation import one_step_rmse, rollout_scores
from datagen.dataset import load as load_trajectory

__all__ = ["Trainer", "TrainingDiverged", "lr_factor", "METRICS_FIELDS"]

# These may change when a run is resumed; anything else must match the run's saved config.
_OPERATIONAL = {"train.progress", "train.workers", "train.device", "dataset.workers", "dataset.generate",
                "evaluate.batch", "train.tensorboard"}
# Keys added after runs were saved, with the value that keeps what those runs did.
_ADDED = {"dataset.kind": "mpm", "graph.contact_distance": None, "train.unroll": 1, "train.unroll_gradient": "last",
          "train.unroll_warmup": 0, "graph.from_rest": False, "train.trajectories": None,
          "graph.penetration": False, "graph.clearance": False, "train.rotate": 0.0,
          "graph.elastic": False, "train.shard": False}


def _flat(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        out.update(_flat(value, name + ".") if isinstance(value, dict) else {name: value})
    return out


# ----------------------------------------------------------------------------- schedule, RNG, interrupts
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


def _seed_everything(seed: int) -> None:
    """Seed every global RNG a run may draw from (torch, numpy's legacy one, Python's) from the config."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 (the legacy global RNG, for code that uses it)
    random.seed(seed)


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    pos, has_gauss, gauss = state["numpy_rest"]
    keys = state["numpy_keys"].numpy().astype(np.uint32)
    np.random.set_state(("MT19937", keys, pos, has_gauss, gauss))  # noqa: NPY002 (the legacy global RNG)
    random.setstate((3, tuple(state["python"]), state["python_gauss"]))


class _StopRequest:
    """While active (main thread only), the first SIGINT or SIGTERM is recorded instead of acted
    on, so that training stops between steps with a consistent state and saves it; a second
    one raises KeyboardInterrupt at once. ``signal_name`` says which arrived."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)
    requested = False
    signal_name = ""

    def __enter__(self) -> _StopRequest:
        self._previous = {}
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._record) for sig in self.SIGNALS}
        return self

    def _record(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested, self.signal_name = True, signal.Signals(signum).name

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)


class TrainingDiverged(RuntimeError):
    """The loss, a gradient or the weights went non-finite; the message names the step, what
    went non-finite, the usual causes and what latest.pt holds. ``weights_finite``: whether the
    weights were still finite (then they are saved in latest.pt)."""

    weights_finite = False


def _ignore_interrupts(worker_id: int) -> None:
    """Data-loading workers leave Ctrl-C and SIGTERM to the trainer, which stops between steps."""
    for sig in _StopRequest.SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


# ----------------------------------------------------------------------------- trainer
class Trainer:
    """Trains the model of ``config`` on its dataset, writing the run folder (rank 0 only).

    Args:
        config: the run's :class:`~bsms.run.Config`.
        resume: continue from ``<run>/checkpoints/latest.pt``; without it a run folder that
            already holds a checkpoint is an error (nothing is overwritten).
        dataset_folder: the dataset (default: prepared from ``config.dataset``).
        base: folder a relative ``dataset.config`` may be relative to.
    """

    def __init__(self, config: Config, *, resume: bool = False, dataset_folder=None, base: Path | None = None):
        self.config = config
        self.rank, self.world = self._init_distributed()
        self.device = self._device()
        self.run_dir = config.run_dir
        self.latest, self.best_path = checkpoint_path(self.run_dir, "latest"), checkpoint_path(self.run_dir, "best")
        self._check_run_folder(resume)
        if config.train.tensorboard and self.rank == 0:
            require_tensorboard()  # before anything is written
        progress = config.train.progress and self.rank == 0
        self.dataset_folder = Path(self._dataset_folder(dataset_folder, base, progress))
        cache = self.dataset_folder / "hierarchies"
        self.train_set = FrameDataset(self._train_files(), config.graph, config.noise,
                                      cache_dir=cache, progress=progress, mirror=config.train.mirror,
                                      loss_weight=config.train.loss_weight, rotate=config.train.rotate,
                                      frame_stride=config.train.frame_stride)
        self.valid_set = FrameDataset(split_files(self.dataset_folder, "valid"), config.graph, cache_dir=cache,
                                      progress=progress, frame_stride=config.train.frame_stride)
        if config.train.validation == "rollout" and not self.valid_set.spec.is_lagrangian:
            raise ConfigError("config key 'train.validation' is 'rollout', but the dataset holds Eulerian fields "
                              f"({self.valid_set.spec.describe()}); validate them one step at a time (one_step)")
        self._valid_trajectories = None  # loaded at the first rollout validation
        self.valid_vs_rest = None  # the last rollout validation's skill (bsms.rollouts.motion)
        self.samples = UnrollSamples(self.train_set, config.train.unroll)  # (trajectory, t) with t + K <= T - 1
        t = config.train
        self.batches = Batches(len(self.samples), t.batch_size, t.seed, self.rank, self.world, t.shard,
                               source=str(self.dataset_folder))
        _seed_everything(config.train.seed)
        self.model = build_model(config, self.train_set.dim, self.train_set.spec).to(self.device)
        if self.world > 1:
            for tensor in [*self.model.parameters(), *self.model.buffers()]:
                dist.broadcast(tensor.data, src=0)
        o = config.optim
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=o.lr, weight_decay=o.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: lr_factor(s, o.warmup, config.train.steps, o.min_lr_ratio))
        self.step, self.best_valid, self.seconds = 0, math.inf, 0.0
        if resume:
            self._check_resumable()
            self._restore(load_checkpoint(self.latest))
        elif self.rank == 0:
            write_run_files(config, self.dataset_folder)
        self.log = TrainingLog(self.run_dir, config.train.tensorboard, self.step if resume else None) \
            if self.rank == 0 else None

    # -- setup
    def _train_files(self) -> list[Path]:
        """The training trajectories: all of them, or the first ``train.trajectories``."""
        files, wanted = split_files(self.dataset_folder, "train"), self.config.train.trajectories
        if wanted is not None and wanted > len(files):
            raise ConfigError(f"config key 'train.trajectories' asks for {wanted} training trajectories, but "
                              f"{self.dataset_folder / 'train'} holds {len(files)}; ask for fewer or generate more "
                              "(splits.train in the dataset config)")
        return shard_of(files[:wanted], self.rank, self.world, self.config.train.shard)

    @staticmethod
    def _init_distributed() -> tuple[int, int]:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world > 1 and not dist.is_initialized():
            backend = "nccl" if torch.cuda.is_available() and os.environ.get("BSMS_BACKEND") != "gloo" else "gloo"
            dist.init_process_group(backend)
        if dist.is_available() and dist.is_initialized():
            return dist.get_rank(), dist.get_world_size()
        return 0, 1

    @property
    def _precision(self) -> str:
        """The core network's number format (``train.amp``: bfloat16 autocast)."""
        return "bf16" if self.config.train.amp else "f32"

    def _device(self) -> torch.device:
        t = self.config.train
        device = resolve_device(t.device, "train.device")
        if device.type == "cuda":
            if device.index is None:  # set_device needs an index: this process's GPU
                local = int(os.environ.get("LOCAL_RANK", "0")) if self.world > 1 else torch.cuda.current_device()
                device = torch.device("cuda", local)
            torch.cuda.set_device(device)
        elif t.amp and not cpu_has_bf16():
            raise ConfigError("config key 'train.amp' needs a CUDA device or a CPU with bfloat16 instructions "
                              "(AMX-BF16 or AVX512-BF16) for bfloat16 autocast, and this CPU has neither; set "
                              "train.amp: false")
        if t.batch_size < self.world:
            raise ConfigError(f"config key 'train.batch_size' ({t.batch_size}) must be at least the "
                              f"number of processes ({self.world})")
        return device

    def _check_run_folder(self, resume: bool) -> None:
        if not resume and self.latest.exists():
            raise ConfigError(f"run folder {self.run_dir} already holds a checkpoint; pass --resume to continue it, "
                              f"or choose another name (name=...)")
        if resume and not self.latest.exists():
            raise ConfigError(f"cannot resume: {self.latest} does not exist; start the run without --resume")

    def _dataset_folder(self, given, base: Path | None, progress: bool):
        if given is not None:
            return given
        folder = prepare_dataset(self.config, base, progress) if self.rank == 0 else None
        if self.world > 1:
            holder = [str(folder)]
            dist.broadcast_object_list(holder, src=0)
            folder = holder[0]
        return folder

    def _check_resumable(self) -> None:
        saved_path = self.run_dir / "config.yaml"
        if not saved_path.is_file():
            return
        saved = load(saved_path)  # less the keys retired since (an error where the run used one)
        saved["graph"] = without_retired(GraphOptions.RETIRED, saved.get("graph") or {}, "graph")
        saved, now = {**_ADDED, **_flat(saved)}, _flat(to_dict(self.config))
        changed = sorted(k for k in set(saved) | set(now) if k not in _OPERATIONAL and saved.get(k) != now.get(k))
        if changed:
            key = changed[0]
            was = "absent (the run predates it)" if key not in saved else repr(saved[key])
            keep = yaml.safe_dump(saved.get(key), default_flow_style=True).strip().removesuffix("...").strip()
            raise ConfigError(f"cannot resume {self.run_dir}: config key '{key}' was {was} and is now "
                              f"{now.get(key)!r}; resume with {key}={keep} (what the run was trained with), or start "
                              "a new run name")

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

    # -- checkpoints
    def state(self) -> dict:
        return {
            "format": FORMAT, "config": to_dict(self.config), "dim": self.train_set.dim,
            "fields": self.train_set.spec.to_dict(), "step": self.step,
            "best_valid": self.best_valid, "seconds": self.seconds, "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(), "rng": _rng_state(),
        }

    def save(self, path: Path) -> None:
        if self.rank == 0:
            save_checkpoint(path, self.state())

    # -- batches
    def global_batch(self, step: int) -> list[int]:
        """Sample indices of ``step``: the global batch (all processes), or this process's own
        with ``train.shard`` (:class:`bsms.training.batches.Batches`)."""
        return self.batches.drawn(step)

    def _loader(self, start: int, stop: int):
        keys = [self.batches.keys(s) for s in range(start, stop)]
        # the loader's own generator, so that starting it does not draw from the global torch RNG
        # (a resumed run then continues the global stream, e.g. of dropout, exactly)
        generator = torch.Generator().manual_seed(self.config.train.seed * 1_000_003 + start)
        return torch.utils.data.DataLoader(
            self.samples, batch_sampler=keys, collate_fn=collate, num_workers=self.config.train.workers,
            persistent_workers=False, worker_init_fn=_ignore_interrupts, generator=generator,
        )

    # -- one step
    def train_step(self, batch) -> float:
        """One optimiser step on this process's part of the batch (an :class:`~bsms.training.unroll.UnrollBatch`,
        or a PyG ``Batch`` of one-step samples), unrolled over ``train.unroll`` model steps (after
        ``train.unroll_warmup`` steps); returns the batch's loss."""
        self.model.train()
        batch = (batch if isinstance(batch, UnrollBatch) else UnrollBatch(batch)).to(self.device)
        count = batch.graph.loss_mask.sum().to(torch.float64)
        if self.world > 1:
            dist.all_reduce(count)
        t = self.config.train
        loss = unrolled_loss(self.model, batch, self.samples, 1 if self.step < t.unroll_warmup else t.unroll,
                             t.unroll_gradient, accumulate=self.step < t.normalizer_steps, precision=self._precision)
        loss = loss / count.clamp(min=1).float()
        self.optimizer.zero_grad(set_to_none=False)
        loss.backward()
        loss = loss.detach()
        if self.world > 1:
            grads = [p.grad for p in self.model.parameters()]
            flat = torch.cat([g.reshape(-1) for g in grads])
            dist.all_reduce(flat)
            torch.nn.utils.vector_to_parameters(flat, grads)
            dist.all_reduce(loss)
        clip = self.config.optim.grad_clip
        norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), math.inf if clip is None else clip)
        self._check_finite(loss, norm)
        self.optimizer.step()
        self._check_weights()
        self.scheduler.step()
        self.step += 1
        return float(loss)

    def _diverged(self, what: str) -> TrainingDiverged:
        o = self.config.optim
        return TrainingDiverged(
            f"training diverged at step {self.step + 1}: {what}. Usual causes: a learning rate too large "
            f"(optim.lr is {o.lr:g}; 1e-4 to 1e-3 is typical), no gradient clipping (optim.grad_clip is "
            f"{o.grad_clip}), or training data with huge values")

    def _check_finite(self, loss: torch.Tensor, grad_norm: torch.Tensor) -> None:
        """TrainingDiverged (weights still finite) before an update from a non-finite loss or gradient."""
        bad = [name for name, value in (("loss", loss), ("gradient norm", grad_norm)) if not torch.isfinite(value)]
        if bad:
            error = self._diverged(f"the {' and the '.join(bad)} went non-finite (loss {float(loss):.4g}, "
                                   f"gradient norm {float(grad_norm):.4g})")
            error.weights_finite = True
            raise error

    def _check_weights(self) -> None:
        """TrainingDiverged (weights not finite) after an update that overflowed them."""
        params = dict(self.model.named_parameters())
        if bool(torch.stack([torch.isfinite(p).all() for p in params.values()]).all()):  # one sync a step
            return
        bad = [name for name, p in params.items() if not bool(torch.isfinite(p).all())]
        if bad:
            error = self._diverged(f"the update made {len(bad)} weight tensors non-finite ({bad[0]}, ...)")
            error.weights_finite = False
            raise error

    def validate(self) -> float:
        """One-step RMSE over the validation samples (:func:`~bsms.training.validation.one_step_rmse`); with
        ``train.validation: rollout`` the rollout RMSE over all steps and validation trajectories,
        its skill against predicting no motion kept as ``valid_vs_rest``
        (:func:`~bsms.training.validation.rollout_scores`)."""
        self.model.eval()
        t = self.config.train
        if t.validation == "one_step":
            return one_step_rmse(self.model, self.valid_set, t.valid_samples, t.batch_size, self.device,
                                 self._precision)
        if self._valid_trajectories is None:
            self._valid_trajectories = [load_trajectory(path) for path in split_files(self.dataset_folder, "valid")]
        rmse, self.valid_vs_rest = rollout_scores(self.model, self.config.graph, self._valid_trajectories,
                                                  self.dataset_folder / "hierarchies", self.device,
                                                  self.valid_set.scenarios if t.frame_stride == 1 else None)
        return rmse

    # -- the loop
    def _after_divergence(self, exc: TrainingDiverged) -> TrainingDiverged:
        """Save the weights if they are still finite; the error, completed with what latest.pt holds."""
        if exc.weights_finite:
            self.save(self.latest)
            held = f"{self.latest} holds the last finite weights (step {self.step})"
        elif self.latest.exists():
            held = (f"{self.latest} keeps its last checkpoint (step {int(load_checkpoint(self.latest)['step'])}), "
                    "whose weights are finite")
        else:
            held = "no checkpoint was written before it"
        done = TrainingDiverged(f"{exc}; {held}")
        done.weights_finite = exc.weights_finite
        return done

    def _validate_and_keep_best(self) -> float | None:
        """Validation RMSE on rank 0 (None elsewhere); best.pt follows the best so far."""
        rmse = None
        if self.rank == 0:
            rmse = self.validate()
            if rmse < self.best_valid:
                self.best_valid = rmse
                self.save(self.best_path)
        if self.world > 1:
            holder = [self.best_valid]
            dist.broadcast_object_list(holder, src=0)
            self.best_valid = holder[0]
        return rmse

    def _log(self, losses: list[float], since: float, rmse: float | None) -> None:
        """Log a row (metrics.csv, TensorBoard): mean loss, lr, time and throughput over the steps since ``since``."""
        elapsed = time.perf_counter() - since
        row = {"step": self.step, "loss": f"{np.mean(losses):.6g}", "lr": f"{self.scheduler.get_last_lr()[0]:.6g}",
               "seconds": f"{self.seconds:.3f}",
               "samples_per_s": f"{len(losses) * self.config.train.batch_size / max(elapsed, 1e-9):.3f}",
               "valid_rmse": "" if rmse is None else f"{rmse:.6g}",
               "valid_vs_rest": "" if rmse is None or self.valid_vs_rest is None else f"{self.valid_vs_rest:.6g}"}
        self.log.write(row)

    def _stop_requested(self, stop: _StopRequest) -> bool:
        if self.world == 1:
            return stop.requested
        flag = torch.tensor([float(stop.requested)], device=self.device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        return bool(flag.item())

    def fit(self, stop_at: int | None = None) -> dict:
        """Train until ``train.steps`` (or ``stop_at``, then save as if interrupted), or Ctrl-C.

        Returns a summary: steps, final loss, best validation RMSE, seconds, and whether a
        Ctrl-C stopped it (``interrupted``; latest.pt then holds the step reached).
        """
        t = self.config.train
        stop = t.steps if stop_at is None else min(stop_at, t.steps)
        bar = tqdm(total=t.steps, initial=self.step, desc=self.config.name, unit="step",
                   disable=not (t.progress and self.rank == 0))
        losses, since = [], time.perf_counter()
        last_loss, interrupted = math.nan, False
        with bar, _StopRequest() as request:
            for batch in self._loader(self.step, stop):
                start = time.perf_counter()
                try:
                    last_loss = self.train_step(batch)
                except TrainingDiverged as exc:
                    raise self._after_divergence(exc) from None
                self.seconds += time.perf_counter() - start
                losses.append(last_loss)
                bar.update()
                validate = self.step % t.valid_every == 0 or self.step == t.steps
                rmse = self._validate_and_keep_best() if validate else None
                bar.set_postfix(loss=f"{last_loss:.3g}", **({} if rmse is None else {"valid": f"{rmse:.3g}"}))
                if self.step % t.log_every == 0 or validate:
                    if self.rank == 0:
                        self._log(losses, since, rmse)
                    losses, since = [], time.perf_counter()
                interrupted = self._stop_requested(request)
                if self.step % t.checkpoint_every == 0 or self.step == stop or interrupted:
                    self.save(self.latest)
                if interrupted:
                    break
        if self.log is not None:
            self.log.flush()
        return {"steps": self.step, "loss": last_loss, "best_valid_rmse": self.best_valid, "seconds": self.seconds,
                "interrupted": interrupted, "signal": request.signal_name}
