"""simulate(config): config checking, the vibrating bar against UMLS eq. 34, APIC conservation."""

import dataclasses
import warnings

import numpy as np
import pytest
import torch
import yaml

import datagen
from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mpm.boundary import Mirror, Slip, Wall, apply_conditions, fold_mirrors, mesh_conditions
from datagen.scenes import ConfigError, vibrating_bar

pytestmark = pytest.mark.usefixtures("one_thread")


# ----------------------------------------------------------------------------- config
@pytest.mark.parametrize("config, key", [
    ({"scene": "no_such_scene"}, "scene"),
    ({"scene": "vibrating_bar", "colour": 1}, "colour"),
    ({"scene": "vibrating_bar", "params": {"lenght": 3.0}}, "params.lenght"),
    ({"scene": "vibrating_bar", "params": {"n_cells": "many"}}, "params.n_cells"),
    ({"scene": "vibrating_bar", "params": {"E": -1.0}}, "params.E"),
    ({"scene": "vibrating_bar", "params": {"dim": 4}}, "params.dim"),
    ({"scene": "vibrating_bar", "solver": {"kernel": "quartic"}}, "solver.kernel"),
    ({"scene": "vibrating_bar", "solver": {"transfer": "flop"}}, "solver.transfer"),
    ({"scene": "vibrating_bar", "solver": {"dt": 0}}, "solver.dt"),
    ({"scene": "vibrating_bar", "solver": {"cfl": 2.0}}, "solver.cfl"),
    ({"scene": "vibrating_bar", "solver": {"device": "tpu:7"}}, "solver.device"),
    ({"scene": "vibrating_bar", "output": {"frames": 2.5}}, "output.frames"),
    ({"scene": "vibrating_bar", "output": {"fps": 3}}, "output.fps"),
    ({"params": {}}, "scene"),
])
def test_bad_configs_name_the_key(config, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        datagen.simulate(config)


def test_yaml_config_and_trajectory_contents(tmp_path):
    path = tmp_path / "bar.yaml"
    path.write_text(yaml.safe_dump({
        "scene": "vibrating_bar", "params": {"n_cells": 10, "particles_per_cell": 1},
        "solver": {"kernel": "umls"}, "output": {"frames": 4, "frame_interval": 0.05, "step_diagnostics": True},
    }))
    traj = datagen.simulate(path)
    assert isinstance(traj, datagen.Trajectory)
    assert traj.positions.shape == (5, 10, 1) and traj.velocities.shape == (5, 10, 1)
    assert traj.mesh.n_nodes == 10 and traj.times.shape == (5,)
    np.testing.assert_allclose(traj.times, np.arange(5) * 0.05)
    assert traj.substeps * traj.dt == pytest.approx(0.05)
    assert traj.config["params"]["E"] == 100.0 and traj.config["solver"]["transfer"] == "flip"
    assert traj.step_diagnostics["kinetic_energy"].shape == (4 * traj.substeps,)
    for name in ("mass", "momentum", "angular_momentum", "kinetic_energy", "elastic_energy",
                 "gravitational_energy", "center_of_mass", "probe_stress"):
        assert name in traj.diagnostics
    assert traj.frame_wall_times.shape == (5,) and traj.frame_wall_times[0] == 0.0
    assert traj.wall_time == pytest.approx(traj.frame_wall_times.sum(), rel=1e-12)


# ----------------------------------------------------------------------------- vibrating bar (item 4)
def _stress_noise(t: np.ndarray, stress: np.ndarray, omega: float) -> float:
    """RMS of what a least-squares fit of the smooth response (1, 3 omega harmonics) leaves."""
    basis = np.stack([np.ones_like(t)] + [f(k * omega * t) for k in (1, 3) for f in (np.sin, np.cos)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, stress, rcond=None)
    return float(np.sqrt(np.mean((stress - basis @ coef) ** 2)))


def test_vibrating_bar_defaults_reproduce_the_closed_form():
    """UMLS §3.1 (UMLS eq. 34) with nothing but the scene name: one period, 80 cells; the centre of mass's
    RMSE is 0.027% of its amplitude (the paper asks < 1%)."""
    traj = datagen.simulate({"scene": "vibrating_bar"})
    p = traj.config["params"]
    assert p["n_cells"] == 80 and traj.times[-1] >= 2 * np.pi / vibrating_bar.omega(p) - 1e-9
    cm = traj.diagnostics["center_of_mass"][:, 0]
    rmse = np.sqrt(np.mean((cm - vibrating_bar.center_of_mass(p, traj.times)) ** 2))
    assert rmse < 0.002 * vibrating_bar.amplitude(p)


def test_layer_nodes_between_opposite_walls_get_a_unit_normal():
    """A 2D strip two cells high: layer nodes beyond the free end touch both slip walls, whose
    normals cancel; they take their nearest wall neighbour's normal (was 0/0 = NaN)."""
    scene = vibrating_bar.build(vibrating_bar.params({"dim": 2, "n_cells": 40}))  # dx 0.625, height 1
    extended = with_extra_layer(scene.domain)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        conditions = mesh_conditions(scene.domain, extended, scene.walls, [])
    slip = next(c for c in conditions if isinstance(c, Slip))
    normals = slip.normals.numpy().T  # (n, d)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(normals[:, 1]), 1.0, atol=1e-12)  # the strip's walls are y = 0 and y = 1


@pytest.mark.parametrize("dim", [1, 2])
def test_sticky_wall_mirrors_the_extra_layer(dim):
    """Layer nodes beyond the bar's fixed end get minus the velocity at their reflection across x = 0."""
    scene = vibrating_bar.build(vibrating_bar.params({"dim": dim}))
    extended = with_extra_layer(scene.domain)
    nodes = extended.mesh.nodes
    conditions = mesh_conditions(scene.domain, extended, scene.walls, [])
    mirror = conditions[-1]
    assert isinstance(mirror, Mirror) and mirror.ghosts.numel() > 0
    assert (nodes[mirror.ghosts.numpy(), 0] < 0).all()
    linear = torch.tensor(nodes.T, dtype=torch.float64)  # v = x is odd about x = 0 in its first component
    ghosts = mirror.ghosts.numpy()
    got = mirror.apply(linear.clone())[:, ghosts].numpy()
    np.testing.assert_allclose(got[0], nodes[ghosts, 0], atol=1e-12)
    if dim == 2:
        np.testing.assert_allclose(got[1], -nodes[ghosts, 1], atol=1e-12)
    plain = [dataclasses.replace(w, mirror=False) for w in scene.walls]
    assert not any(isinstance(c, Mirror) for c in mesh_conditions(scene.domain, extended, plain, []))


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_folded_mirror_is_the_transpose_of_the_ghost_velocities(dim):
    """fold_mirrors moves the ghosts' odd node sums (momentum, force) onto their sources so that the
    power sum_i f_i v_i of a constrained velocity field is the same before and after the fold."""
    if dim < 3:
        scene = vibrating_bar.build(vibrating_bar.params({"dim": dim, "n_cells": 20}))
        domain, walls = scene.domain, [w for w in scene.walls if w.kind == "sticky"]
    else:  # a tetrahedral box clamped at x = 0
        domain, walls = shapes.box((1.0, 0.5, 0.5), 0.2), [Wall("sticky", lambda c, n: n[:, 0] < -0.5)]
    extended = with_extra_layer(domain)
    conditions = mesh_conditions(domain, extended, walls, [])
    mirror = conditions[-1]
    assert isinstance(mirror, Mirror) and mirror.wall is not None and mirror.wall.numel() > 0
    rng = np.random.default_rng(0)
    n = extended.mesh.n_nodes
    v = apply_conditions(torch.tensor(rng.normal(size=(dim, n))), conditions)  # wall at rest, ghosts mirrored
    f = torch.tensor(rng.normal(size=(dim, n)))
    folded = fold_mirrors(f.clone(), conditions, [-1.0] * dim)
    assert float((folded * v).sum()) == pytest.approx(float((f * v).sum()), rel=1e-12)
    assert float(folded[:, mirror.ghosts].abs().max()) == 0.0 and float(folded[:, mirror.wall].abs().max()) == 0.0
    mass = torch.ones(1, n, dtype=torch.float64)  # even rows: each ghost's mass goes to its sources, the total is kept
    assert float(fold_mirrors(mass.clone(), conditions, [1.0]).sum()) == pytest.approx(n)


def _bar_rmse(n: int, fixed_end: str, kernel: str = "umls") -> float:
    """Displacement RMSE of the 1D bar over one period, relative to the amplitude (CFL step)."""
    traj = datagen.simulate({"scene": "vibrating_bar", "params": {"n_cells": n, "fixed_end": fixed_end},
                             "solver": {"kernel": kernel}})
    p = traj.config["params"]
    X = traj.positions[0, :, 0]
    amplitude = p["v0"] / vibrating_bar.omega(p)
    exact = amplitude * np.sin(vibrating_bar.omega(p) * traj.times)[:, None] * np.sin(np.pi / 50 * X)[None, :]
    return float(np.sqrt(np.mean((traj.positions[:, :, 0] - X - exact) ** 2))) / amplitude


_LOG_DX = np.log(25.0 / np.array([12, 25, 50]))


def test_vibrating_bar_converges_at_second_order():
    """12-50 cells, the paper's amplitude, CFL step: with the ghosts beyond the fixed end folded the
    displacement RMSE falls as dx^2 (measured slope 1.88: 0.70/0.17/0.048%); only overwriting them left
    the clamp about 0.07 dx beyond x = 0 and the error first order (slope 1.24: 1.8/0.69/0.31%)."""
    folded = [_bar_rmse(n, "fold") for n in (12, 25, 50)]
    assert np.polyfit(_LOG_DX, np.log(folded), 1)[0] > 1.8 and folded[-1] < 1e-3
    overwritten = [_bar_rmse(n, "overwrite") for n in (12, 25, 50)]
    assert np.polyfit(_LOG_DX, np.log(overwritten), 1)[0] < 1.4


def test_bspline_grid_solver_clamps_with_folded_mirror_ghosts():
    """The structured B-spline solver's grid mirrors and folds the nodes beyond a sticky face too: the bar's error falls
    as dx^1.75 (measured 0.73/0.19/0.061%); holding them at rest is first order (3.6/1.6/0.75%)."""
    folded = [_bar_rmse(n, "fold", "bspline") for n in (12, 25, 50)]
    assert np.polyfit(_LOG_DX, np.log(folded), 1)[0] > 1.6 and folded[-1] < 1e-3
    rest = [_bar_rmse(n, "rest", "bspline") for n in (12, 25, 50)]
    assert np.polyfit(_LOG_DX, np.log(rest), 1)[0] < 1.3


def test_vibrating_bar_2d_strip_reproduces_the_closed_form():
    """The 2D strip (slip walls, nu = 0) at 80 cells: RMSE < 1% of amplitude (measured 0.57% with the sticky
    wall's mirror ghosts folded; 0.98% unfolded, 1.56% with the layer nodes held at rest)."""
    traj = datagen.simulate({"scene": "vibrating_bar", "params": {"dim": 2}})
    p = traj.config["params"]
    cm = traj.diagnostics["center_of_mass"][:, 0]
    rmse = np.sqrt(np.mean((cm - vibrating_bar.center_of_mass(p, traj.times)) ** 2))
    assert rmse < 0.01 * vibrating_bar.amplitude(p)


def test_linear_kernel_shows_cell_crossing_stress_noise():
    """Same bar, MUSL strain update for both kernels (the linear hat blows up with plain FLIP)."""
    noise = {}
    for kernel in ("umls", "linear"):
        traj = datagen.simulate({"scene": "vibrating_bar", "solver": {"kernel": kernel, "transfer": "musl"},
                                 "output": {"frames": 200, "frame_interval": 0.025}})
        stress = traj.diagnostics["probe_stress"][:, 0, 0, 0]
        noise[kernel] = _stress_noise(traj.times, stress, vibrating_bar.omega(traj.config["params"]))
    assert noise["linear"] >= 15 * noise["umls"]  # measured 33x


# ----------------------------------------------------------------------------- rotating square (item 5)
def test_apic_rotating_square_conserves_momenta_over_5000_steps():
    """App. D.1 with the paper's particles, material and dt = 1e-5 s, on a smaller box; checked every 10 steps."""
    traj = datagen.simulate({
        "scene": "rotating_square", "params": {"box": 0.4, "mesh_size": 0.02},
        "output": {"frames": 500, "frame_interval": 1e-4},
    })
    steps = traj.diagnostics
    assert traj.substeps == 10 and len(steps["momentum"]) - 1 == 500
    p = traj.config["params"]
    scale = float(traj.diagnostics["mass"][0]) * p["speed"]
    assert np.abs(steps["momentum"]).max() < 1.5e-14 * scale  # measured 1.6e-15
    L0 = float(traj.diagnostics["angular_momentum"][0])
    assert abs(L0) > 0.4 * scale * p["side"] / 2  # it really spins (measured 0.5)
    assert np.abs(steps["angular_momentum"] - L0).max() < 8e-14 * abs(L0)  # measured 8.2e-15
