"""Shared test fixtures."""

import pytest
import torch


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


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """(dataset config path, data root) of a tiny glyphs dataset generated once per session."""
    from pathlib import Path

    from datagen.generate import generate

    folder = tmp_path_factory.mktemp("tiny_dataset")
    base = Path(__file__).resolve().parents[1] / "configs" / "datasets" / "glyphs_quick.yaml"
    config = folder / "tiny_glyphs.yaml"
    config.write_text(TINY_DATASET.format(base=base))
    generate(config, out=folder / "data", progress=False)
    return config, folder / "data"
