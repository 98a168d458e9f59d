"""The ``bsms`` command: its subcommands are the entry points beside them, and it works from any
folder after a plain (not editable) ``pip install .``."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import tiny_run_config

from bsms import cli

ROOT = Path(__file__).resolve().parents[1]


def test_help_lists_every_subcommand(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in ("train", "generate", "evaluate", "infer", "convert", "export"):
        assert f"\n  {name} " in out, name


def test_no_subcommand_prints_the_usage_and_fails(capsys):
    assert cli.main([]) == 2
    assert capsys.readouterr().err.startswith("usage: bsms SUBCOMMAND")


def test_an_unknown_subcommand_is_one_clear_error(capsys):
    assert cli.main(["trian", "x.yaml"]) == 2
    assert capsys.readouterr().err == ("error: bsms has no subcommand 'trian'; choose one of train, generate, "
                                       "evaluate, infer, convert, export (bsms --help lists them)\n")


@pytest.mark.parametrize("name, words", [
    ("train", ["configs/quickstart.yaml"]), ("generate", []), ("evaluate", []), ("infer", []), ("convert", []),
    ("export", [])])
def test_each_subcommand_has_help_under_its_own_name(name, words, capsys):
    with pytest.raises(SystemExit) as done:
        cli.main([name, *words, "--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: bsms {name} ")


def test_bsms_train_is_python_train_py(tiny_dataset, tmp_path, capsys):
    """Same code: the same errors, and the resume hint names the command it was started with."""
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump(tiny_run_config(tiny_dataset, tmp_path, train={"steps": 0})))
    assert cli.main(["train", str(config)]) == 2
    err = capsys.readouterr().err
    assert err == "error: config key 'train.steps' must be >= 1, got 0\n"


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The package installed as a user would get it from ``pip install .`` (a wheel, not a link to
    this tree) into a folder of its own; the environment's other packages serve its dependencies."""
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--target", str(target), str(ROOT)], check=True, capture_output=True,
                   env={**os.environ, "TMPDIR": str(build)}, timeout=600)
    env = {**os.environ, "PYTHONPATH": str(target), "OMP_NUM_THREADS": "1"}
    return target, env


def _bsms(installed, cwd, *words, timeout=300):
    target, env = installed
    return subprocess.run([str(target / "bin" / "bsms"), *words], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.slow
def test_the_installed_command_works_from_any_folder(installed, tmp_path):
    target, env = installed
    where = subprocess.run([sys.executable, "-c", "import bsms, datagen; print(bsms.__file__, datagen.__file__)"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, check=True).stdout.split()
    assert all(Path(p).is_relative_to(target) for p in where), f"not the installed copy: {where}"
    for source in ("datagen/mpm/csrc/umls.c", "bsms/graph/csrc/graph.c"):  # compiled on first use
        assert (target / source).is_file(), f"{source} is not in the wheel"
    listing = _bsms(installed, tmp_path, "--help")
    assert listing.returncode == 0 and "  export " in listing.stdout
    for words in (["train", "configs/quickstart.yaml", "--help"], ["generate", "--help"], ["evaluate", "--help"],
                  ["infer", "--help"], ["convert", "--help"], ["export", "--help"]):
        result = _bsms(installed, tmp_path, *words)
        assert result.returncode == 0 and result.stdout.startswith(f"usage: bsms {words[0]} "), (words, result.stderr)


@pytest.mark.slow
def test_a_user_trains_from_a_config_of_their_own(installed, tiny_dataset, tmp_path):
    """No clone: a config file in the user's folder, its dataset config beside it."""
    dataset_config, data_root = tiny_dataset
    mine = tmp_path / "my_dataset.yaml"
    mine.write_text(dataset_config.read_text())
    run = tiny_run_config(tiny_dataset, "runs", name="mine", train={"steps": 4, "valid_every": 4,
                                                                  "checkpoint_every": 4},
                          evaluate={"enabled": False})
    run["dataset"]["config"] = "my_dataset.yaml"
    (tmp_path / "my_run.yaml").write_text(yaml.safe_dump(run))
    result = _bsms(installed, tmp_path, "train", "my_run.yaml", "--quiet")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1].startswith("trained 4 steps in ")
    assert (tmp_path / "runs" / "mine" / "checkpoints" / "latest.pt").is_file()
