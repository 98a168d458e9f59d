"""3D bodies in a box (scene ``balls``, family ``balls``), user meshes (scene ``bodies``) and
zero-shot placement of any mesh into a family's setting (``datagen.families.place``)."""

from pathlib import Path

import meshio
import numpy as np
import pytest

from datagen import shapes
from datagen.config import ConfigError
from datagen.dataset import load
from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.families import get_family, place
from datagen.generate import generate
from datagen.simulation import build_simulation, resolve_config, simulate

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "datasets"
BOX3 = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]


def _ball(gravity: float, frames: int = 4) -> dict:
    """One ball in the middle of a unit box, far enough from the walls that no wall node is in its kernels."""
    return {"scene": "balls", "params": {"radii": [0.1], "centers": [[0.5, 0.55, 0.5]], "velocities": [[0.1, -0.2, 0.05]],
                                         "body_size": 0.06, "mesh_size": 0.15, "gravity": gravity},
            "solver": {"threads": 1}, "output": {"frames": frames, "frame_interval": 0.05}}


def _bodies(sim) -> list[np.ndarray]:
    """(n_k, d) rest positions of each body of a built simulation."""
    body_id = sim.scene.body_id
    return [sim.scene.body.nodes[body_id == k] for k in np.unique(body_id)]


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory):
    """A tiny 2D disk (VTU, points padded with z = 0) and a tiny 3D ball (gmsh .msh), written by meshio."""
    folder = tmp_path_factory.mktemp("meshes")
    disk, ball = shapes.disk(1.0, 0.5, center=(3.0, -2.0)), shapes.sphere(1.0, 0.7)
    flat = np.hstack([disk.nodes, np.zeros((disk.n_nodes, 1))])
    meshio.write(folder / "disk.vtu", meshio.Mesh(flat, [("triangle", disk.cells)]))
    meshio.write(folder / "ball.msh", meshio.Mesh(ball.nodes, [("tetra", ball.cells)]), file_format="gmsh22",
                 binary=False)
    (folder / "broken.vtu").write_text("not a mesh")
    return {"disk": folder / "disk.vtu", "ball": folder / "ball.msh", "broken": folder / "broken.vtu",
            "disk_mesh": disk, "ball_mesh": ball}


# ----------------------------------------------------------------------------- 3D box scene
def test_3d_box_scene_geometry():
    sim = build_simulation(_ball(2.0, frames=1))
    scene = sim.scene
    assert scene.dim == 3 and scene.body.cells.shape[1] == 4
    np.testing.assert_array_equal(scene.gravity, [0.0, -2.0, 0.0])  # y is up, as in 2D
    assert scene.obstacle_facets.shape[1] == 3  # the box's boundary triangles
    on_face = np.isclose(scene.obstacle_nodes, 0.0) | np.isclose(scene.obstacle_nodes, 1.0)
    assert on_face.any(axis=1).all()
    np.testing.assert_allclose(scene.obstacle_nodes.min(0), 0.0, atol=1e-12)
    np.testing.assert_allclose(scene.obstacle_nodes.max(0), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(scene.body.nodes - [0.5, 0.55, 0.5], axis=1).max(), 0.1, rtol=1e-9)


def test_3d_box_conserves_momentum_without_gravity_before_contact():
    traj = simulate(_ball(0.0))
    d = traj.diagnostics
    np.testing.assert_allclose(d["mass"], d["mass"][0], rtol=1e-12)
    np.testing.assert_allclose(d["momentum"] / d["mass"][:, None], np.tile([0.1, -0.2, 0.05], (5, 1)), atol=1e-12)


def test_3d_box_falls_at_gravity_before_contact():
    g, v0 = 2.0, np.array([0.1, -0.2, 0.05])
    traj = simulate(_ball(g))
    d, t = traj.diagnostics, traj.times[:, None]
    expected_v = v0 + t * [0.0, -g, 0.0]
    np.testing.assert_allclose(d["momentum"] / d["mass"][:, None], expected_v, atol=1e-12)
    # symplectic Euler: x_n = x_0 + v_0 t - g dt^2 n (n + 1) / 2 for a rigid translation
    expected_x = d["center_of_mass"][0] + v0 * t + [0.0, -g, 0.0] * t * (t + traj.dt) / 2
    np.testing.assert_allclose(d["center_of_mass"], expected_x, atol=1e-12)


