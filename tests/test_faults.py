"""Faults during training, through the real ``python train.py``: SIGINT (Ctrl-C) and SIGTERM (what
batch schedulers send before a kill) save the step reached; SIGKILL loses at most the steps
since the last checkpoint; in every case the command the run prints (or ``--resume``) ends
bit-identical to an uninterrupted run. Signals during start-up say truly that nothing is saved.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import tiny_run_config

from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]
STEPS = 60
TRAIN = {"steps": STEPS, "log_every": 1, "valid_every": 20, "checkpoint_every": 7}
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": os.pathsep.join(sys.path)}


def _config(tiny_dataset, tmp_path, name="run", **sections) -> Path:
    data = tiny_run_config(tiny_dataset, tmp_path / "runs", name=name, train=TRAIN, evaluate={"enabled": False},
                           **sections)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _default_interrupts() -> None:
    """In the child: SIGINT back to its default action, which Python then turns into
    KeyboardInterrupt (a test suite started in the background inherits it ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(config: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(ROOT / "train.py"), str(config), *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT, preexec_fn=_default_interrupts)


def _wait_for_steps(process: subprocess.Popen, metrics: Path, steps: int) -> None:
    deadline = time.monotonic() + 240
    while not metrics.is_file() or len(metrics.read_text().splitlines()) < steps + 1:  # a header, then a row a step
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.02)


def _weights(run: Path) -> dict:
    return torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["model"]


@pytest.fixture(scope="module")
def uninterrupted(tiny_dataset, tmp_path_factory):
    """The final weights of the run trained in one go (in-process, on one thread like the
    subprocesses: another thread count sums in another order)."""
    folder = tmp_path_factory.mktemp("whole")
    data = tiny_run_config(tiny_dataset, folder, name="whole", train=TRAIN, evaluate={"enabled": False})
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        trainer = Trainer(load_config(data), dataset_folder=prepare_dataset(load_config(data), progress=False))
        trainer.fit()
    finally:
        torch.set_num_threads(before)
    return trainer.model.state_dict()


def _assert_same(weights: dict, expected: dict) -> None:
    assert weights.keys() == expected.keys()
    for name, value in expected.items():
        assert torch.equal(weights[name], value), f"{name} differs from the uninterrupted run"


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_mid_run_saves_the_step_and_the_printed_command_resumes_exactly(
        tiny_dataset, tmp_path, uninterrupted, sig, code):
    config = _config(tiny_dataset, tmp_path)
    run = tmp_path / "runs" / "run"
    process = _start(config)
    _wait_for_steps(process, run / "metrics.csv", 3)
    process.send_signal(sig)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == code and "Traceback" not in stderr, stderr
    found = re.search(rf"{sig.name}: interrupted at step (\d+); saved in (\S+)\. Continue with: (.+)$", stderr.strip())
    assert found, stderr
    step = int(found.group(1))
    assert 3 <= step < STEPS and Path(found.group(2)) == run / "checkpoints" / "latest.pt"
    assert torch.load(found.group(2), weights_only=True)["step"] == step
    command = shlex.split(found.group(3))
    assert command[-1] == "--resume" and command[1] == str(ROOT / "train.py")
    resumed = subprocess.run([sys.executable, *command[1:]], capture_output=True, text=True, env=ENV, cwd=ROOT,
                             timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    _assert_same(_weights(run), uninterrupted)
    rows = (run / "metrics.csv").read_bytes()
    assert b"\r" not in rows and rows.count(b"\n") == STEPS + 1, "one row a step, each logged once, \\n endings"


def test_sigkill_at_a_random_moment_then_resume_is_bit_identical(tiny_dataset, tmp_path, uninterrupted):
    rng = np.random.default_rng(int(time.time()))
    at = int(rng.integers(8, 40))  # a step past the first checkpoint (every 7 steps)
    config = _config(tiny_dataset, tmp_path)
    run = tmp_path / "runs" / "run"
    process = _start(config)
    _wait_for_steps(process, run / "metrics.csv", at)
    process.kill()
    process.communicate(timeout=60)
    saved = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["step"]
    assert saved % 7 == 0 and 7 <= saved <= STEPS, f"killed after step {at}: latest.pt is a periodic checkpoint"
    resumed = subprocess.run([sys.executable, str(ROOT / "train.py"), str(config), "--resume"], capture_output=True,
                             text=True, env=ENV, cwd=ROOT, timeout=300)
    assert resumed.returncode == 0, f"killed after step {at}: {resumed.stderr}"
    _assert_same(_weights(run), uninterrupted)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_start_up_says_nothing_is_saved(tiny_dataset, tmp_path, sig):
    """While the dataset is still being generated, an interruption leaves no checkpoint and says so."""
    big = tmp_path / "big.yaml"
    big.write_text(yaml.safe_dump({"extends": str(tiny_dataset[0]), "dataset": "big", "splits": {"train": 500}}))
    config = _config(tiny_dataset, tmp_path, dataset={"config": str(big), "root": str(tmp_path / "data"),
                                                       "generate": True})
    process = _start(config)
    deadline = time.monotonic() + 120
    while not (tmp_path / "data" / "big" / "train").is_dir():  # generation has begun
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.02)
    process.send_signal(sig)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130 and "Traceback" not in stderr, stderr
    latest = tmp_path / "runs" / "run" / "checkpoints" / "latest.pt"
    found = re.search(r"interrupted; nothing was saved \((\S+) does not exist yet\)\. Start again with: (.+)$",
                      stderr.strip())
    assert found and Path(found.group(1)) == latest, stderr
    assert shlex.split(found.group(2))[1:] == [str(ROOT / "train.py"), str(config)], "the command that starts it"
    assert not latest.exists()
