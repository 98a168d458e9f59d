"""The documentation stays true to the code: the API reference names every public name and each
has a docstring, the config table lists every key with its default, every benchmark script and
every page is reachable, the README stays a landing page with the two commands CI runs, and the
site builds with the README's command without a warning."""

import dataclasses
import importlib
import importlib.util
import inspect
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from bsms.run import Config, load_config
from datagen.dataset_config import load_dataset_config

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# The public API the reference must show (issue: simulate, Mesh, shapes, the scene and family
# registries, Trajectory and the file format, bistride_levels and the graph types,
# LearnedSimulator and the cores, rollout(s), evaluate, infer, the config dataclasses).
API = [
    "datagen.simulate", "datagen.mesh.Mesh", "datagen.mesh.MeshError", "datagen.shapes", "datagen.surface",
    "datagen.scenes.SCENES", "datagen.scenes.get_scene", "datagen.families.FAMILIES", "datagen.families.get_family", "datagen.families.place",
    "datagen.trajectory.Trajectory", "datagen.trajectory.NodeType", "datagen.dataset",
    "bsms.graph.bistride_levels", "bsms.graph.Hierarchy", "bsms.graph.BistrideLevel", "bsms.graph.Transition",
    "bsms.data.Scenario", "bsms.data.FrameDataset", "bsms.level_graph.LevelGraph", "bsms.level_graph.FrameArrays",
    "bsms.models.simulator.LearnedSimulator", "bsms.models.BSMSGNN", "bsms.models.MeshGraphNets",
    "bsms.models.MSGNNGrid", "bsms.models.GraphUNets",
    "bsms.rollouts.rollout.rollout", "bsms.rollouts.rollout.rollouts", "bsms.rollouts.rollout.Rollout", "bsms.rollouts.motion.skill",
    "bsms.evaluate.evaluate", "bsms.infer.infer", "bsms.infer.pretrained.export", "bsms.infer.pretrained.export_ensemble",
    "bsms.models.ensemble.Ensemble", "bsms.ensemble.spread",
    "bsms.run.load_config", "bsms.run.Config", "bsms.run.DatasetConfig", "bsms.options.GraphOptions",
    "bsms.options.NoiseOptions", "bsms.run.ModelConfig", "bsms.run.OptimConfig", "bsms.run.TrainConfig",
    "bsms.run.EvaluateConfig",
]
# registries are dicts: their docs are the module's (a dict has no docstring of its own)
REGISTRIES = {"datagen.scenes.SCENES": "datagen.scenes", "datagen.families.FAMILIES": "datagen.families"}


def resolve(dotted: str):
    try:
        return importlib.import_module(dotted)
    except ModuleNotFoundError:
        module, _, name = dotted.rpartition(".")
        return getattr(importlib.import_module(module), name)


def _doc(dotted: str) -> str:
    obj = resolve(REGISTRIES.get(dotted, dotted))
    return inspect.getdoc(obj) or ""


@pytest.mark.parametrize("name", API)
def test_every_public_name_has_a_docstring(name):
    doc = _doc(name)
    assert len(doc.split()) >= 5, f"{name} has no docstring worth the name: {doc!r}"


def test_the_api_page_shows_exactly_the_public_names():
    shown = re.findall(r"^::: (\S+)$", (DOCS / "api.md").read_text(), flags=re.M)
    assert sorted(shown) == sorted(API)
    assert len(shown) == len(set(shown))


def _nav_pages(nav) -> list[str]:
    pages = []
    for entry in nav:
        for value in entry.values():
            pages += _nav_pages(value) if isinstance(value, list) else [value]
    return pages


def test_every_page_is_in_the_site_and_every_nav_entry_exists():
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    pages = _nav_pages(config["nav"])
    assert sorted(pages) == sorted(p.name for p in DOCS.glob("*.md"))


def _config_keys(cls, prefix=""):
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if dataclasses.is_dataclass(default):
            yield from _config_keys(type(default), f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", default


def test_the_training_page_lists_every_config_key_with_its_default():
    rows = re.findall(r"^\| `([a-z_.]+)` \| `(.*?)` \| (.+) \|$", (DOCS / "training.md").read_text(), flags=re.M)
    documented = {key: json.loads(default) for key, default, _ in rows}
    expected = dict(_config_keys(Config))
    assert list(documented) == list(expected), "keys missing, extra or out of order"
    assert documented == expected, "a default differs from the code"
    assert all(len(meaning.split()) >= 3 for _, _, meaning in rows)


def test_the_benchmarks_page_lists_every_script():
    page = (DOCS / "benchmarks.md").read_text()
    missing = [p.name for p in sorted((ROOT / "benchmarks").glob("*.py")) if f"`{p.name}" not in page]
    assert not missing


def test_the_getting_started_configs_load(tmp_path):
    blocks = re.findall(r"```yaml\n# ([\w.]+?):?(?: [^\n]*)?\n(.*?)```", (DOCS / "getting_started.md").read_text(), flags=re.S)
    assert [name for name, _ in blocks] == ["my_dataset.yaml", "my_run.yaml"]
    for name, text in blocks:
        (tmp_path / name).write_text(text)
    dataset = load_dataset_config(tmp_path / "my_dataset.yaml")
    run = load_config(tmp_path / "my_run.yaml")
    assert dataset["family"] == "glyphs" and run.train.tensorboard and run.dataset.config == "my_dataset.yaml"


def test_the_readme_is_a_landing_page_with_the_two_commands():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && pip install -e . && " \
           "python train.py configs/quickstart.yaml" in readme
    assert "pip install torch==2.13.0 && pip install -e \".[test]\" && python -m pytest -q" in readme
    assert "python -m pytest -q" in ci
    for link in re.findall(r"\]\((docs/[^)#]+)", readme):
        assert (ROOT / link).is_file(), f"README links to {link}, which does not exist"


def _readme_docs_command() -> list[str]:
    """The README's command that builds the documentation site (it names it more than once: the same)."""
    commands = set(re.findall(r"mkdocs build(?: --?[\w-]+)*", (ROOT / "README.md").read_text()))
    assert len(commands) == 1, f"the README names no docs build command, or several: {sorted(commands)}"
    command = commands.pop().split()
    assert "--strict" in command, "the README's docs build must be strict (a warning fails it)"
    return command


def test_the_docs_build_as_the_readme_says_without_a_warning(tmp_path):
    """The README's docs command as written, in a copy of what it reads (mkdocs.yml, the pages and
    the packages the API reference is generated from), so that no site/ folder lands in the tree:
    it exits 0 and prints no warning (strict mode aborts on one; none may be printed either)."""
    if importlib.util.find_spec("mkdocs") is None:
        pytest.fail('mkdocs is not installed, so the documentation cannot be built: install the docs extra '
                    '(pip install -e ".[docs]"; the test extra includes it), as CI does')
    command = _readme_docs_command()
    for name in ["mkdocs.yml", "docs", *(p.parent.name for p in sorted(ROOT.glob("*/__init__.py")))]:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(ROOT / name, tmp_path / name)
    beside = Path(sys.executable).with_name(command[0])  # this environment's mkdocs, activated or not
    executable = str(beside) if beside.is_file() else shutil.which(command[0])
    assert executable, f"no {command[0]} command beside {sys.executable} or on PATH"
    # NO_MKDOCS_2_WARNING: the theme's banner about its own end of life (as CI sets it), not about the docs
    result = subprocess.run([executable, *command[1:]], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                            env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert "WARNING" not in output, output
    assert (tmp_path / "site" / "index.html").is_file() and (tmp_path / "site" / "api" / "index.html").is_file()
