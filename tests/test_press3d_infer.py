"""Zero-shot on a user's part in the 3D press family: datagen.families.press3d.place puts a given
tetrahedral mesh in the family's setting (datagen.scenes.press3d's ``body: mesh``), and
``bsms infer RUN --mesh part.stl --solver`` runs it end to end on a tiny press3d run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import meshio
import numpy as np
import pytest
import torch
from conftest import _tiny, tiny_run_config
from surface_files import box_surface, triangles, write_binary_stl

from datagen import shapes, shapes3d
from datagen.config import ConfigError
from datagen.dataset_config import load_dataset_config
from datagen.families import place
from datagen.mesh import Mesh
from datagen.scenes import get_scene
from datagen.scenes.solids import rest_pose, stands
from datagen.simulation import resolve_config

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "datasets"
QUICK = CONFIGS / "press3d_quick.yaml"
scene = get_scene("press3d")

# A tiny press3d dataset: press3d_quick's soft 200-300-node bodies on a 20 mm background, 3 frames
# (about a second a trajectory on one core), three trajectories.
TINY_PRESS3D = """\
extends: {base}
dataset: tiny_press3d
splits: {{train: 2, valid: 1}}
"""


def l_section(scale: float = 1.0) -> Mesh:
    """An L section 1 x 0.8 x 0.6 (x ``scale``; legs 0.25 and 0.3 thick), meshed at 0.12 x scale:
    500-odd nodes."""
    return shapes3d.extrude(shapes3d.section_outline("L", scale, 0.8 * scale, 0.25 * scale, 0.3 * scale),
                            depth=0.6 * scale, size=0.12 * scale)


def write(mesh: Mesh, path: Path) -> Path:
    meshio.write(path, meshio.Mesh(mesh.nodes, [("tetra", mesh.cells)]))
    return path


def built(mesh_file, overrides=None, dconfig=QUICK):
    config = place("press3d", [str(mesh_file)], dconfig, overrides)
    resolved = resolve_config(config)
    return config, scene.build(resolved["params"])


def scale_of(given: Mesh, placed: Mesh) -> float:
    """The one ratio of every edge's length, placed over given (a similarity: posed, scaled, moved)."""
    ratio = np.linalg.norm(np.subtract(*placed.nodes[given.edges.T]), axis=1) / given.edge_lengths
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)
    return float(ratio[0])


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_a_given_mesh_is_the_body_scaled_to_the_familys_size_and_bonded_on_the_floor(tmp_path, suffix):
    given = l_section(100.0)  # in millimetres, say
    config, built_scene = built(write(given, tmp_path / f"part{suffix}"))
    p = config["params"]
    d = load_dataset_config(QUICK)
    assert p["body"] == "mesh" and p["mesh"] == str((tmp_path / f"part{suffix}").resolve())
    assert p["size"] == pytest.approx(0.115) and p["nodes"] == 250, "mid-range of press3d_quick's ranges"
    assert p["E"] == pytest.approx(math.sqrt(1e5 * 1e6)) and p["nu"] == pytest.approx(0.35)
    assert p["density"] == pytest.approx(1250.0) and p["speed"] == pytest.approx(0.16)
    assert p["base"] == d["params"]["base"] == "bonded" and p["mesh_size"] == 0.02
    body = built_scene.body
    assert body.n_nodes == given.n_nodes and built_scene.given_cells is None, "as fine as the family's bodies"
    np.testing.assert_array_equal(body.cells, given.cells)
    s = scale_of(given, body)
    assert np.ptp(body.nodes, axis=0).max() == pytest.approx(0.115, rel=1e-12)
    assert body.cell_measures.sum() == pytest.approx(given.cell_measures.sum() * s**3, rel=1e-12)
    base = body.nodes[:, 1] < 1e-9
    assert body.nodes[:, 1].min() == 0.0 and base.sum() >= 4, "the L's foot on the floor"
    assert built_scene.walls[0].kind == "sticky", "bonded: the floor is a sticky wall"
    lower, upper = np.array([0.0, 0.0, 0.0]), np.array([0.18, 0.16, 0.18])
    np.testing.assert_allclose((body.nodes.min(0) + body.nodes.max(0))[[0, 2]] / 2, ((lower + upper) / 2)[[0, 2]])


def gap_under(built_scene) -> float:
    """How far the indenter starts above the body where they come closest, vertically."""
    collider = built_scene.colliders[0]
    nodes = torch.tensor(built_scene.body.nodes)

    def touches(lift: float) -> bool:
        distance, _ = collider.signed_distance(nodes + torch.tensor([0.0, lift, 0.0], dtype=nodes.dtype), 0.0)
        return float(distance.min()) <= 0.0

    low, high = 0.0, 0.05  # the body lifted by low clears the indenter, by high it reaches it
    assert not touches(low) and touches(high)
    for _ in range(40):
        low, high = (low, (low + high) / 2) if touches((low + high) / 2) else ((low + high) / 2, high)
    return high


