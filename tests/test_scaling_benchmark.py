"""benchmarks/scaling.py: its meshes, its fitted slopes, when it stops running a model, and its
last line (the timed workers are replaced by a stand-in: their measurements are model_costs.py's)."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import scaling  # noqa: E402

from datagen.scenes.base import vertex_volumes  # noqa: E402


def test_slope_is_the_exponent_of_a_power_law():
    points = [(n, 3e-6 * n**1.37) for n in (5e3, 1.5e4, 4.5e4, 1.5e5)]
    assert scaling.slope(points) == pytest.approx(1.37, abs=1e-12)
    assert scaling.slope(points[:1]) is None


def test_the_plate_is_meshed_to_the_node_count_asked(tmp_path):
    nodes, cells = scaling.cached_plate(tmp_path, 2000)
    assert abs(len(nodes) / 2000 - 1) < 0.1 and cells.shape[1] == 4
    np.testing.assert_allclose(np.ptp(nodes, axis=0), scaling.PLATE, rtol=1e-12)
    from datagen.mesh import Mesh

    assert vertex_volumes(Mesh(nodes, cells)).sum() == pytest.approx(math.prod(scaling.PLATE), rel=1e-12)
    again, _ = scaling.cached_plate(tmp_path, 2000)
    assert np.array_equal(again, nodes), "cached"


def test_a_slow_model_is_not_run_at_larger_sizes_and_the_last_line(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(scaling, "cached_plate", lambda folder, n: (np.zeros((n, 3)), np.zeros((1, 4), int)))
    asked = []

    def fake(spec):
        asked.append((spec["kind"], spec.get("model"), spec["size"], spec.get("phase")))
        n = spec["size"]
        if spec["kind"] == "solver":
            return {"substep_s": 1e-6 * n, "substeps": round(100 * n ** (1 / 3)), "frame_s": 1e-4 * n ** (4 / 3),
                    "nodes": float(n)}
        scale, exponent = {"bsms_gnn": (1e-3, 1.0), "meshgraphnets": (1e-3, 1.1), "ms_gnn_grid": (5e-5, 1.2)}[
            spec["model"]]
        if spec["model"] == "ms_gnn_grid" and n > 20000:
            return {"oom": True}
        common = {"nodes": float(n), "levels": 5}
        if spec["phase"] == "memory":
            return {**common, "train_peak_bytes": 1000 * n}
        if spec["phase"] == "infer":
            return {**common, "infer_s": 0.3 * scale * n**exponent}
        return {**common, "train_s": scale * n**exponent, "infer_s": 0.3 * scale * n**exponent}

    monkeypatch.setattr(scaling, "run_worker", fake)
    sizes = ["5000", "15000", "45000", "150000"]
    assert scaling.main(["--sizes", *sizes, "--max-step", "30", "--max-infer", "30",
                         "--out", str(tmp_path / "s.json")]) == 0
    phases = {(m, n): phase for kind, m, n, phase in asked if kind == "model"}
    # BSMS-GNN trains at 15k (1e-3 n: 15 s, as slope 1 from 5k predicts), not at 45k (45 s predicted >
    # 30 s): inference alone (13.5 s); at 150k inference would take 45 s > 30 s: not run
    assert phases[("bsms_gnn", 15000)] == "memory" and phases[("bsms_gnn", 45000)] == "infer"
    assert ("bsms_gnn", 150000) not in phases
    # MeshGraphNets: 12 s at 5k predicts 35 s at 15k: inference alone (12 s), then 39 s predicted at 45k
    assert phases[("meshgraphnets", 5000)] == "memory" and phases[("meshgraphnets", 15000)] == "infer"
    assert ("meshgraphnets", 45000) not in phases
    # MS-GNN-Grid out of memory training at 45k: inference alone at 150k
    assert phases[("ms_gnn_grid", 45000)] == "time" and phases[("ms_gnn_grid", 150000)] == "infer"
    assert sorted(n for kind, _, n, _ in asked if kind == "solver") == [5000, 15000, 45000, 150000]
    calls = len(asked)
    assert scaling.main(["--sizes", *sizes, "--max-step", "30", "--max-infer", "30", "--resume",
                         "--out", str(tmp_path / "s.json")]) == 0
    assert len(asked) == calls, "--resume keeps every size measured with the same settings"
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1] == ("scaling: BSMS-GNN slope 1.00, MeshGraphNets slope 1.10, MS-GNN-Grid slope 1.20, "
                         "solver slope 1.33, largest 45000 nodes")
    assert any("| OOM / OOM, -" in line for line in lines)


def test_lean_blocks_reach_the_workers_and_resume_only_keeps_the_same_settings(monkeypatch, tmp_path, capsys):
    specs = []

    def fake(spec):
        specs.append(spec)
        if spec["kind"] == "solver":
            return {"substep_s": 1e-3, "substeps": 100, "frame_s": 0.1, "nodes": float(spec["size"])}
        return {"nodes": float(spec["size"]), "levels": 4, "train_s": 1.0, "infer_s": 0.5, "train_peak_bytes": 10}

    monkeypatch.setattr(scaling, "run_worker", fake)
    out = str(tmp_path / "lean.json")
    assert scaling.main(["--sizes", "5000", "--latent", "64", "--hidden-layers", "1", "--no-layer-norm", "--out", out]) == 0
    models = [s for s in specs if s["kind"] == "model"]
    assert models and all(s["latent"] == 64 and s["hidden_layers"] == 1 and s["layer_norm"] is False for s in models)
    count = len(specs)
    assert scaling.main(["--sizes", "5000", "--latent", "64", "--resume", "--out", out]) == 0
    assert len(specs) > count, "two hidden layers with LayerNorm is another measurement"
