"""python -m bsms.infer: zero-shot rollouts on mesh files (2D and 3D), larger meshes, errors."""

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import meshio
import numpy as np
import pytest
from conftest import tiny_run_config
from PIL import Image

from bsms.infer import main
from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer
from datagen import shapes
from datagen.compiled import cpu_summary
from datagen.simulation import SOLVER_DEFAULTS

ROOT = Path(__file__).resolve().parents[1]


def train_tiny(dataset, runs, name):
    config = load_config(tiny_run_config(dataset, runs, name=name, train={"steps": 4, "valid_every": 4,
                                                                          "checkpoint_every": 4}))
    trainer = Trainer(config, dataset_folder=prepare_dataset(config, progress=False))
    trainer.fit()
    return runs / name, trainer


@pytest.fixture(scope="module")
def run_2d(tiny_dataset, tmp_path_factory):
    return train_tiny(tiny_dataset, tmp_path_factory.mktemp("runs"), "glyphs2d")


@pytest.fixture(scope="module")
def run_3d(tiny_dataset_3d, tmp_path_factory):
    return train_tiny(tiny_dataset_3d, tmp_path_factory.mktemp("runs"), "balls3d")


def write(mesh, path):
    kind = {2: "triangle", 3: "tetra"}[mesh.dim]
    meshio.write(path, meshio.Mesh(np.pad(mesh.nodes, ((0, 0), (0, 3 - mesh.dim))), [(kind, mesh.cells)]))
    return path


def check_outputs(out: Path, summary: dict, steps: int) -> None:
    """prediction.xdmf holds every frame and the error against the solver behind summary.json's
    RMSE (zero at frame 0: both start from the same state); the GIF shows every frame."""
    with meshio.xdmf.TimeSeriesReader(str(out / "prediction.xdmf")) as reader:
        reader.read_points_cells()
        assert reader.num_steps == steps + 1
        errors = np.stack([reader.read_data(k)[1]["error"] for k in range(steps + 1)])
    assert (errors[0] == 0).all()
    curve = np.sqrt(np.mean(errors[1:] ** 2, axis=1))
    assert summary["rmse_1"] == pytest.approx(curve[0], rel=2e-15)
    assert summary["rmse_all"] == pytest.approx(np.sqrt(np.mean(curve**2)), rel=2e-15)
    check_speed(summary, steps)
    with Image.open(out / "prediction.gif") as gif:
        assert gif.n_frames == steps + 1
    predicted = read_positions(out / "prediction.xdmf")
    solver = read_positions(out / "solver.xdmf")  # the solver's body nodes at the same frames
    assert solver.shape == predicted.shape and (solver[0] == predicted[0]).all()
    np.testing.assert_allclose(np.linalg.norm(predicted - solver, axis=-1), errors, rtol=1e-12, atol=1e-15)
    size = np.linalg.norm(np.ptp(solver[0], axis=0))
    rest = np.sqrt(np.mean(np.sum((solver[1:] - solver[0]) ** 2, axis=-1))) / size  # predicting no motion
    assert summary["rest_rel_all"] == pytest.approx(rest, rel=1e-10)
    assert summary["vs_rest"] == pytest.approx(summary["rel_all"] / rest, rel=1e-10)
    assert summary["rigid_rel_all"] >= 0 and summary["deform_rel_all"] >= 0
    assert summary["rest_rigid_rel_all"] <= rest * (1 + 1e-12) and summary["rest_deform_rel_all"] <= rest * (1 + 1e-12)


