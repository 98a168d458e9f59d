"""Hostile inputs through the command lines a user types (``train.py``, ``python -m datagen``,
``python -m bsms.evaluate``, ``python -m bsms.infer``): each is refused before any work with
exit status 2 and one ``error:`` line naming the thing and the fix, never a traceback.

The ``main`` functions run in-process (the same argument parsing and error handling as the
commands); one case per command also runs as a real subprocess.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml
from conftest import tiny_run_config

from bsms import evaluate as evaluate_cli
from bsms import infer as infer_cli
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer
from datagen import generate as datagen_cli
from datagen import shapes
from datagen.mesh import Mesh

ROOT = Path(__file__).resolve().parents[1]
NO_CUDA = not torch.cuda.is_available()
_spec = importlib.util.spec_from_file_location("train_script", ROOT / "train.py")
train_cli = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(train_cli)


def _run(main, argv, capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, f"one error line, nothing else: {err!r}"
    return code, err


@pytest.fixture(scope="module")
def run(tiny_dataset, tmp_path_factory):
    """A tiny trained run (4 steps) and its config file."""
    runs = tmp_path_factory.mktemp("runs")
    data = tiny_run_config(tiny_dataset, runs, name="tiny", train={"steps": 4, "valid_every": 4,
                                                                   "checkpoint_every": 4})
    Trainer(load_config(data), dataset_folder=prepare_dataset(load_config(data), progress=False)).fit()
    config = runs / "tiny.yaml"
    config.write_text(yaml.safe_dump({**data, "name": "fresh"}))
    return runs / "tiny", config


@pytest.fixture(scope="module")
def meshes(tmp_path_factory) -> dict[str, Path]:
    """Bad mesh files a user might export: seams not merged, a copy pasted over, a repeated cell."""
    folder = tmp_path_factory.mktemp("meshes")
    disk = shapes.disk(0.1, size=0.03)
    left, right = shapes.rectangle(0.1, 0.1, 0.03), shapes.rectangle(0.1, 0.1, 0.03, origin=(0.1, 0.0))
    import meshio

    def write(name, nodes, cells):
        path = folder / name
        meshio.write(path, meshio.Mesh(np.c_[nodes, np.zeros(len(nodes))], [("triangle", cells)]))
        return path

    return {
        "good": write("good.vtu", disk.nodes, disk.cells),
        "seam": write("seam.vtu", np.vstack([left.nodes, right.nodes]),
                      np.vstack([left.cells, right.cells + left.n_nodes])),
        "overlap": write("overlap.vtu", np.vstack([disk.nodes, disk.nodes + 0.02]),
                         np.vstack([disk.cells, disk.cells + disk.n_nodes])),
        "repeated": write("repeated.vtu", disk.nodes, np.vstack([disk.cells, disk.cells[:1]])),
    }


# ----------------------------------------------------------------------------- train.py
@pytest.mark.parametrize(("overrides", "words"), [
    (["runs={file}"], r"the run folder \(config keys 'runs' and 'name'\) .*: .* is a file, not a folder"),
    (["runs=/sys"], r"the run folder .* /sys/fresh: cannot write there \(.*\); give a folder you can write to"),
    (["train.device=cuda"] if NO_CUDA else ["train.device=tpu"], r"config key 'train.device'"),
    (["train.stpes=3"], r"unknown config key 'train.stpes'; 'train' accepts: "),
    (["optim.lr"], r"override 'optim.lr' must look like section.key=value"),
    (["dataset.root={missing}", "dataset.generate=false"],
     r"dataset tiny_glyphs lacks 4 trajectory files under .*missing; generate them with python -m datagen .* --out "),
])
def test_train_refuses_before_training(run, tmp_path, capsys, overrides, words):
    (tmp_path / "file").write_text("")
    argv = [run[1], *[o.format(file=tmp_path / "file", missing=tmp_path / "missing") for o in overrides]]
    code, err = _run(train_cli.main, argv, capsys)
    assert code == 2 and err.startswith("error: "), err
    assert __import__("re").search(words, err), err


def test_train_config_file_errors(tmp_path, capsys):
    code, err = _run(train_cli.main, [tmp_path / "nothing.yaml"], capsys)
    assert code == 2 and "nothing.yaml does not exist" in err
    (tmp_path / "list.yaml").write_text("- a\n- b\n")
    code, err = _run(train_cli.main, [tmp_path / "list.yaml"], capsys)
    assert code == 2 and "list.yaml must hold a mapping" in err
    code, err = _run(train_cli.main, [tmp_path / "list.yaml", "--resume"], capsys)
    assert code == 2


def test_train_resume_without_a_checkpoint(run, capsys):
    code, err = _run(train_cli.main, [run[1], "name=never_run", "--resume"], capsys)
    assert code == 2 and "cannot resume" in err and "start the run without --resume" in err


def test_a_diverging_run_stops_with_the_last_finite_weights(run, capsys):
    code, err = _run(train_cli.main, [run[1], "name=diverged", "optim.lr=1e30", "train.steps=30"], capsys)
    assert code == 3, err
    found = __import__("re").search(r"training diverged at step (\d+): .* went non-finite .*optim.lr is 1e\+30.*"
                                    r"latest.pt (holds the last finite weights \(step (\d+)\)|keeps its last)", err)
    assert found, err
    state = torch.load(run[0].parent / "diverged" / "checkpoints" / "latest.pt", weights_only=True)
    assert all(bool(torch.isfinite(v).all()) for v in state["model"].values()), "latest.pt holds finite weights"
    assert state["step"] < int(found.group(1))


def _corrupt_copy(dataset_root: Path, tmp_path: Path, edit) -> Path:
    copy = tmp_path / "data"
    shutil.copytree(dataset_root, copy)
    first = sorted((copy / "tiny_glyphs" / "train").glob("*.h5"))[0]
    with h5py.File(first, "r+") as f:
        edit(f)
    return copy


def _set(f, name, value):
    del f[name]
    f.create_dataset(name, data=value)


@pytest.mark.parametrize(("edit", "words"), [
    (lambda f: _set(f, "frames/positions", np.full(f["frames/positions"].shape, np.nan)),
     r"00000\.h5: 'frames/positions' holds NaN or inf from frame 0 on"),
    (lambda f: _set(f, "mesh/node_type", np.full(f["mesh/node_type"].shape, 9, np.int8)),
     r"00000\.h5: 'mesh/node_type' holds unknown codes \[9\]"),
    (lambda f: _set(f, "frames/times", -f["frames/times"][()]),
     r"00000\.h5: 'frames/times' must increase strictly"),
])
def test_bad_training_data_names_the_file(run, tiny_dataset, tmp_path, capsys, edit, words):
    root = _corrupt_copy(tiny_dataset[1], tmp_path, edit)
    code, err = _run(train_cli.main, [run[1], f"dataset.root={root}", "name=bad_data"], capsys)
    assert code == 2 and __import__("re").search(words, err), err


# ----------------------------------------------------------------------------- python -m datagen
@pytest.mark.parametrize(("over", "out", "words"), [
    ({}, "{file}/data", r"--out .*file/data: .*file is a file, not a folder; give a folder path"),
    ({}, "/sys", r"--out /sys: cannot write there"),
    ({"solver": {"dt": 1e-9}}, "{tmp}", r"solver.dt 1e-09 s makes [\d,]+ solver steps per .* hours per frame"),
    ({"ranges": {"count": [0, 0]}}, "{tmp}", r"ranges.count must be at least 1, got \[0, 0\]"),
    ({"splits": {"train": -2}}, "{tmp}", r"dataset config key 'splits.train' must be a count >= 0"),
])
def test_datagen_refuses_before_generating(tiny_dataset, tmp_path, capsys, over, out, words):
    (tmp_path / "file").write_text("")
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump({"extends": str(tiny_dataset[0]), **over}))
    code, err = _run(datagen_cli.main, [config, "--out", out.format(file=tmp_path / "file", tmp=tmp_path / "d"),
                                        "--quiet"], capsys)
    assert code == 2 and __import__("re").search(words, err), err
    assert not list(tmp_path.glob("d/*/*/*.h5")), "nothing was generated"


# ----------------------------------------------------------------------------- python -m bsms.evaluate
@pytest.mark.parametrize(("argv", "words"), [
    (["--device", "cuda"] if NO_CUDA else ["--device", "tpu"], r"--device "),
    (["--device", "gpu"], r"--device must be auto, cpu, cuda or cuda:N, got 'gpu'"),
    (["--steps", "0"], r"evaluate.steps"),
])
def test_evaluate_refuses_before_work(run, capsys, argv, words):
    code, err = _run(evaluate_cli.main, [run[0], *argv, "--quiet"], capsys)
    assert code == 2 and __import__("re").search(words, err), err


def test_evaluate_with_a_moved_dataset(tiny_dataset, tmp_path, capsys):
    shutil.copytree(tiny_dataset[1], tmp_path / "data")
    data = tiny_run_config((tiny_dataset[0], tmp_path / "data"), tmp_path / "runs", name="moved",
                           train={"steps": 2, "valid_every": 2, "checkpoint_every": 2})
    Trainer(load_config(data), dataset_folder=prepare_dataset(load_config(data), progress=False)).fit()
    shutil.rmtree(tmp_path / "data")
    code, err = _run(evaluate_cli.main, [tmp_path / "runs" / "moved", "--quiet", "--no-solver"], capsys)
    assert code == 2 and "data/tiny_glyphs does not exist (moved or deleted?); put the dataset back" in err, err


# ----------------------------------------------------------------------------- python -m bsms.infer
@pytest.mark.parametrize(("mesh", "extra", "words"), [
    ("good", ["--device", "cuda"] if NO_CUDA else ["--device", "tpu"], r"--device "),
    ("good", ["--out", "{file}/out"], r"--out .*file/out: .*file is a file, not a folder"),
    ("good", ["--out", "/sys"], r"--out /sys: cannot write there"),
    ("seam", [], r"seam\.vtu: coincident nodes: \d+ pairs of nodes lie at the same point"),
    ("overlap", [], r"piece 1 of body 0 .*overlap\.vtu.* overlaps piece 0 .*remove the copy"),
    ("repeated", [], r"repeated\.vtu: duplicate cells: 1 cells repeat another"),
])
def test_infer_refuses_before_the_rollout(run, meshes, tmp_path, capsys, mesh, extra, words):
    (tmp_path / "file").write_text("")
    extra = [e.format(file=tmp_path / "file") for e in extra]
    code, err = _run(infer_cli.main, [run[0], "--mesh", meshes[mesh], *extra, "--quiet"], capsys)
    assert code == 2 and __import__("re").search(words, err), err
    assert not (run[0] / "infer").exists() or not any((run[0] / "infer").rglob("summary.json"))


def test_a_real_subprocess_gives_one_error_line(run, meshes):
    result = subprocess.run([sys.executable, "-m", "bsms.infer", str(run[0]), "--mesh", str(meshes["seam"]),
                             "--quiet"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "coincident nodes" in result.stderr
    assert Mesh.read(meshes["seam"], merge_coincident=True).n_components == 1
