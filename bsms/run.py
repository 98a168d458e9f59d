"""A training run: its typed config, its folder, its dataset and the model it describes.

Everything that both training (:mod:`bsms.training.trainer`) and the tools that read a finished run
(:mod:`bsms.evaluate`, :mod:`bsms.infer`) need lives here, so neither imports the other.

A run lives in ``<runs>/<name>/``: ``config.yaml`` (the resolved config), ``dataset.json``
(the generating config of its dataset, so the folder stands alone), ``metrics.csv`` and
``checkpoints/{latest,best}.pt`` (:mod:`bsms.checkpoint`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch
import yaml

from bsms.checkpoint import CheckpointError, load_checkpoint
from bsms.config import ConfigError, apply_overrides, at_least, build, load, to_dict
from bsms.data import GraphOptions, NoiseOptions, saved_graph_options
from bsms.ensemble import is_ensemble, load_ensemble
from bsms.fields import FieldSpec
from bsms.models.config import ModelConfig
from bsms.models.simulator import LearnedSimulator
from bsms.rollouts.rollout import DEFAULT_BOUND
from bsms.rollouts.solver_runs import SOLVER_SETTINGS, is_setting
from datagen.atomic import atomic_path
from datagen.dataset_config import load_dataset_config, trajectory_path
from datagen.generate import generate, jobs
from datagen.metadata import write_metadata

__all__ = [
    "Config", "DatasetConfig", "ModelConfig", "OptimConfig", "TrainConfig", "EvaluateConfig", "load_config",
    "checkpoint_path", "find_checkpoint", "write_run_files", "prepare_dataset", "run_dataset_config",
    "dataset_folder", "convert_fix", "split_files", "build_model", "load_model", "resolve_device",
]


# ----------------------------------------------------------------------------- config
@dataclass
class DatasetConfig:
    """kind: ``mpm`` (the solver's datasets), or ``deepmind`` / ``authors`` (a dataset converted
    with ``python -m bsms.datasets convert KIND SRC DST``, never generated).
    config (mpm): the dataset YAML (``configs/datasets/...``); root: mpm: the folder of
    datasets (the dataset is ``root/<its name>``); converted: the converted folder itself (DST).
    generate: generate missing trajectories (resumable) before training; workers: processes
    for that."""

    config: str = ""
    root: str = "data"
    generate: bool = True
    workers: int = 1
    kind: Literal["mpm", "deepmind", "authors"] = "mpm"

    def validate(self, prefix: str) -> None:
        if self.kind != "mpm":
            if self.config:
                raise ConfigError(f"config key '{prefix}.config' applies to MPM datasets; a {self.kind} dataset is "
                                  f"the folder '{prefix}.root' names (remove '{prefix}.config')")
        elif not self.config:
            raise ConfigError(f"config key '{prefix}.config' is required: the dataset config YAML, "
                              "e.g. configs/datasets/glyphs_quick.yaml")
        if self.workers < 1:
            raise ConfigError(f"config key '{prefix}.workers' must be >= 1, got {self.workers}")


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
        at_least(self, prefix, 0, ("weight_decay", "warmup"))
        if not 0.0 <= self.min_lr_ratio <= 1.0:
            raise ConfigError(f"config key '{prefix}.min_lr_ratio' must lie in [0, 1], got {self.min_lr_ratio}")
        if self.grad_clip is not None and self.grad_clip <= 0:
            raise ConfigError(f"config key '{prefix}.grad_clip' must be positive or null, got {self.grad_clip}")


@dataclass
class TrainConfig:
    """steps and batch_size (graphs per step, over all processes); normalizer_steps: batches
    the normalisers learn from before they freeze; log/valid/checkpoint cadence in steps;
    valid_samples: validation samples (evenly spread over the split); device: auto, cpu, cuda
    or cuda:N; amp: bfloat16 autocast of the network (CUDA, or CPUs with AMX-BF16 or AVX512-BF16;
    :mod:`bsms.models.precision`); workers: data-loading processes.

    Multi-step (pushforward) training (:mod:`bsms.training.unroll`): unroll: model steps per sample (K;
    1: one-step training). A sample is frame t of a trajectory with t + K <= T - 1; step 0 reads
    frame t (with the training noise), each later step the model's own prediction, integrated
    as a rollout integrates (kinematic nodes from the data), on a graph rebuilt from the
    predicted positions, with the target that brings that state to the data's next frame.
    unroll_gradient: ``last`` (pushforward: the first K-1 steps run without gradient, the last
    step's loss is trained), ``all`` (the mean of every step's loss; each step's state is
    passed on detached), ``through`` (the mean of every step's loss, with gradients through the
    predicted states into the later steps' inputs and targets). unroll_warmup: optimiser steps
    of one-step training (on the same samples) before unrolling starts. Normalisers learn from
    step 0 only.

    validation: what ``valid_rmse`` (and so ``best.pt``) measures: ``one_step``, the one-step
    RMSE over ``valid_samples`` samples; ``rollout``, the RMSE over all steps of rolling the
    model out from frame 0 on every validation trajectory (m; Lagrangian data only), the measure
    a learned simulator is used by (one-step error ranks checkpoints poorly where errors pile up).
    mirror: every training trajectory also enters reflected by x -> -x (:mod:`bsms.augment`;
    scenes symmetric under it: gravity along y, isotropic materials). trajectories: train on the
    first this many training trajectories only (null: all of them), for learning curves.
    tensorboard: also write the training log as TensorBoard event files to
    ``<run>/tensorboard/`` (:mod:`bsms.training.training_log`; needs ``pip install "bsms[tensorboard]"``).
    loss_weight: how the training trajectories weigh in the loss: ``uniform`` (every free node
    alike), or ``motion`` (Lagrangian data: each trajectory's nodes weighted by 1 / s^2, s its
    at-rest error, the RMS distance of its free nodes from frame 0 over all frames, floored at a
    quarter of the median s; weights scaled to mean 1 over the samples), so that the loss
    weighs each trajectory's error against its own motion as ``vs_rest`` does (:mod:`bsms.rollouts.motion`)
    and bodies that hardly move are not drowned by those that move far. rotate: each training
    sample turned by a random angle up to this many degrees (0: off; 180: any orientation;
    :mod:`bsms.augment`), for scenes whose physics has no preferred direction (gravity negligible);
    one-step training of Lagrangian data. shard: with several processes (``torchrun``), each holds
    only its share of the training trajectories and draws its part of every batch from it
    (:mod:`bsms.training.batches`): the training set's memory divided by the process count, for data sets
    too large to hold once per process; ``batch_size`` a multiple of the process count.
    frame_stride: k data frames per model step (Lagrangian models that carry state; :mod:`bsms.rollouts.stride`):
    trained on the steps t -> t + k from every frame, rolled out at k frame times per step with
    every data frame given back (cubic Hermite between the model's states)."""

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
    unroll: int = 1
    unroll_gradient: Literal["last", "all", "through"] = "last"
    unroll_warmup: int = 0
    validation: Literal["one_step", "rollout"] = "one_step"
    mirror: bool = False
    trajectories: int | None = None
    tensorboard: bool = False
    loss_weight: Literal["uniform", "motion"] = "uniform"
    rotate: float = 0.0
    shard: bool = False
    frame_stride: int = 1

    def validate(self, prefix: str) -> None:
        if not 0.0 <= self.rotate <= 180.0:
            raise ConfigError(f"config key '{prefix}.rotate' must lie in [0, 180] degrees, got {self.rotate}")
        if self.rotate and self.unroll > 1:
            raise ConfigError(f"config key '{prefix}.rotate' turns one-step samples; set '{prefix}.unroll: 1' or "
                              f"'{prefix}.rotate: 0'")
        if self.trajectories is not None and self.trajectories < 1:
            raise ConfigError(f"config key '{prefix}.trajectories' must be >= 1 (null: every training trajectory), "
                              f"got {self.trajectories}")
        at_least(self, prefix, 1, ("steps", "batch_size", "normalizer_steps", "log_every", "valid_every",
                                    "valid_samples", "checkpoint_every", "unroll", "frame_stride"))
        at_least(self, prefix, 0, ("seed", "workers", "unroll_warmup"))
        _check_device(self.device, f"{prefix}.device")


@dataclass
class EvaluateConfig:
    """The ``evaluate`` section of a training config (train.py evaluates after training).

    split: dataset split; trajectories: at most this many (null: all); steps: rollout steps
    (null: every frame of the trajectory); bound: relative error (of the body size) that
    marks a rollout unstable; solver: the solver settings to time and compare
    (:data:`bsms.rollouts.solver_runs.SOLVER_SETTINGS`; ``ground_truth`` is the speed-up's baseline);
    gifs: rollout GIFs to draw; device: auto, cpu or cuda[:N]; threads: CPU threads of the
    learned models and of the solver runs while timed (null: torch's default), so that every
    point is timed alike whatever solver.threads the data was made with (metrics.json records
    both); small graphs run fastest on one thread. batch: trajectories rolled out together, one
    model call per step on the batch of their graphs (a rollout's time per step is its share
    of the batch's step; 1: each rollout alone). workers: processes the work is spread over
    (each on ``threads`` threads): 1 runs the learned rollouts and then every solver run in this
    process; K > 1 makes the learned rollouts one job and each trajectory's solver runs another
    in a pool of K, so that every point, learned or solver, is timed while the other workers run
    (the same footing for all, and about K times sooner on K cores). checkpoint: which
    checkpoint of every run is evaluated: ``best`` (lowest validation RMSE) or ``latest`` (the
    fixed training budget; what a recipe that exports its last checkpoint ships).
    """

    enabled: bool = True
    split: str = "test"
    trajectories: int | None = None
    steps: int | None = None
    bound: float = DEFAULT_BOUND
    solver: list[str] = field(default_factory=lambda: list(SOLVER_SETTINGS))
    gifs: int = 2
    device: str = "auto"
    threads: int | None = 1
    batch: int = 8
    workers: int = 1
    checkpoint: Literal["best", "latest"] = "best"

    def validate(self, prefix: str) -> None:
        if self.split not in ("train", "valid", "test", "final"):
            raise ConfigError(f"config key '{prefix}.split' must be train, valid, test or final, got {self.split!r}")
        at_least(self, prefix, 1, ("trajectories", "steps", "threads"), optional=True)
        at_least(self, prefix, 0, ("gifs",))
        at_least(self, prefix, 1, ("batch", "workers"))
        if self.bound <= 0:
            raise ConfigError(f"config key '{prefix}.bound' must be positive, got {self.bound}")
        # runs saved before the setting was renamed list 'reference'
        self.solver = ["ground_truth" if s == "reference" else s for s in self.solver]
        unknown = sorted(s for s in self.solver if not is_setting(s))
        if unknown:
            raise ConfigError(f"unknown config key '{prefix}.solver.{unknown[0]}'; '{prefix}.solver' accepts: "
                              f"{', '.join(sorted(SOLVER_SETTINGS))}, or mass_scaling_S for a whole S >= 2")
        _check_device(self.device, f"{prefix}.device")


@dataclass
class Config:
    """A training run: what data, which graphs, which model, how to optimise, train and evaluate."""

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
        if self.model.first_level >= self.graph.levels:
            raise ConfigError(f"config key 'model.first_level' must be below 'graph.levels' ({self.graph.levels}): "
                              f"the coarsest level always passes messages; got {self.model.first_level}")
        if self.graph.from_rest and self.train.unroll > 1:
            raise ConfigError("config key 'train.unroll' must be 1 with 'graph.from_rest': every frame is predicted "
                              f"from the rest shape and the drive alone, so unrolled steps see the same inputs as "
                              f"single steps; got {self.train.unroll}")
        if self.graph.from_rest and self.train.frame_stride > 1:
            raise ConfigError("config key 'train.frame_stride' must be 1 with 'graph.from_rest': every frame is "
                              f"predicted from the rest shape alone, there is no step to stretch; got "
                              f"{self.train.frame_stride}")
        if self.model.mirror_average and not self.train.mirror:
            raise ConfigError("config key 'model.mirror_average' averages the answers to each frame and to its mirror "
                              "image: train the network on both images (train.mirror: true)")

    @property
    def run_dir(self) -> Path:
        return Path(self.runs) / self.name


def _device_label(key: str) -> str:
    return key if key.startswith("--") else f"config key '{key}'"


def _check_device(name: str, key: str) -> None:
    if not isinstance(name, str) or (
            name not in ("auto", "cpu", "cuda") and not (name.startswith("cuda:") and name[5:].isdigit())):
        raise ConfigError(f"{_device_label(key)} must be auto, cpu, cuda or cuda:N, got {name!r}")


def resolve_device(name: str, key: str) -> torch.device:
    """The device ``name`` names (auto: cuda where available, else cpu); ConfigError naming ``key``
    (a config key, or a ``--flag``) for a bad name or CUDA on a machine without."""
    _check_device(name, key)
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"{_device_label(key)} is {name!r} but CUDA is not available on this machine; use cpu "
                          "or auto")
    return torch.device(name)


def load_config(source, overrides: list[str] = ()) -> Config:
    """A checked :class:`Config` from a YAML path or a mapping, with ``key=value`` overrides."""
    data = load(source) if isinstance(source, (str, Path)) else dict(source)
    return build(Config, apply_overrides(data, list(overrides)))


# ----------------------------------------------------------------------------- run folder
def checkpoint_path(run_dir, which: str) -> Path:
    """``<run_dir>/checkpoints/<which>.pt`` (which: latest or best)."""
    return Path(run_dir) / "checkpoints" / f"{which}.pt"


def saved_options(run_dir) -> EvaluateConfig | None:
    """The evaluate section of a run folder's config.yaml (None without one), read before any
    checkpoint is chosen, so that a run whose ``evaluate.checkpoint`` is latest never opens best.pt."""
    path = Path(run_dir) / "config.yaml"
    return load_config(path).evaluate if path.is_file() else None


def find_checkpoint(run_dir, which: str = "best") -> Path:
    """The checkpoint ``which`` of a run folder, falling back from best to latest and from latest
    to best (a pretrained folder, :mod:`bsms.infer.pretrained`, holds its one checkpoint as best)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CheckpointError(f"run folder {run_dir} does not exist; train one with python train.py CONFIG")
    order = [which] + (["latest"] if which == "best" else ["best"])
    for name in order:
        if checkpoint_path(run_dir, name).is_file():
            return checkpoint_path(run_dir, name)
    raise CheckpointError(f"run folder {run_dir} has no usable checkpoint (looked for "
                          f"{', '.join(f'checkpoints/{n}.pt' for n in order)}); train it with python train.py CONFIG "
                          "(or --resume an interrupted run)")


def write_run_files(config: Config, dataset_folder: Path) -> None:
    """``config.yaml`` and (where the dataset has metadata) ``dataset.json`` of a new run folder."""
    run_dir = config.run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(run_dir / "config.yaml") as tmp:
        tmp.write_text(yaml.safe_dump(to_dict(config), sort_keys=False))
    metadata = Path(dataset_folder) / "metadata.json"
    if metadata.is_file():
        with atomic_path(run_dir / "dataset.json") as tmp:
            tmp.write_text(json.dumps(json.loads(metadata.read_text())["config"], indent=1))


def dataset_folder(run_dir, config: Config) -> tuple[Path, str]:
    """(folder, name) of a run's dataset: ``dataset.root`` itself for a converted dataset,
    ``dataset.root/<name>`` for an MPM one."""
    if config.dataset.kind != "mpm":
        return Path(config.dataset.root), Path(config.dataset.root).name
    name = run_dataset_config(run_dir, config)["dataset"]
    return Path(config.dataset.root) / name, name


def run_dataset_config(run_dir, config: Config) -> dict:
    """The generating dataset config of a run: its ``dataset.json``, else ``config.dataset.config``."""
    saved = Path(run_dir) / "dataset.json"
    if saved.is_file():
        return json.loads(saved.read_text())
    try:
        return load_dataset_config(config.dataset.config)
    except ConfigError as exc:
        raise CheckpointError(f"run folder {run_dir} has no dataset.json and its dataset config cannot be read "
                              f"({exc}); run from the folder train.py ran in") from None


# ----------------------------------------------------------------------------- dataset
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
    A converted dataset (``dataset.kind`` deepmind or authors) is never generated: its folder
    must hold the train and valid trajectories.
    """
    if config.dataset.kind != "mpm":
        folder = Path(config.dataset.root)
        for split in ("train", "valid"):
            split_files(folder, split, convert_fix(config.dataset.kind, folder, split))
        return folder
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


def convert_fix(kind: str, folder: Path, split: str) -> str:
    """What to do about a converted dataset folder that lacks ``split``."""
    source = "SRC (the folder of meta.json and {train,valid,test}.tfrecord)" if kind == "deepmind" else \
        "SRC (the folder of train/, valid/, test/ with <index>.h5 files)"
    return (f"convert it with python -m bsms.datasets convert {kind} SRC {folder} --split {split}, where {source}, "
            "or point the config at the folder you converted into with dataset.root=FOLDER")


def split_files(folder: Path, split: str, fix: str | None = None) -> list[Path]:
    """The trajectory files of ``split`` in a dataset folder, sorted; ConfigError when there are
    none (``fix``: what to do then, default: generate them)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"dataset folder {folder} does not exist (moved or deleted?); " + (
            fix or f"put the dataset back there, or regenerate it with python -m datagen DATASET_CONFIG "
                   f"--out {folder.parent}"))
    files = sorted((folder / split).glob("*.h5"))
    if not files:
        raise ConfigError(f"dataset folder {folder} has no {split} trajectories (files {folder / split}/*.h5); " + (
            fix or f"generate them (its dataset config must give splits.{split} > 0)"))
    return files


# ----------------------------------------------------------------------------- model
def build_model(config: Config, dim: int, fields: FieldSpec | None = None) -> LearnedSimulator:
    """The learned simulator a config describes, for dimension ``dim`` and the data's field spec
    ``fields`` (default: Lagrangian), untrained."""
    model = LearnedSimulator(
        config.model.name, dim, n_levels=config.graph.levels, contact=config.graph.contact,
        n_constants=len(config.graph.constants), latent=config.model.latent, n_passes=config.model.passes,
        hidden_layers=config.model.hidden_layers, max_accumulations=config.train.normalizer_steps,
        core_options=config.model.core_options(dim), fields=fields, penetration=config.graph.penetration,
        clearance=config.graph.clearance, elastic=config.graph.elastic, mirror_average=config.model.mirror_average,
        edge_velocity=config.model.edge_velocity, rigid_part=config.model.rigid_part,
        rigid_step=config.model.rigid_step,
    )
    model.frame_stride = config.train.frame_stride  # data frames per model step (bsms.rollouts.stride)
    return model


def load_model(source, which: str = "best", device="cpu") -> tuple[LearnedSimulator, Config, dict]:
    """(model in eval mode on ``device``, Config, checkpoint dict) from a run folder, a checkpoint
    file or an ensemble folder (:mod:`bsms.ensemble`: an :class:`~bsms.models.ensemble.Ensemble`,
    the first member's Config and checkpoint dict, ``members`` added)."""
    path = Path(source)
    if is_ensemble(path):
        return load_ensemble(path, which, device, load_model, run_dataset_config)
    path = path if path.is_file() else find_checkpoint(path, which)
    state = load_checkpoint(path)
    try:
        config = build(Config, {**state["config"], "graph": saved_graph_options(state["config"].get("graph"))})
    except ConfigError as exc:
        raise CheckpointError(f"checkpoint {path} holds a config this bsms cannot read ({exc})") from None
    try:
        fields = FieldSpec.from_dict(state["fields"], f"checkpoint {path}") if "fields" in state else None
        model = build_model(config, int(state["dim"]), fields)
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {path}: {exc}") from None
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"checkpoint {path}: its weights do not fit its own config ({str(exc)[:200]})") from None
    return model.to(device).eval(), config, state
