"""bsms.training.training_log: metrics.csv and TensorBoard event files, read back with TensorBoard's own
reader, across a resume."""

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import tiny_run_config
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from bsms.config import ConfigError
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer
from bsms.training.training_log import TENSORBOARD_TAGS

ROOT = Path(__file__).resolve().parents[1]


def _scalars(folder) -> dict[str, list[tuple[int, float]]]:
    events = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def _rows(run_dir) -> list[dict]:
    with open(run_dir / "metrics.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_tensorboard_holds_what_metrics_csv_holds_after_a_resume(tiny_dataset, tmp_path, one_thread):
    data = tiny_run_config(tiny_dataset, tmp_path, graph={"levels": 3}, train={
        "tensorboard": True, "steps": 12, "log_every": 2, "valid_every": 4, "validation": "rollout"})
    folder = prepare_dataset(load_config(data), progress=False)
    run_dir = tmp_path / "tiny"
    latest = run_dir / "checkpoints" / "latest.pt"
    Trainer(load_config(data), dataset_folder=folder).fit(stop_at=6)
    shutil.copyfile(latest, tmp_path / "step6.pt")
    Trainer(load_config(data), dataset_folder=folder, resume=True).fit(stop_at=10)
    # a crash after step 10 that lost every checkpoint after step 6: steps 8 and 10 are trained,
    # logged and validated again on resume; none may appear twice
    shutil.copyfile(tmp_path / "step6.pt", latest)
    Trainer(load_config(data), dataset_folder=folder, resume=True).fit()
    rows = _rows(run_dir)
    assert [int(r["step"]) for r in rows] == [2, 4, 6, 8, 10, 12]
    scalars = _scalars(run_dir / "tensorboard")
    assert set(scalars) == set(TENSORBOARD_TAGS.values())
    for column, tag in TENSORBOARD_TAGS.items():
        expected = [(int(r["step"]), float(r[column])) for r in rows if r[column] != ""]
        got = sorted(scalars[tag])
        assert [s for s, _ in got] == [s for s, _ in expected], f"{tag}: steps"
        assert [v for _, v in got] == pytest.approx([v for _, v in expected], rel=1e-6), tag  # float32 events
    assert [s for s, _ in sorted(scalars["valid/vs_rest"])] == [4, 8, 12]


def test_without_tensorboard_nothing_is_written_there(tiny_dataset, tmp_path, one_thread):
    data = tiny_run_config(tiny_dataset, tmp_path, train={"steps": 2, "log_every": 1, "valid_every": 2})
    Trainer(load_config(data), dataset_folder=prepare_dataset(load_config(data), progress=False)).fit()
    assert not (tmp_path / "tiny" / "tensorboard").exists()
    assert [int(r["step"]) for r in _rows(tmp_path / "tiny")] == [1, 2]


def test_asking_for_tensorboard_without_it_names_the_extra(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # import fails as if not installed
    data = tiny_run_config(tiny_dataset, tmp_path, train={"tensorboard": True})
    with pytest.raises(ConfigError) as error:
        Trainer(load_config(data), dataset_folder=prepare_dataset(load_config(data), progress=False))
    assert str(error.value) == ("config key 'train.tensorboard' needs the tensorboard package, which is not "
                                "installed: pip install \"bsms[tensorboard]\" (or pip install tensorboard), or set "
                                "train.tensorboard=false")
    assert not (tmp_path / "tiny").exists(), "nothing is written before the error"


def test_train_py_with_the_tensorboard_override_writes_events_tensorboard_reads(tiny_dataset, tmp_path):
    """The documented command form: ``python train.py CONFIG train.tensorboard=true``."""
    config = tmp_path / "run.yaml"
    config.write_text(yaml.safe_dump(tiny_run_config(tiny_dataset, tmp_path / "runs", train={
        "steps": 4, "log_every": 2, "valid_every": 4, "checkpoint_every": 4}, evaluate={"enabled": False})))
    result = subprocess.run([sys.executable, str(ROOT / "train.py"), str(config), "train.tensorboard=true", "--quiet"],
                            capture_output=True, text=True, cwd=tmp_path, timeout=300,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr
    scalars = _scalars(tmp_path / "runs" / "tiny" / "tensorboard")
    rows = _rows(tmp_path / "runs" / "tiny")
    assert [s for s, _ in scalars["train/loss"]] == [2, 4]
    assert [v for _, v in scalars["train/loss"]] == pytest.approx([float(r["loss"]) for r in rows], rel=1e-6)
    assert [s for s, _ in scalars["valid/rmse"]] == [4]