def test_3d_box_floor_stops_a_falling_ball():
    traj = simulate({"scene": "balls", "params": {"radii": [0.12], "centers": [[0.5, 0.2, 0.5]],
                                                  "velocities": [[0.2, -0.6, 0.0]], "body_size": 0.08,
                                                  "mesh_size": 0.25},
                     "solver": {"threads": 1}, "output": {"frames": 8, "frame_interval": 0.05}})
    d = traj.diagnostics
    vy = d["momentum"][:, 1] / d["mass"]
    assert vy[0] == pytest.approx(-0.6) and vy[-1] > 0  # bounced
    assert traj.positions[..., 1].min() > 0.0  # never through the floor
    energy = d["kinetic_energy"] + d["elastic_energy"] + d["gravitational_energy"]
    assert energy.max() <= energy[0] * (1 + 1e-9)


# ----------------------------------------------------------------------------- bodies scene
def test_bodies_2d_mesh_file_runs_with_placed_vertices_as_tracked_points(mesh_files):
    config = {"scene": "bodies", "params": {"meshes": [str(mesh_files["disk"])] * 2, "centers": [[0.3, 0.5], [2.0, 1.5]],
                                            "sizes": [0.3, None], "velocities": [[0.2, 0.0], [-0.2, 0.0]],
                                            "box": [0.0, 0.0, 3.0, 3.0], "mesh_size": 0.3},
              "solver": {"threads": 1}, "output": {"frames": 3, "frame_interval": 0.02}}
    traj = simulate(config)
    disk = mesh_files["disk_mesh"]
    middle = (disk.nodes.min(0) + disk.nodes.max(0)) / 2
    scale = 0.3 / np.ptp(disk.nodes, axis=0).max()  # largest extent becomes the size
    np.testing.assert_allclose(traj.positions[0, traj.body_id == 0], (disk.nodes - middle) * scale + [0.3, 0.5])
    np.testing.assert_allclose(traj.positions[0, traj.body_id == 1], disk.nodes - middle + [2.0, 1.5])
    np.testing.assert_array_equal(traj.mesh.cells[: disk.n_cells], disk.cells)
    assert traj.positions.shape == (4, 2 * disk.n_nodes, 2) and np.isfinite(traj.positions).all()
    assert traj.config["params"]["velocities"] == [[0.2, 0.0], [-0.2, 0.0]]
    assert traj.obstacle_facets.shape[1] == 2


def test_bodies_3d_mesh_file_runs(mesh_files):
    config = {"scene": "bodies", "params": {"meshes": [str(mesh_files["ball"])], "centers": [[0.5, 0.5, 0.5]],
                                            "sizes": [0.3], "box": BOX3, "mesh_size": 0.3},
              "solver": {"threads": 1}, "output": {"frames": 3, "frame_interval": 0.05}}
    traj = simulate(config)
    x0 = traj.positions[0]
    assert traj.mesh.dim == 3 and traj.mesh.n_nodes == mesh_files["ball_mesh"].n_nodes
    assert np.ptp(x0, axis=0).max() == pytest.approx(0.3, rel=1e-12)
    np.testing.assert_allclose((x0.min(0) + x0.max(0)) / 2, [0.5, 0.5, 0.5], atol=1e-12)
    assert np.isfinite(traj.positions).all() and traj.positions[-1, :, 1].mean() < x0[:, 1].mean()  # falling


def _error(params: dict) -> str:
    with pytest.raises(ConfigError) as info:
        resolve_config({"scene": "bodies", "params": params})
    return str(info.value)


def test_bodies_missing_file_and_wrong_dimension_messages(mesh_files, tmp_path):
    missing = tmp_path / "nowhere.vtu"
    assert _error({"meshes": [str(missing)]}) == (
        f"params.meshes[0]: mesh file {missing} does not exist (relative paths start from the working directory)")
    ball = str(mesh_files["ball"])
    assert _error({"meshes": [ball], "box": [0.0, 0.0, 1.0, 1.0]}) == (
        "params.meshes[0] holds a 3D mesh but params.box [0.0, 0.0, 1.0, 1.0] is 2D; give a 3D box or a 2D mesh")
    assert _error({"meshes": [str(mesh_files["disk"]), ball], "sizes": [0.3, 0.3]}) == (
        "params.meshes[1] holds a 3D mesh but params.meshes[0] is 2D; all bodies must have the same dimension")