def check_speed(summary: dict, steps: int) -> None:
    """The speed-ups are what they claim: end to end (the solver from the scene to the last frame
    over the learned side's setup and rollout), throughput (per batched frame), never the other
    way round; the latency is a frame's."""
    for key in ("speedup", "speedup_throughput", "latency_ms", "setup_s", "learned_s", "solver_s", "solver_preroll_s"):
        assert key in summary and math.isfinite(summary[key]) and summary[key] >= 0, key
    assert summary["setup_s"] > 0 and summary["learned_s"] > 0 and summary["solver_s"] > 0
    assert summary["speedup"] == pytest.approx(summary["solver_s"] / (summary["setup_s"] + summary["learned_s"]),
                                               rel=1e-12)
    assert summary["solver_seconds_per_step"] == pytest.approx(summary["solver_s"] / steps, rel=1e-12)
    assert summary["speedup_throughput"] == pytest.approx(
        summary["solver_seconds_per_step"] / summary["seconds_per_step"], rel=1e-12)
    assert summary["speedup"] <= summary["speedup_throughput"], "the setup and every call are in the end-to-end time"
    assert summary["learned_s"] >= steps * summary["seconds_per_step"] * (1 - 1e-9)
    assert summary["cpu"] == cpu_summary()
    assert summary["model_load_s"] > 0 and summary["outputs_s"] > 0, "reported apart, not in the end-to-end time"
    parts = summary["model_load_s"] + summary["setup_s"] + summary["learned_s"] + summary["outputs_s"]
    assert summary["call_s"] >= parts, "the whole call holds every part timed apart"


def read_positions(path: Path) -> np.ndarray:
    """(T, N, d) node positions of an XDMF time series written by datagen.export.write_series."""
    with meshio.xdmf.TimeSeriesReader(str(path)) as reader:
        points, _ = reader.read_points_cells()
        frames = [reader.read_data(k)[1]["position"] for k in range(reader.num_steps)]
    return np.stack(frames)[..., : points.shape[1] if points.shape[1] < 3 else frames[0].shape[-1]]


def test_2d_mesh_file_with_the_solver(run_2d, tmp_path, capsys):
    run, _ = run_2d
    mesh_file = write(shapes.annulus(0.5, 1.0, 0.25), tmp_path / "ring.vtu")
    code = main([str(run), "--mesh", str(mesh_file), "--steps", "3", "--solver", "--out", str(tmp_path / "out"),
                 "--quiet"])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["steps"] == 3 and summary["finite"] and summary["scene"] == "bodies"
    check_outputs(tmp_path / "out", summary, 3)
    printed = capsys.readouterr().out
    assert f"against the solver: RMSE {summary['rmse_all']:.3g} m" in printed
    assert f"{summary['vs_rest']:.3g} of predicting no motion" in printed and "solver.xdmf" in printed


