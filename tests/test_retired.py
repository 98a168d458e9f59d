"""Options retired from the code (docs/experiments.md): a config that asks for one gets one error
that names it; the configs that give what the code still does -- the published models', and every
saved run's, which list every key -- load, train on and resume as before."""

import re

import numpy as np
import pytest
import torch
import yaml
from conftest import tiny_run_config
from pretrained_checks import PRETRAINED

from bsms.config import ConfigError, build, load, to_dict
from bsms.data import saved_graph_options
from bsms.options import GraphOptions
from bsms.run import Config, load_config
from bsms.training.trainer import Trainer
from datagen.families import get_family

# (graph section, the error's exact message)
RETIRED = [
    ({"quasi_static": True, "displacement": True},
     "config key 'graph.displacement' is retired (with quasi_static, free nodes' displacement from rest as their "
     "velocity input: measured and not adopted, docs/experiments.md); got true: leave it out (this version always "
     "does what false did), or use the commit that has it: git checkout b28cc7d"),
    ({"from_rest": True, "drive": True},
     "config key 'graph.drive' is retired (with from_rest, every node's displacement from rest (the drive's travel) "
     "as an input: measured and not adopted, docs/experiments.md); got true: leave it out (this version always does "
     "what false did), or use the commit that has it: git checkout 066728a"),
    ({"from_rest": True, "penetration": True, "elastic": True, "elastic_residual": True},
     "config key 'graph.elastic_residual' is retired (with elastic and from_rest, the network learning the correction "
     "to the elastic answer: measured and not adopted, docs/experiments.md); got true: leave it out (this version "
     "always does what false did), or use the commit that has it: git checkout 3ed6533"),
    ({"from_rest": True, "penetration": True, "push": "collider"},
     "config key 'graph.push' is retired (how the penetration input puts a node back: leading, through the facets "
     "that face the obstacle's travel; collider, as the data's solver pushes: measured and not adopted, "
     "docs/experiments.md); got collider: leave it out (this version always does what nearest did), or use the "
     "commit that has it: git checkout fc6ef27"),
    ({"from_rest": True, "penetration": True, "elastic": True, "elastic_load": "force"},
     "config key 'graph.elastic_load' is retired (force: the elastic input loaded by forces along the pushes, its "
     "answer scaled to them: measured and not adopted, docs/experiments.md); got force: leave it out (this version "
     "always does what contact did), or use the commit that has it: git checkout 4a6f103"),
]


@pytest.mark.parametrize(("graph", "message"), RETIRED)
def test_a_retired_option_is_one_error_that_names_it(graph, message):
    with pytest.raises(ConfigError) as error:
        build(Config, {"name": "a", "graph": graph})
    assert str(error.value) == message


def test_each_retired_option_names_the_commit_that_has_it():
    assert all(re.fullmatch(r"[0-9a-f]{7,40}", entry.commit) for entry in GraphOptions.RETIRED.values())


def test_a_retired_option_at_what_the_code_does_is_dropped():
    graph = {"levels": 3, "push": "nearest", "elastic_load": "force",  # force did nothing without graph.elastic
             **{name: False for name in ("displacement", "drive", "elastic_residual")}}
    assert build(Config, {"name": "a", "graph": graph}).graph == GraphOptions(levels=3)
    graph = {**graph, "penetration": True, "elastic": True, "elastic_load": "contact"}
    assert build(Config, {"name": "a", "graph": graph}).graph == GraphOptions(levels=3, penetration=True, elastic=True)


def test_a_run_saved_by_this_version_loads_back():
    """Its saved config lists no retired key: graph.elastic's contact answer is no retired load."""
    config = build(Config, {"name": "a", "graph": {"from_rest": True, "penetration": True, "elastic": True}})
    saved = to_dict(config)
    assert "elastic_load" not in saved["graph"]
    assert build(GraphOptions, saved_graph_options(saved["graph"]), "graph") == config.graph


@pytest.mark.parametrize("name", ["press2d", "bracket2d", "cantilever2d"])
def test_the_published_models_configs_load(name):
    """Their config.yaml and their checkpoint's config list the retired keys at what the code still does."""
    config = build(Config, load(PRETRAINED / name / "config.yaml"))
    state = torch.load(PRETRAINED / name / "checkpoints" / "best.pt", map_location="cpu", weights_only=True)
    saved = build(Config, {**state["config"], "graph": saved_graph_options(state["config"].get("graph"))})
    assert saved.graph == config.graph and saved.model == config.model


def test_a_retired_dataset_range_is_one_error_that_names_it():
    press = get_family("press")
    with pytest.raises(ConfigError) as error:
        press.sample({"train_body_size": [0.0015, 0.005]}, np.random.default_rng(0), "train")
    assert str(error.value) == (
        "config key 'ranges.train_body_size' is retired (the train and valid bodies meshed at a spacing drawn for "
        "each: measured and not adopted, docs/experiments.md); got [0.0015, 0.005]: leave it out (this version "
        "always does what null did), or use the commit that has it: git checkout 0417dad")
    rng = np.random.default_rng(0)
    assert press.sample({"train_body_size": None}, rng, "train") == press.sample({}, np.random.default_rng(0), "train")


def test_a_saved_run_that_lists_the_retired_keys_resumes(tiny_dataset, tmp_path, one_thread):
    data = tiny_run_config(tiny_dataset, tmp_path, train={"steps": 4, "checkpoint_every": 2, "valid_every": 2})
    trainer = Trainer(load_config(data))
    trainer.fit(stop_at=2)
    saved = trainer.run_dir / "config.yaml"
    written = yaml.safe_load(saved.read_text())
    written["graph"].update(displacement=False, drive=False, elastic_residual=False, push="nearest",
                            elastic_load="force")  # as a run saved before the retirements lists them
    saved.write_text(yaml.safe_dump(written))
    assert Trainer(load_config(data), resume=True).step == 2
    written["graph"].update(displacement=True)
    saved.write_text(yaml.safe_dump(written))
    with pytest.raises(ConfigError, match=r"^config key 'graph.displacement' is retired \("):
        Trainer(load_config(data), resume=True)
