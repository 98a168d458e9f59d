"""benchmarks/press_zero_shot.py: the shapes it meshes, what it hands bsms.infer, and its last line
(bsms.infer itself is tested in tests/test_infer.py; here it is replaced by a stand-in)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import press_zero_shot  # noqa: E402

from datagen.config import ConfigError  # noqa: E402
from datagen.scenes.base import vertex_volumes  # noqa: E402
from datagen.scenes.bodies import read_body  # noqa: E402


def test_scene_overrides_reach_infer_and_the_last_line_names_every_shape(monkeypatch, capsys):
    calls = []

    def fake_infer(run, files, **kwargs):  # one call per shape, each mesh alone, as a user runs it
        k = len(calls)
        calls.append(dict(run=run, files=files, **kwargs))
        (path,) = files
        assert 300 < read_body(path, 0).n_nodes < 700  # meshed at --size (4 mm): a few hundred nodes
        return {"nodes": [100 + k], "body_nodes": 400 + k, "rel_all": 0.001 * (k + 1), "rest_rel_all": 0.004,
                "vs_rest": 0.25 * (k + 1), "seconds_per_step": 0.01, "latency_ms": 20.0,
                "solver_seconds_per_step": 0.5 + k, "speedup": 50.0 + 100 * k, "solver_s": 20.0 + k, "call_s": 2.0}

    monkeypatch.setattr(press_zero_shot, "infer", fake_infer)
    assert press_zero_shot.main(["RUN", "--scene", "grid_ratio=1.5", "E=2e7", "--checkpoint", "latest"]) == 0
    assert len(calls) == 3
    for call in calls:
        assert call["run"] == "RUN" and call["overrides"] == {"grid_ratio": 1.5, "E": 2e7}
        assert call["which"] == "latest" and call["solver"] is True and "separately" not in call
    assert [Path(c["files"][0]).stem for c in calls] == ["star", "L_bracket", "notched_plate"]
    assert len({c["out"] for c in calls}) == 3, "one output folder per shape"
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[2].endswith("| 50x | 2 | 10x |"), "the whole call and the solver's time over it"
    assert lines[-1] == ("zero-shot: vs at rest star 0.25, L bracket 0.5, notched plate 0.75 (max 0.75), "
                         "speedup 50-250 x")


def test_a_scene_override_without_a_value_is_refused():
    with pytest.raises(ConfigError, match=r"--scene 'grid_ratio' must look like KEY=VALUE"):
        press_zero_shot.main(["RUN", "--scene", "grid_ratio"])


def test_the_wide_set_meshes_sixteen_bodies_with_their_holes_and_names_the_worst(monkeypatch, capsys):
    seen = {"files": [], "areas": []}

    def fake_infer(run, files, **kwargs):
        k = len(seen["files"])
        seen["files"] += files
        seen["areas"] += [float(vertex_volumes(read_body(path, 0)).sum()) for path in files]
        return {"nodes": [100], "body_nodes": 400, "rel_all": 0.001, "rest_rel_all": 0.004, "vs_rest": 0.1 + 0.05 * k,
                "seconds_per_step": 0.01, "latency_ms": 20.0, "solver_seconds_per_step": 0.5, "speedup": 40.0 + k,
                "solver_s": 20.0, "call_s": 2.0}

    monkeypatch.setattr(press_zero_shot, "infer", fake_infer)
    assert press_zero_shot.main(["RUN", "--shapes", "wide"]) == 0
    names = [Path(f).stem for f in seen["files"]]
    assert len(names) == 16 and names[:3] == ["star", "L_bracket", "notched_plate"]
    area = dict(zip(names, seen["areas"], strict=True))
    np.testing.assert_allclose(area["plate_with_hole"], 0.12 * 0.09 - 32 / 2 * 0.02**2 * np.sin(2 * np.pi / 32),
                               rtol=1e-9)
    np.testing.assert_allclose(area["ring"], 48 / 2 * 0.055**2 * np.sin(2 * np.pi / 48)
                               - 40 / 2 * 0.03**2 * np.sin(2 * np.pi / 40), rtol=1e-9)
    np.testing.assert_allclose(area["L_bracket"], 0.11 * 0.035 * 2 - 0.035**2, rtol=1e-9)
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == "zero-shot: vs at rest mean 0.475 on 16 shapes, above 0.5 on 7 (max 0.85, ring), speedup 40-55 x"
