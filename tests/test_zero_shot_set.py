"""benchmarks/zero_shot_set.py: the shapes it places as bsms.infer does, the files it writes, resuming
and sharding, and its last line (the solver replaced by a stand-in; bsms.infer's solver runs are
tested in tests/test_infer.py)."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import zero_shot_set  # noqa: E402

from datagen.scenes.bodies import read_body  # noqa: E402


def test_it_places_each_shape_as_infer_does_writes_it_once_and_shards(monkeypatch, tmp_path, capsys):
    placed, saved = [], []

    def fake_simulate(config):
        placed.append(config)
        mesh = read_body(config["params"]["mesh"]["file"] if isinstance(config["params"]["mesh"], dict)
                         else config["params"]["mesh"], 0)
        frames = config["output"]["frames"]
        return SimpleNamespace(positions=np.zeros((frames + 1, mesh.n_nodes, 2)), mesh=mesh, wall_time=2.0 * frames), 1.0

    def fake_save(path, trajectory):
        saved.append(Path(path).name)
        Path(path).write_text("a trajectory")

    monkeypatch.setattr(zero_shot_set, "simulate_stable", fake_simulate)
    monkeypatch.setattr(zero_shot_set, "save", fake_save)
    out = tmp_path / "set"
    assert zero_shot_set.main(["--out", str(out), "--shard", "1/2"]) == 0
    assert saved == [zero_shot_set.file_name(k, name) for k, name in enumerate(zero_shot_set.wider_set()) if k % 2]
    assert saved[0] == "01_L_bracket.h5" and len(saved) == 8
    params = placed[0]["params"]  # the family's placement: a disk straight down over the body's centre
    assert params["indenter"] == "disk" and params["indenter_x"] == 0.0 and params["angle"] == 0.0
    assert params["refine"] is True and placed[0]["scene"] == "press"
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == f"zero-shot set: 8 shapes in {out / 'test'}, 8 solved here, 2 s of solver time per frame"
    assert zero_shot_set.main(["--out", str(out)]) == 0  # resumes: only the other eight are solved
    assert len(saved) == 16 and sorted(saved) == sorted(p.name for p in (out / "test").glob("*.h5"))
    assert capsys.readouterr().out.strip().splitlines()[-1] == \
        f"zero-shot set: 16 shapes in {out / 'test'}, 8 solved here, 2 s of solver time per frame"