@pytest.mark.parametrize(("overrides", "shape", "sizes"), [
    ({}, "sphere", [0.225 * 0.115]),
    ({"indenter": "bar"}, "box", None),
    ({"indenter": "box", "indenter_scale": 0.2, "indenter_x": 0.01, "indenter_z": -0.005, "angle": 10.0,
      "azimuth": 90.0, "speed": 0.1}, "box", [0.023, 0.7 * 0.023, 0.023]),
])
def test_the_indenter_starts_the_familys_gap_above_the_body(tmp_path, overrides, shape, sizes):
    config, built_scene = built(write(l_section(), tmp_path / "l.vtu"), overrides)
    p = config["params"]
    collider = built_scene.colliders[0]
    assert collider.shape == shape and p["indenter"] == overrides.get("indenter", "sphere")
    if sizes is not None:
        np.testing.assert_allclose(collider.size, sizes, rtol=1e-4)  # rounded to the micrometre
    else:  # a bar of the mid-range half width 0.225 x size, 0.7 as wide, across the body and 10% of size beyond
        np.testing.assert_allclose(collider.size[:2], [0.7 * 0.225 * 0.115, 0.225 * 0.115], rtol=1e-4)
        assert 2 * collider.size[2] == pytest.approx(np.ptp(built_scene.body.nodes[:, 2]) + 0.2 * 0.115)
    assert p["gap"] == pytest.approx(0.016), "the middle of the family's 14-18 mm"
    assert gap_under(built_scene) == pytest.approx(p["gap"], abs=1e-9)
    start, bottom = collider.path.position(0.0), collider.path.position(p["press_time"])
    middle = (built_scene.body.nodes.min(0) + built_scene.body.nodes.max(0)) / 2
    np.testing.assert_allclose(start[[0, 2]], middle[[0, 2]] + [p["indenter_x"], p["indenter_z"]], atol=1e-15)
    tilt = math.radians(p["angle"])
    direction = [0.0, -math.cos(tilt), math.sin(tilt)] if p["azimuth"] == 90.0 else [0.0, -1.0, 0.0]
    np.testing.assert_allclose(bottom - start, p["speed"] * p["press_time"] * np.array(direction), atol=1e-15)


def test_a_toppling_part_is_set_on_its_most_stable_side(tmp_path):
    """A tall thin column lies down; a block turned at random is set down on its largest face (the
    face of its hull nearest its centre of mass), the 2D press's stable pose in 3D."""
    column = shapes.box((0.2, 1.0, 0.2), 0.1)
    assert not stands(column)
    np.testing.assert_allclose(np.sort(np.ptp(rest_pose(column).nodes, axis=0)), [0.2, 0.2, 1.0], atol=1e-12)
    block = shapes.box((1.0, 0.6, 0.5), 0.2)
    assert stands(block) and rest_pose(block) is block, "a body that stands is kept as given"
    c, s = math.cos(0.7), math.sin(0.7)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    turned = Mesh(block.nodes @ turn.T, block.cells)
    assert not stands(turned)
    laid = rest_pose(turned)
    assert stands(laid) and np.ptp(laid.nodes[:, 1]) == pytest.approx(0.5, abs=1e-12)
    _, placed = built(write(turned, tmp_path / "turned.vtu"))
    assert np.ptp(placed.body.nodes[:, 1]) == pytest.approx(0.5 * scale_of(turned, placed.body), rel=1e-9)
    assert (placed.body.nodes[:, 1] < 1e-9).sum() >= 4, "a whole face on the floor"
    _, upright = built(write(turned, tmp_path / "turned.vtu"), {"pose": "upright"})
    assert np.ptp(upright.body.nodes[:, 1]) > 0.6 * scale_of(turned, upright.body)


def test_a_mesh_coarser_than_the_familys_bodies_is_refined_and_keeps_its_volume(tmp_path):
    given = shapes.box((1.0, 0.6, 0.5), 0.5)  # a few dozen nodes against the family's 250
    config, refined = built(write(given, tmp_path / "coarse.vtu"))
    assert refined.body.n_nodes > given.n_nodes and refined.given_cells is not None
    np.testing.assert_array_equal(refined.given_cells, given.cells)
    s = scale_of(given, Mesh(refined.body.nodes[: given.n_nodes], given.cells))
    assert refined.body.cell_measures.sum() == pytest.approx(given.cell_measures.sum() * s**3, rel=1e-12)
    _, kept = built(write(given, tmp_path / "coarse.vtu"), {"refine": False})
    assert kept.body.n_nodes == given.n_nodes and kept.given_cells is None


