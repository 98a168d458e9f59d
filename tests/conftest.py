"""Shared test fixtures.

The suite runs in two worker processes (pytest-xdist, ``-n 2`` in pyproject.toml's addopts; ``-n 0``
runs it in one): each worker, and every process a test starts, computes on one thread, so that two
workers on two cores do not fight over them (torch's OpenMP threads slow many times over when
another process holds a core)."""

import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = "1"

import pytest  # noqa: E402
import torch  # noqa: E402

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)


@pytest.fixture
def one_thread():
    """Small solver problems run fastest (and most steadily on a shared machine) on one thread."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


TINY_DATASET = """\
extends: {base}
dataset: tiny_glyphs
splits: {{train: 2, valid: 1, test: 1}}
ranges: {{count: [1, 2]}}
params: {{body_size: 0.05, mesh_size: 0.1}}
output: {{frames: 6, frame_interval: 0.05}}
"""


TINY_DATASET_3D = """\
extends: {base}
dataset: tiny_balls
splits: {{train: 2, valid: 1, test: 1}}
ranges: {{count: 1}}
output: {{frames: 4, frame_interval: 0.05}}
"""


def _tiny(tmp_path_factory, name: str, template: str, base: str):
    from pathlib import Path

    from datagen.generate import generate

    folder = tmp_path_factory.mktemp(name)
    config = folder / f"{name}.yaml"
    config.write_text(template.format(base=Path(__file__).resolve().parents[1] / "configs" / "datasets" / base))
    generate(config, out=folder / "data", progress=False)
    return config, folder / "data"


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """(dataset config path, data root) of a tiny glyphs dataset generated once per session."""
    return _tiny(tmp_path_factory, "tiny_glyphs", TINY_DATASET, "glyphs_quick.yaml")


@pytest.fixture(scope="session")
def tiny_folder(tiny_dataset, tmp_path_factory):
    """The tiny dataset's folder, prepared as a training run prepares it (trajectories, metadata)."""
    from bsms.run import load_config, prepare_dataset

    config = load_config(tiny_run_config(tiny_dataset, tmp_path_factory.mktemp("runs")))
    return prepare_dataset(config, progress=False)


@pytest.fixture(scope="session")
def tiny_dataset_3d(tmp_path_factory):
    """(dataset config path, data root) of a tiny 3D balls dataset generated once per session."""
    return _tiny(tmp_path_factory, "tiny_balls", TINY_DATASET_3D, "balls_quick.yaml")


def tiny_run_config(tiny, runs, /, name: str = "tiny", **sections) -> dict:
    """A training config dict on the tiny dataset ``tiny``: small model, few steps, no progress bars."""
    dataset_config, data_root = tiny
    config = {
        "name": name, "runs": str(runs),
        "dataset": {"config": str(dataset_config), "root": str(data_root), "generate": False},
        "graph": {"levels": 3, "constants": ["log_E"]},
        "noise": {"position": 2e-4, "velocity": 1e-3},
        "model": {"name": "bsms_gnn", "latent": 32},
        "optim": {"lr": 1e-3, "warmup": 3},
        "train": {"steps": 12, "batch_size": 2, "normalizer_steps": 6, "log_every": 4, "valid_every": 6,
                  "checkpoint_every": 6, "progress": False, "valid_samples": 4},
    }
    for section, values in sections.items():
        config[section] = {**config.get(section, {}), **values} if isinstance(values, dict) else values
    return config