def test_the_solver_is_retried_at_smaller_cfl_numbers_where_it_goes_non_finite(run_2d, tmp_path, monkeypatch, capsys):
    """Where the solver goes non-finite on a placement (a body meshed about as coarse as the
    background mesh can), ``--solver`` runs it again at half and a quarter of the data's CFL
    number and says which one ran; where all fail, one error names them and the fix."""
    import datagen.generate as gen
    from datagen.mpm.errors import SimulationError

    run, _ = run_2d
    mesh_file = write(shapes.annulus(0.5, 1.0, 0.25), tmp_path / "ring.vtu")
    real, asked = gen.simulate, []

    def failing_above(limit):
        def fake(config):
            asked.append(config["solver"]["cfl"])
            if config["solver"]["cfl"] > limit:
                raise SimulationError("step 7 (t = 0.01): the state became non-finite (NaN or inf)")
            return real(config)
        return fake

    data_cfl = json.loads((run / "dataset.json").read_text())["solver"].get("cfl", SOLVER_DEFAULTS["cfl"])
    monkeypatch.setattr(gen, "simulate", failing_above(0.3 * data_cfl))
    out = tmp_path / "out"
    assert main([str(run), "--mesh", str(mesh_file), "--steps", "3", "--solver", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert asked == [data_cfl, data_cfl / 2, data_cfl / 4] and summary["solver_cfl"] == data_cfl / 4
    check_outputs(out, summary, 3)
    assert f"the solver at CFL {data_cfl / 4:g}: " in capsys.readouterr().out
    asked.clear()
    monkeypatch.setattr(gen, "simulate", failing_above(0.0))
    assert main([str(run), "--mesh", str(mesh_file), "--steps", "3", "--solver", "--out", str(out), "--quiet"]) == 2
    assert asked == [data_cfl, data_cfl / 2, data_cfl / 4]
    assert capsys.readouterr().err.strip() == (
        f"error: the MPM solver went non-finite on this placement at CFL {data_cfl:g}, {data_cfl / 2:g}, "
        f"{data_cfl / 4:g} (step 7 (t = 0.01): the state became non-finite (NaN or inf)); run without --solver, "
        "or mesh the body finer")


def test_mesh_four_times_larger_than_any_in_training(run_2d, tmp_path):
    run, trainer = run_2d
    largest = max(s.n_body for s in trainer.train_set.scenarios + trainer.valid_set.scenarios)
    mesh = shapes.disk(1.0, 0.05)
    assert mesh.n_nodes >= 4 * largest
    out = tmp_path / "big"
    assert main([str(run), "--mesh", str(write(mesh, tmp_path / "big.msh")), "--steps", "2", "--out", str(out),
                 "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["nodes"] == [mesh.n_nodes] and summary["finite"]
    assert len(summary["graph_nodes_per_level"]) == 3
    assert mesh.n_nodes <= summary["graph_nodes_per_level"][0] <= 1.2 * mesh.n_nodes, "walls only where in reach"


def test_3d_mesh_file(run_3d, tmp_path):
    run, _ = run_3d
    out = tmp_path / "cube"
    mesh_file = write(shapes.box((1.0, 1.0, 1.0), 0.4), tmp_path / "cube.vtu")
    assert main([str(run), "--mesh", str(mesh_file), "--steps", "2", "--solver", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 2 and summary["finite"]
    check_outputs(out, summary, 2)


def test_a_closed_surface_file_is_tetrahedralised_at_the_models_spacing(run_3d, tmp_path, capsys):
    """bsms infer RUN --mesh part.stl on a 3D run: the part's surface meshed at the family's body
    spacing once scaled to its bodies' size, rolled out and checked by the solver on that mesh."""
    from surface_files import box_surface, triangles, write_binary_stl

    run, _ = run_3d
    points, quads = box_surface()
    part = write_binary_stl(tmp_path / "part.stl", 30.0 * points, triangles(quads))  # a 30 x 60 x 15 mm part
    out = tmp_path / "part"
    assert main([str(run), "--mesh", str(part), "--steps", "2", "--solver", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    (record,) = summary["tetrahedralised"]
    volume_file = out / "part_tetrahedra.vtu"
    assert record["surface"] == str(part) and record["mesh"] == str(volume_file) and volume_file.is_file()
    scale = summary["params"]["sizes"][0] / 60.0  # the family scales the part's largest extent to its bodies' size
    assert record["spacing"] == 0.075 and record["size"] == pytest.approx(0.075 / scale), "balls_quick's body_size"
    assert summary["meshes"] == [str(part)] and summary["nodes"] == [record["nodes"]]
    assert summary["finite"] and summary["meshing_s"] == record["seconds"] > 0
    check_outputs(out, summary, 2)
    printed = capsys.readouterr().out
    assert f"{part}: tetrahedralised at {record['size']:.4g} (the model's spacing 0.075 at the family's scale)" in printed


def test_a_surface_file_for_a_2d_run_is_refused(run_2d, tmp_path, capsys):
    from surface_files import box_surface, triangles, write_ascii_stl

    run, _ = run_2d
    points, quads = box_surface()
    part = write_ascii_stl(tmp_path / "part.stl", points, triangles(quads))
    assert main([str(run), "--mesh", str(part), "--quiet"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"error: mesh file {part} is a surface in 3D (triangles off the plane z = 0) but run {run} was trained on "
        "2D meshes; give a 2D mesh (.msh, .vtu; a 2D mesh with z = 0)")


def test_meshes_rolled_out_separately_as_one_batch(run_2d, tmp_path):
    from bsms.infer import infer

    run, _ = run_2d
    meshes = [write(shapes.annulus(0.5, 1.0, 0.25), tmp_path / "ring.vtu"), write(shapes.disk(1.0, 0.3), tmp_path / "a.msh")]
    summary = infer(run, meshes, steps=2, out=tmp_path / "apart", separately=True, progress=False)
    assert [r["meshes"] for r in summary["rollouts"]] == [[str(m)] for m in meshes]
    for rollout_summary, name in zip(summary["rollouts"], ("ring", "a"), strict=True):
        assert rollout_summary["out"] == str(tmp_path / "apart" / name) and rollout_summary["steps"] == 2
        assert json.loads((tmp_path / "apart" / name / "summary.json").read_text())["nodes"] == rollout_summary["nodes"]
    start = time.perf_counter()
    together = infer(run, meshes, steps=2, out=tmp_path / "together", progress=False)
    wall = time.perf_counter() - start
    assert together["call_s"] <= wall, "what a caller timing infer sees, no more"
    assert together["call_s"] >= together["setup_s"] + together["learned_s"] + together["outputs_s"]
    assert together["nodes"] == [r["nodes"][0] for r in summary["rollouts"]], "one scene of both meshes"
    from bsms.infer import main

    assert main([str(run), "--mesh", str(meshes[0]), "--mesh", str(meshes[1]), "--steps", "2", "--separately",
                 "--out", str(tmp_path / "cli"), "--quiet"]) == 0
    assert all((tmp_path / "cli" / name / "summary.json").is_file() for name in ("ring", "a"))


def test_runs_saved_before_lean_obstacles_load_with_every_obstacle_node(run_2d, tmp_path):
    import torch

    from bsms.checkpoint import load_checkpoint
    from bsms.run import find_checkpoint, load_model

    run, _ = run_2d
    state = load_checkpoint(find_checkpoint(run))
    assert state["config"]["graph"]["obstacle_margin"] == 0.0, "new runs are lean"
    del state["config"]["graph"]["obstacle_margin"]
    torch.save(state, tmp_path / "old.pt")
    _, config, _ = load_model(tmp_path / "old.pt")
    assert config.graph.obstacle_margin is None


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "bsms.infer", *map(str, args), "--quiet"], capture_output=True,
                          text=True, cwd=ROOT, timeout=180)


def test_errors_name_the_file_and_the_fix(run_2d, tmp_path):
    run, _ = run_2d
    cube = write(shapes.box((1.0, 1.0, 1.0), 0.5), tmp_path / "cube.vtu")
    result = run_cli(run, "--mesh", cube)
    assert result.returncode == 2
    assert result.stderr.strip() == (f"error: mesh file {cube} is 3D but run {run} was trained on 2D meshes; "
                                     "give a 2D mesh")
    bad = tmp_path / "bad.vtu"
    meshio.write(bad, meshio.Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), [("triangle", np.array([[0, 1, 2]]))]))
    result = run_cli(run, "--mesh", bad)
    assert result.returncode == 2 and f"mesh file {bad}" in result.stderr and "degenerate" in result.stderr
    (tmp_path / "empty_run").mkdir()
    result = run_cli(tmp_path / "empty_run", "--mesh", cube)
    assert result.returncode == 2
    assert "has no usable checkpoint" in result.stderr and "train it with python train.py CONFIG" in result.stderr
    result = run_cli(run, "--mesh", tmp_path / "nothing.msh")
    assert result.returncode == 2 and f"mesh file {tmp_path / 'nothing.msh'} does not exist" in result.stderr


def test_a_pretrained_export_infers_like_its_run(run_2d, tmp_path):
    """The exported folder keeps weights and normalisers only (weights_only loadable, no optimiser),
    and inference from it equals inference from the run, bit for bit."""
    import torch

    from bsms.infer.pretrained import main as export_main

    run, _ = run_2d
    out = tmp_path / "pretrained"
    assert export_main([str(run), str(out)]) == 0
    state = torch.load(out / "checkpoints" / "best.pt", map_location="cpu", weights_only=True)
    assert sorted(state) == sorted(k for k in ("format", "config", "dim", "fields", "step", "best_valid", "seconds",
                                                "model"))
    assert any("normalizer" in key or "mean" in key for key in state["model"])
    assert (out / "config.yaml").is_file() and json.loads((out / "dataset.json").read_text())["family"] == "glyphs"
    mesh_file = write(shapes.disk(1.0, 0.3), tmp_path / "disk.msh")
    for folder, name in ((run, "from_run"), (out, "from_export")):
        assert main([str(folder), "--mesh", str(mesh_file), "--steps", "2", "--out", str(tmp_path / name),
                     "--quiet"]) == 0
    read = [meshio.xdmf.TimeSeriesReader(str(tmp_path / name / "prediction.xdmf")) for name in ("from_run",
                                                                                               "from_export")]
    for reader in read:
        reader.read_points_cells()
    moved = [np.stack([reader.read_data(k)[1]["position"] for k in range(3)]) for reader in read]
    assert np.abs(moved[0][2] - moved[0][0]).max() > 0  # the bodies moved
    np.testing.assert_array_equal(moved[0], moved[1])
    assert export_main([str(tmp_path / "missing"), str(tmp_path / "x")]) == 2


def test_the_committed_pretrained_press_model_infers_on_a_new_shape(tmp_path):
    """pretrained/press2d is in the repository (weights-only loadable, a few MB) and infers from a
    fresh clone: a shape it never saw, placed as the family's bodies are, rolls out finite."""
    import torch

    folder = Path(__file__).resolve().parents[1] / "pretrained" / "press2d"
    weights = folder / "checkpoints" / "best.pt"
    assert weights.is_file() and weights.stat().st_size < 10 * 2**20
    state = torch.load(weights, map_location="cpu", weights_only=True)
    assert "optimizer" not in state and state["config"]["model"]["name"] == "bsms_gnn"
    dataset = json.loads((folder / "dataset.json").read_text())
    assert dataset["family"] == "press" and dataset["solver"]["reference"] == "eulerian"
    mesh_file = write(shapes.polygon(np.array([[0.0, 0.0], [1.0, 0.0], [0.8, 0.7], [0.2, 0.9]]), size=0.1),
                      tmp_path / "quad.msh")
    assert main([str(folder), "--mesh", str(mesh_file), "--steps", "3", "--out", str(tmp_path / "out"), "--quiet"]) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["finite"] is True and summary["steps"] == 3


def test_a_mesh_coarser_than_the_familys_bodies_is_refined_and_reported_on_its_nodes(tmp_path):
    """A 4 mm mesh, coarser than the press family's 2.5 mm bodies, is subdivided once for the model
    and the solver (datagen.refine); prediction.xdmf and solver.xdmf hold the given mesh's nodes
    and cells, the errors are theirs. ``--scene refine=false`` keeps the mesh as given."""
    from datagen.refine import subdivide

    folder = Path(__file__).resolve().parents[1] / "pretrained" / "press2d"
    ring = np.array([[0.0, 0.0], [0.12, 0.0], [0.12, 0.06], [0.07, 0.06], [0.06, 0.032], [0.05, 0.06], [0.0, 0.06]])
    mesh = shapes.polygon(ring, size=0.004)
    mesh_file = write(mesh, tmp_path / "plate.msh")
    out = tmp_path / "out"
    assert main([str(folder), "--mesh", str(mesh_file), "--steps", "2", "--solver", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["nodes"] == [mesh.n_nodes] and summary["body_nodes"] == subdivide(mesh).n_nodes
    with meshio.xdmf.TimeSeriesReader(str(out / "prediction.xdmf")) as reader:
        _, cells = reader.read_points_cells()
        errors = np.stack([reader.read_data(k)[1]["error"] for k in range(3)])
    np.testing.assert_array_equal(cells[0].data, mesh.cells)
    predicted, solver = read_positions(out / "prediction.xdmf"), read_positions(out / "solver.xdmf")
    assert predicted.shape == solver.shape and predicted.shape[:2] == (3, mesh.n_nodes)
    np.testing.assert_allclose(np.linalg.norm(predicted - solver, axis=-1), errors, rtol=1e-12, atol=1e-15)
    curve = np.sqrt(np.mean(errors[1:] ** 2, axis=1))
    assert summary["rmse_all"] == pytest.approx(np.sqrt(np.mean(curve**2)), rel=1e-12)
    first = predicted[0]  # the given nodes, placed: scaled and moved alike
    ratio = np.linalg.norm(np.subtract(*first[mesh.edges.T]), axis=1) / mesh.edge_lengths
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)
    kept = tmp_path / "kept"
    assert main([str(folder), "--mesh", str(mesh_file), "--steps", "2", "--scene", "refine=false", "--out", str(kept),
                 "--quiet"]) == 0
    assert json.loads((kept / "summary.json").read_text())["body_nodes"] == mesh.n_nodes