def test_bad_placements_give_the_familys_errors(tmp_path):
    part = write(l_section(), tmp_path / "l.vtu")
    with pytest.raises(ConfigError, match="overrides.char is not a press3d scene parameter that can be overridden; "
                                          "known: E, angle, azimuth"):
        place("press3d", [str(part)], QUICK, {"char": "A"})
    with pytest.raises(ConfigError, match="overrides.radius is not a press3d scene parameter"):
        place("press3d", [str(part)], QUICK, {"radius": 0.1})
    with pytest.raises(ConfigError, match="family 'press3d' presses one body"):
        place("press3d", [str(part), str(part)], QUICK)
    with pytest.raises(ConfigError, match=r"overrides.indenter must be one of \['bar', 'box', 'sphere'\], got 'wedge'"):
        place("press3d", [str(part)], QUICK, {"indenter": "wedge"})
    with pytest.raises(ConfigError, match="give it or indenter_scale and indenter_aspect"):
        place("press3d", [str(part)], QUICK, {"indenter_size": [0.02], "indenter_scale": 0.2})
    with pytest.raises(ConfigError, match="overrides.indenter_scale must be a positive number"):
        place("press3d", [str(part)], QUICK, {"indenter_scale": -0.1})
    with pytest.raises(ConfigError, match=r"params.indenter_size must list 3 positive length\(s\) for a box"):
        place("press3d", [str(part)], QUICK, {"indenter": "box", "indenter_size": [0.02]})
    flat = shapes.rectangle(1.0, 1.0, 0.5)
    with pytest.raises(ConfigError, match="meshes\\[0\\] is a 2D mesh but family 'press3d' is 3D"):
        place("press3d", [flat], QUICK)
    with pytest.raises(ConfigError, match="params.mesh gives the body with params.body: mesh"):
        scene.params({"body": "mesh"})
    with pytest.raises(ConfigError, match="params.mesh: mesh file .*missing.vtu does not exist"):
        scene.build(scene.params({"body": "mesh", "mesh": str(tmp_path / "missing.vtu")}))


@pytest.fixture(scope="module")
def run_press3d(tmp_path_factory):
    """A press3d model trained for 4 steps on three tiny trajectories."""
    from bsms.run import load_config, prepare_dataset
    from bsms.training.trainer import Trainer

    dataset = _tiny(tmp_path_factory, "tiny_press3d", TINY_PRESS3D, "press3d_quick.yaml")
    runs = tmp_path_factory.mktemp("runs")
    config = load_config(tiny_run_config(dataset, runs, name="press3d", train={"steps": 4, "valid_every": 4,
                                                                              "checkpoint_every": 4}))
    Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    return runs / "press3d"


def test_infer_on_a_parts_stl_with_the_solver(run_press3d, tmp_path, capsys):
    """bsms infer RUN --mesh part.stl --solver on a press3d run: the part tetrahedralised to the
    family's node count, pressed by a bar as --scene asks, prediction.xdmf and solver.xdmf written."""
    from bsms.cli import main

    points, quads = box_surface(upper=(40.0, 20.0, 30.0))  # a 40 x 20 x 30 mm block
    part = write_binary_stl(tmp_path / "part.stl", points, triangles(quads))
    out = tmp_path / "out"
    code = main(["infer", str(run_press3d), "--mesh", str(part), "--solver", "--scene", "indenter=bar",
                 "--scene", "indenter_x=0.01", "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    (record,) = summary["tetrahedralised"]
    assert abs(record["nodes"] / 250 - 1) <= 0.25, "press3d_quick's mid-range node count"
    assert summary["params"]["indenter"] == "bar" and summary["params"]["indenter_x"] == 0.01
    assert summary["params"]["body"] == "mesh" and summary["finite"] and summary["steps"] == 3
    for key in ("vs_rest", "rest_rel_all", "speedup", "speedup_throughput", "solver_s", "setup_s", "learned_s"):
        assert math.isfinite(summary[key]), key
    for name in ("prediction.xdmf", "solver.xdmf"):
        with meshio.xdmf.TimeSeriesReader(str(out / name)) as reader:
            points_read, cells = reader.read_points_cells()
            assert reader.num_steps == 4 and cells[0].type == "tetra"
            assert len(points_read) == record["nodes"] and reader.read_data(3)[1]["position"].shape == (len(points_read), 3)
    assert "solver.xdmf (ParaView)" in capsys.readouterr().out


def test_an_open_surface_is_refused_naming_the_file(run_press3d, tmp_path, capsys):
    from bsms.cli import main

    points, quads = box_surface()
    part = write_binary_stl(tmp_path / "open.stl", points, triangles(quads[1:]))  # a face missing
    assert main(["infer", str(run_press3d), "--mesh", str(part), "--solver", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: surface file {part} does not bound a solid: 4 edges belong to one triangle only")
    assert err.count("\n") == 0 and "Traceback" not in err
