"""benchmarks/learned_frame.py: stage timings per run, and --without-compiled's baseline row."""

import os
import re
import sys
from pathlib import Path

from conftest import tiny_run_config

from bsms.graph import native as graph_native
from bsms.models import native as model_native
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import learned_frame  # noqa: E402


def test_the_torch_baseline_row_comes_first_and_the_compiled_loops_come_back(tiny_dataset, tmp_path, capsys,
                                                                               monkeypatch):
    monkeypatch.delenv("BSMS_NATIVE", raising=False)
    config = load_config(tiny_run_config(tiny_dataset, tmp_path, name="lean",
                                         model={"hidden_layers": 1, "layer_norm": False},
                                         train={"steps": 4, "valid_every": 4, "checkpoint_every": 4}))
    Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    run = str(tmp_path / "lean")
    assert learned_frame.main([run, "--trajectories", "1", "--repeats", "1", "--without-compiled"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line.split()[0] for line in lines[:3]] == ["run", "lean,", "lean"] and len(lines) == 4
    torch_row, compiled_row = ([float(x) for x in line.split()[-8:]] for line in lines[1:3])
    assert all(x >= 0 for x in torch_row + compiled_row) and torch_row[-1] > 0 and compiled_row[-1] > 0
    assert lines[-1].startswith(f"learned frame: lean, torch {torch_row[-1]:.2f} ms (graph {torch_row[5]:.2f}, "
                                f"network {torch_row[6]:.2f}), lean {compiled_row[-1]:.2f} ms")
    assert re.fullmatch(r".*\(graph \d+\.\d\d, network \d+\.\d\d\): \d+\.\d\d x faster", lines[-1]), lines[-1]
    assert "BSMS_NATIVE" not in os.environ  # the compiled loops are on again afterwards
    assert graph_native.library() is not None and model_native.library() is not None