@pytest.mark.parametrize(("params", "message"), [
    ({"meshes": ["{broken}"]}, r"^params.meshes\[0\]: cannot read mesh file .*broken.vtu: "),
    ({"meshes": []}, r"^params.meshes must list at least one body"),
    ({"meshes": ["{disk}"], "sizes": [1.5]}, r"^params.sizes: body 0 \(.*disk.vtu\) spans \[1.4\d*, 1.5\], larger "
                                             r"than params.box \[0.0, 0.0, 1.0, 1.0\]; make params.sizes smaller$"),
    ({"meshes": ["{disk}"]}, r"^params.sizes: body 0 .* larger than params.box .*; shrink it with params.sizes$"),
    ({"meshes": ["{disk}"], "sizes": [0.3], "centers": [[0.9, 0.5]]},
     r"^params.centers: body 0 .* centred at \[0.9, 0.5\] spans .* outside params.box .*; move it inside$"),
    ({"meshes": ["{disk}", "{disk}"], "sizes": [0.3, 0.3], "centers": [[0.5, 0.5], [0.6, 0.5]]},
     r"^params.centers: body 1 .* starts inside body 0 .*; move them apart$"),
    ({"meshes": ["{disk}"], "sizes": [0.3], "centers": [[0.5, 0.5, 0.5]]},
     r"^params.centers\[0\] must be a 2D vector \(the box's dimension\)"),
    ({"meshes": ["{disk}"], "sizes": [0.3, 0.2]}, r"^params.sizes must be null or list one entry per mesh \(1\)"),
    ({"meshes": ["{disk}"], "sizes": [-0.3]}, r"^params.sizes\[0\] must be a positive number or null"),
    ({"meshes": ["{disk}"], "box": [0.0, 0.0, 1.0]}, r"^params.box must be \[x0, y0, x1, y1\] \(2D\) or"),
    ({"meshes": ["{disk}"], "sizes": [0.3], "radius": 1.0}, r"^unknown config key 'params.radius'; scene 'bodies' accepts: E, box, centers,"),
])
def test_bodies_bad_params_name_the_key(mesh_files, params, message):
    params = {k: [m.format(**mesh_files) for m in v] if k == "meshes" else v for k, v in params.items()}
    with pytest.raises(ConfigError, match=message):
        resolve_config({"scene": "bodies", "params": params})


def test_bodies_takes_inline_meshes_and_defaults_to_the_unit_box():
    disk = shapes.disk(0.2, 0.1, center=(0.5, 0.5))
    p = resolve_config({"scene": "bodies", "params": {"meshes": [{"nodes": disk.nodes.tolist(),
                                                                  "cells": disk.cells.tolist()}]}})["params"]
    assert p["box"] == [0.0, 0.0, 1.0, 1.0] and p["sizes"] == [None] and p["velocities"] == [[0.0, 0.0]]
    np.testing.assert_allclose(p["centers"], [(disk.nodes.min(0) + disk.nodes.max(0)) / 2], atol=1e-15)  # kept
    assert resolve_config({"scene": "bodies", "params": p})["params"] == p  # resolved params resolve to themselves


# ----------------------------------------------------------------------------- placement
def _check_placed(config: dict, n: int, size: float) -> list[np.ndarray]:
    sim = build_simulation(config)
    d = sim.scene.dim
    lower, upper = np.asarray(config["params"]["box"][:d]), np.asarray(config["params"]["box"][d:])
    bodies = _bodies(sim)
    assert len(bodies) == n
    for nodes in bodies:
        assert (nodes >= lower).all() and (nodes <= upper).all()
        assert np.ptp(nodes, axis=0).max() == pytest.approx(size, rel=1e-12)
    return bodies


def test_place_glyphs_scales_and_places_like_letters_and_runs(mesh_files):
    dconfig = load_dataset_config(CONFIGS / "glyphs_quick.yaml")
    config = place("glyphs", [mesh_files["disk_mesh"], mesh_files["disk"]], dconfig)
    height = np.mean(dconfig["ranges"]["height"])
    bodies = _check_placed(config, 2, height)
    middles = [(b.min(0) + b.max(0)) / 2 for b in bodies]
    np.testing.assert_allclose([m[0] for m in middles], [0.25, 0.75], atol=1e-12)  # one column each
    assert all(m[1] > 0.5 for m in middles)  # upper half of the box
    p = config["params"]
    assert p["E"] == pytest.approx(np.sqrt(1e4 * 4e4)) and p["density"] == pytest.approx(1000.0)
    assert p["velocities"] == [[0.0, -0.25]] * 2 and p["gravity"] == 2.0 and p["friction"] == 0.2
    assert config["output"] == dconfig["output"] and config["solver"] == dconfig["solver"]
    assert place("glyphs", [mesh_files["disk_mesh"], mesh_files["disk"]], dconfig) == config  # deterministic
    over = place("glyphs", [mesh_files["disk"]], dconfig, {"E": 2e4, "velocities": [[0.0, -0.3]]})
    assert over["params"]["E"] == 2e4 and over["params"]["velocities"] == [[0.0, -0.3]]
    traj = simulate({**over, "output": {"frames": 2, "frame_interval": 0.05}})
    assert np.isfinite(traj.positions).all()
    np.testing.assert_allclose(traj.velocities[0], np.tile([0.0, -0.3], (traj.mesh.n_nodes, 1)))


