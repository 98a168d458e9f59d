"""The ``bsms`` command: its subcommands are the entry points beside them, and it works from any
folder after a plain (not editable) ``pip install .``."""

import json
import os
import shutil
import subprocess
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from conftest import TINY_DATASET, tiny_run_config

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


# What a build of the package reads: pyproject.toml, the readme it names, the packages it finds.
BUILD_INPUTS = ("pyproject.toml", "README.md", "bsms", "datagen")
PACKAGES = ("bsms", "datagen")


@dataclass
class Installed:
    wheel: Path
    python: Path  # the fresh environment's interpreter
    site: Path  # its site-packages, where the wheel went
    env: dict

    def bsms(self, cwd, *words, cache=None, timeout=300):
        """The installed ``bsms`` command, run in ``cwd`` (compiled libraries in ``cache``, if given)."""
        env = self.env if cache is None else {**self.env, "BSMS_CACHE": str(cache)}
        return subprocess.run([str(self.python.parent / "bsms"), *words], cwd=cwd, env=env, capture_output=True,
                              text=True, timeout=timeout)


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The package as a user gets it from ``pip install .``: a wheel built from this tree (from a
    copy of what the build reads, so that nothing in the tree changes and no build/ folder of an
    earlier build adds its files), installed into a fresh virtual environment. The environment
    gets its dependencies from this one's site-packages, as plain path lines of a .pth file: the
    .pth files there (an editable install's finder of this tree) stay inactive."""
    source, wheels, fresh = (tmp_path_factory.mktemp(name) for name in ("source", "wheel", "fresh"))
    for name in BUILD_INPUTS:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(ROOT / name, source / name)
    run = dict(check=True, capture_output=True, text=True, timeout=600)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w",
                    str(wheels), str(source)], **run)
    wheel, = wheels.glob("bsms-*.whl")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(fresh)], **run)
    python = fresh / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
                    str(wheel)], **run)
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                               **run).stdout.strip())
    ours = [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages") and Path(p).is_dir()]
    (site / "dependencies.pth").write_text("".join(f"{p}\n" for p in ours))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(OMP_NUM_THREADS="1", BSMS_CACHE=str(tmp_path_factory.mktemp("cache")))
    return Installed(wheel, python, site, env)


@pytest.mark.slow
def test_the_wheel_holds_every_file_of_every_csrc_folder(installed):
    """The C sources and the headers they include are compiled on first use: all must ship."""
    with zipfile.ZipFile(installed.wheel) as wheel:
        shipped = set(wheel.namelist())
    needed = [file.relative_to(ROOT).as_posix() for package in PACKAGES for folder in (ROOT / package).rglob("csrc")
              for file in folder.rglob("*") if file.is_file() and "__pycache__" not in file.parts]
    assert len(needed) >= 6  # datagen/mpm/csrc (sources and headers), bsms/graph/csrc, bsms/models/csrc
    missing = [name for name in needed if name not in shipped]
    assert not missing, f"not in the wheel: {missing}"


@pytest.mark.slow
def test_the_installed_command_works_from_any_folder(installed, tmp_path):
    where = subprocess.run([str(installed.python), "-c", "import bsms, datagen; print(bsms.__file__, datagen.__file__)"],
                           cwd=tmp_path, env=installed.env, capture_output=True, text=True, check=True).stdout.split()
    assert all(Path(p).is_relative_to(installed.site) for p in where), f"not the installed copy: {where}"
    listing = installed.bsms(tmp_path, "--help")
    assert listing.returncode == 0 and "  export " in listing.stdout
    for words in (["train", "configs/quickstart.yaml", "--help"], ["generate", "--help"], ["evaluate", "--help"],
                  ["infer", "--help"], ["convert", "--help"], ["export", "--help"]):
        result = installed.bsms(tmp_path, *words)
        assert result.returncode == 0 and result.stdout.startswith(f"usage: bsms {words[0]} "), (words, result.stderr)


@pytest.mark.slow
def test_a_user_generates_trains_and_evaluates_in_a_folder_of_their_own(installed, tmp_path):
    """No clone: the user's dataset and run configs in their folder; an empty cache, so that the
    solver's, the graph's and the model's compiled code is built from the installed sources."""
    for name in ("glyphs.yaml", "glyphs_quick.yaml"):  # the example configs, copied by the user
        shutil.copy2(ROOT / "configs" / "datasets" / name, tmp_path / name)
    (tmp_path / "my_dataset.yaml").write_text(TINY_DATASET.format(base="glyphs_quick.yaml"))
    cache = tmp_path / "cache"
    made = installed.bsms(tmp_path, "generate", "my_dataset.yaml", "--quiet", cache=cache)
    assert made.returncode == 0, made.stderr
    assert made.stdout.startswith("4 trajectories generated, 0 already complete")
    run = tiny_run_config(("my_dataset.yaml", "data"), "runs", name="mine",
                          train={"steps": 4, "normalizer_steps": 2, "log_every": 2, "valid_every": 4,
                                 "checkpoint_every": 4},
                          evaluate={"trajectories": 1, "steps": 3, "solver": ["ground_truth"], "gifs": 0})
    (tmp_path / "my_run.yaml").write_text(yaml.safe_dump(run))
    trained = installed.bsms(tmp_path, "train", "my_run.yaml", "--quiet", cache=cache)
    assert trained.returncode == 0, trained.stderr
    lines = trained.stdout.splitlines()
    assert lines[-2].startswith("trained 4 steps in ")
    assert lines[-1].startswith("evaluated on 1 test trajectories: ") and lines[-1].endswith("report: runs/mine/report.md")
    metrics = json.loads((tmp_path / "runs" / "mine" / "evaluation" / "metrics.json").read_text())
    assert [row["kind"] for row in metrics["rows"]] == ["learned", "solver"]
    for result in (made, trained):  # every compiled path was built, none fell back to torch
        assert "could not build" not in result.stderr, result.stderr
    built = sorted(path.name.rsplit("-", 1)[0] for path in (cache / "native").glob("*.so"))
    assert built == ["graph", "messages", "substeps"]
