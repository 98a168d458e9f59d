"""bsms.config: typed configs with errors that name the dotted key."""

from dataclasses import dataclass, field
from typing import Literal

import pytest

from bsms.config import ConfigError, apply_overrides, build, load, to_dict


@dataclass
class Optim:
    lr: float = 1e-3
    warmup: int = 100
    schedule: Literal["cosine", "constant"] = "cosine"

    def validate(self, prefix: str) -> None:
        if self.lr <= 0:
            raise ConfigError(f"config key '{prefix}.lr' must be positive, got {self.lr}")


@dataclass
class Run:
    name: str
    optim: Optim = field(default_factory=Optim)
    levels: int | Literal["auto"] = "auto"
    devices: list[str] = field(default_factory=lambda: ["cpu"])
    seed: int | None = None


def test_defaults_and_coercion():
    run = build(Run, {"name": "a", "optim": {"lr": 1}, "levels": 4})
    assert run.optim.lr == 1.0 and isinstance(run.optim.lr, float)
    assert run.optim.warmup == 100 and run.levels == 4 and run.devices == ["cpu"] and run.seed is None
    assert to_dict(run) == {"name": "a", "optim": {"lr": 1.0, "warmup": 100, "schedule": "cosine"},
                            "levels": 4, "devices": ["cpu"], "seed": None}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"name": "a", "optim": {"lr": 1e-3, "lrr": 2}}, "unknown config key 'optim.lrr'; 'optim' accepts: lr, schedule, warmup"),
        ({"name": "a", "epochs": 3}, "unknown config key 'epochs'; the config accepts: devices, levels, name, optim, seed"),
        ({}, "config key 'name' is required (a string)"),
        ({"name": "a", "optim": {"warmup": 1.5}}, "config key 'optim.warmup' must be an integer, got 1.5"),
        ({"name": "a", "optim": {"warmup": True}}, "config key 'optim.warmup' must be an integer, got True"),
        ({"name": "a", "optim": {"schedule": "step"}}, "config key 'optim.schedule' must be one of 'cosine', 'constant', got 'step'"),
        ({"name": "a", "levels": "many"}, "config key 'levels' must be an integer or one of 'auto', got 'many'"),
        ({"name": "a", "devices": ["cpu", 3]}, "config key 'devices[1]' must be a string, got 3"),
        ({"name": "a", "optim": {"lr": -1.0}}, "config key 'optim.lr' must be positive, got -1.0"),
        ({"name": "a", "optim": 5}, "'optim' must be a mapping of keys to values, got 5"),
        ({"name": "a", "optim": {"lr": float("nan")}}, "config key 'optim.lr' must be a number, got nan"),
    ],
)
def test_errors_name_the_key(data, message):
    with pytest.raises(ConfigError) as info:
        build(Run, data)
    assert str(info.value) == message


def test_overrides(tmp_path):
    path = tmp_path / "run.yaml"
    path.write_text("name: base\noptim:\n  lr: 0.001\n")
    data = apply_overrides(load(path), ["optim.lr=3e-4", "optim.schedule=constant", "seed=7", "devices=[cpu, cuda]"])
    run = build(Run, data)
    assert run.optim.lr == 3e-4 and run.optim.schedule == "constant" and run.seed == 7
    assert run.devices == ["cpu", "cuda"]
    assert load(path)["optim"]["lr"] == 0.001  # the file is untouched
    with pytest.raises(ConfigError, match="override 'optim.lr' must look like section.key=value"):
        apply_overrides({}, ["optim.lr"])
    with pytest.raises(ConfigError, match="'name' is not a section"):
        apply_overrides({"name": "x"}, ["name.first=y"])


def test_load_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load(tmp_path / "missing.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="must hold a mapping"):
        load(tmp_path / "list.yaml")
    (tmp_path / "bad.yaml").write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="is not valid YAML"):
        load(tmp_path / "bad.yaml")
    (tmp_path / "evil.yaml").write_text("a: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(ConfigError, match="is not valid YAML"):
        load(tmp_path / "evil.yaml")