def test_place_balls_in_3d_and_runs(mesh_files):
    config = place("balls", [mesh_files["ball"]], CONFIGS / "balls_quick.yaml", {"E": 2e4})
    dconfig = load_dataset_config(CONFIGS / "balls_quick.yaml")
    (nodes,) = _check_placed(config, 1, 2 * np.mean(dconfig["ranges"]["radius"]))
    np.testing.assert_allclose((nodes.min(0) + nodes.max(0)) / 2, [0.5, 0.7, 0.5], atol=1e-12)
    assert config["params"]["E"] == 2e4 and config["params"]["velocities"] == [[0.15, -0.25, 0.0]]
    traj = simulate({**config, "output": {"frames": 2, "frame_interval": 0.05}})
    assert traj.mesh.dim == 3 and np.isfinite(traj.positions).all()


def test_place_disks_moves_bodies_towards_each_other(mesh_files):
    config = place("disks", [mesh_files["disk_mesh"]] * 2, CONFIGS / "disks.yaml")
    _check_placed(config, 2, 0.32)
    np.testing.assert_allclose(config["params"]["velocities"], [[0.125, 0.0], [-0.125, 0.0]], atol=1e-12)


def test_place_errors(mesh_files):
    for family in ("wavy_channel", "cantilever"):
        with pytest.raises(ConfigError, match=f"zero-shot placement is not supported for family {family}"):
            place(family, [mesh_files["disk"]], CONFIGS / f"{family}_quick.yaml")
    glyphs = CONFIGS / "glyphs_quick.yaml"
    with pytest.raises(ConfigError, match="^meshes\\[0\\] is a 3D mesh but family 'glyphs' is 2D"):
        place("glyphs", [mesh_files["ball"]], glyphs)
    with pytest.raises(ConfigError, match="^overrides.radius is not a bodies scene parameter"):
        place("glyphs", [mesh_files["disk"]], glyphs, {"radius": 0.1})
    with pytest.raises(ConfigError, match="^dconfig is a config of family 'disks', not 'glyphs'"):
        place("glyphs", [mesh_files["disk"]], CONFIGS / "disks_quick.yaml")
    with pytest.raises(ConfigError, match="^params.centers: body 0 .* outside params.box"):
        place("glyphs", [mesh_files["disk"]], glyphs, {"centers": [[0.95, 0.5]]})


# ----------------------------------------------------------------------------- balls family
def test_balls_family_tests_on_unseen_shapes_inside_the_drop_region():
    dconfig = load_dataset_config(CONFIGS / "balls.yaml")
    for split, shape in (("train", "sphere"), ("valid", "sphere"), ("test", "cube")):
        for index in range(20):
            p = trajectory_config(dconfig, split, index)["params"]
            c, r = np.asarray(p["centers"]), np.asarray(p["radii"])
            assert set(p["shapes"]) == {shape} and 1 <= len(r) <= 2
            assert (c - r[:, None] >= [0.0, 0.4, 0.0]).all() and (c + r[:, None] <= 1.0).all()
            gaps = np.linalg.norm(c[:, None] - c[None], axis=-1) - r[:, None] - r[None]
            assert (gaps[~np.eye(len(r), dtype=bool)] > 0).all()
    bad = {**dconfig, "ranges": {**dconfig["ranges"], "test_shapes": ["sphere"]}}
    with pytest.raises(ConfigError, match=r"ranges.test_shapes shares \['sphere'\] with ranges.train_shapes"):
        trajectory_config(bad, "test", 0)
    assert get_family("balls").DIM == 3


def test_balls_quick_generates_one_small_trajectory(tmp_path):
    dconfig = {**load_dataset_config(CONFIGS / "balls_quick.yaml"), "splits": {"train": 1}}
    summary = generate(dconfig, out=tmp_path, progress=False)
    assert [r.skipped for r in summary.results] == [False]
    traj = load(tmp_path / "balls_quick" / "train" / "00000.h5")
    assert 80 <= traj.mesh.n_nodes <= 400 and traj.mesh.cells.shape[1] == 4
    assert traj.positions.shape == (9, traj.mesh.n_nodes, 3) and np.isfinite(traj.positions).all()
    assert ((traj.positions >= 0.0) & (traj.positions <= 1.0)).all()
    assert traj.obstacle_facets.shape[1] == 3 and (tmp_path / "balls_quick" / "metadata.json").is_file()
