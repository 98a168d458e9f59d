"""Dataset families: every quick variant gives finite, mass-conserving, contained, energy-bounded data."""

from pathlib import Path

import numpy as np
import pytest

from datagen.config import ConfigError
from datagen.dataset_config import load_dataset_config, trajectory_config
from datagen.families import FAMILIES, get_family
from datagen.simulation import simulate
from datagen.trajectory import NodeType

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "datasets"


def _inside_box(traj, tol):
    box, d = traj.config["params"]["box"], traj.mesh.dim
    lower, upper = np.asarray(box[:d]), np.asarray(box[d:])
    return (traj.positions >= lower - tol).all() and (traj.positions <= upper + tol).all()


def _inside_channel(traj, tol):
    q = traj.config["params"]
    x, y = traj.positions[..., 0], traj.positions[..., 1]
    inside = (y > 0) & (y <= q["length"])
    left = np.where(inside, q["amplitude"] * np.sin(q["omega1"] * y) * np.sin(q["omega2"] * y), 0.0)  # UMLS eq. 36
    return (x >= left - tol).all() and (x <= left + q["width"] + tol).all() and (y >= -q["outlet"] - tol).all()


def _beside_clamp(traj, tol):
    q = traj.config["params"]
    return (traj.positions[..., 0] >= -tol).all() and (traj.positions[..., 1] >= -q["drop"] - tol).all()


def _around_pin(traj, tol):
    """A plate on a pin at the origin: no node goes further from the pin than the farthest one starts."""
    reach = np.linalg.norm(traj.positions, axis=-1)
    return (reach <= reach[0].max() + tol).all()


CONTAINED = {"disks": _inside_box, "glyphs": _inside_box, "balls": _inside_box, "wavy_channel": _inside_channel,
             "cantilever": _beside_clamp, "press": _inside_box, "bracket": _inside_box, "press3d": _inside_box,
             "pendulum": _around_pin}


# the MPM families; the flow family's Eulerian data (no bodies, no energy diagnostics) is checked
# in test_flow_family.py
@pytest.mark.parametrize("family", sorted(f for f in FAMILIES if f != "shock_channel"))
def test_quick_variant_is_physical(family):
    dconfig = load_dataset_config(CONFIGS / f"{family}_quick.yaml")
    traj = simulate(trajectory_config(dconfig, "train", 1))
    fam = get_family(family)
    assert traj.mesh.dim == fam.DIM and traj.positions.shape[1:] == (traj.mesh.n_nodes, fam.DIM)
    assert np.isfinite(traj.positions).all() and np.isfinite(traj.velocities).all()
    mass = traj.diagnostics["mass"]
    np.testing.assert_allclose(mass, mass[0], rtol=1e-12)
    assert CONTAINED[family](traj, tol=0.5 * traj.config["params"]["mesh_size"])
    d = traj.diagnostics
    energy = d["kinetic_energy"] + d["elastic_energy"] + d["gravitational_energy"]
    scale = d["kinetic_energy"][0] + d["gravitational_energy"][0] - d["gravitational_energy"].min() + 1e-12
    if not getattr(fam, "DRIVEN", False):  # a driven family's moving obstacles do work on the bodies
        assert energy.max() - energy[0] <= 0.05 * scale  # no energy created beyond 5% of what is available
    assert fam.OBSTACLES == (traj.obstacle_nodes is not None and len(traj.obstacle_facets) > 0)
    assert traj.obstacle_facets.max() < len(traj.obstacle_nodes)
    node_type = np.full(traj.mesh.n_nodes, NodeType.FREE) if traj.node_type is None else traj.node_type
    clamped = node_type == NodeType.CLAMPED
    assert clamped.any() == fam.CLAMPED
    if fam.CLAMPED:  # held by the wall: they move far less than the rest of the body
        moved = np.linalg.norm(traj.positions - traj.positions[0], axis=-1).max(0)
        assert moved[clamped].max() < 0.1 * moved.max()
    if traj.body_id is not None:
        assert len(np.unique(traj.body_id)) == len(traj.config["params"].get("radii") or traj.config["params"]["chars"])


def test_sampling_is_seeded_and_differs_between_indices():
    dconfig = load_dataset_config(CONFIGS / "disks_quick.yaml")
    assert trajectory_config(dconfig, "train", 3) == trajectory_config(dconfig, "train", 3)
    assert trajectory_config(dconfig, "train", 3) != trajectory_config(dconfig, "train", 4)
    assert trajectory_config(dconfig, "train", 3) != trajectory_config(dconfig, "test", 3)


@pytest.mark.parametrize(("base", "grown", "factor"), [("bracket", "bracket_xl", 3), ("press_stiff", "press_stiff_xl", 2),
                                                      ("press_stiff_xl", "press_stiff_xxl", 1.25)])
def test_the_xl_datasets_only_add_training_trajectories(base, grown, factor):
    """bracket_xl, press_stiff_xl and press_stiff_xxl only add training
    trajectories: the trajectories each shares with its base are the same simulations (its config
    tells users to hard-link them), and the rest are new."""
    small, large = (load_dataset_config(CONFIGS / f"{name}.yaml") for name in (base, grown))
    assert {k: v for k, v in large.items() if k not in ("dataset", "splits")} == \
        {k: v for k, v in small.items() if k not in ("dataset", "splits")}
    assert large["splits"]["train"] == factor * small["splits"]["train"]
    for split in ("train", "valid", "test"):
        for k in (0, small["splits"][split] - 1):
            assert trajectory_config(large, split, k) == trajectory_config(small, split, k)
    assert trajectory_config(large, "train", small["splits"]["train"]) not in \
        [trajectory_config(small, "train", k) for k in range(small["splits"]["train"])]


def test_press_kinds_shares_press_deeps_test_split_and_trains_on_three_kinds():
    """press_kinds changes only what training shows: its test trajectories are press_deep's (so
    its results compare with press_deep's, and the files can be hard-linked)."""
    deep, kinds = (load_dataset_config(CONFIGS / f"{name}.yaml") for name in ("press_deep", "press_kinds"))
    for k in range(deep["splits"]["test"]):
        assert trajectory_config(kinds, "test", k) == trajectory_config(deep, "test", k)
    bodies = [trajectory_config(kinds, "train", k)["params"] for k in range(100)]
    letters = sum("char" in p and p.get("polygon") is None for p in bodies)
    assert 28 <= letters <= 52 and all(p["char"] in "ABCDEFHKLMNPRTVWXYZ" for p in bodies if p.get("polygon") is None)


def test_press_stiff_is_press_kinds_ten_times_stiffer_on_a_twice_finer_background():
    """press_stiff draws press_kinds' bodies and drives in every split, each E ten times larger,
    on a 3.75 mm background mesh; a draw the solver cannot run is replaced (redraws)."""
    kinds, stiff = (load_dataset_config(CONFIGS / f"{name}.yaml") for name in ("press_kinds", "press_stiff"))
    assert stiff["params"]["mesh_size"] == 0.00375 == kinds["params"]["mesh_size"] / 2
    assert stiff["redraws"] == 2 and kinds.get("redraws", 0) == 0
    for split, k in [("test", 0), ("test", 7), ("valid", 3), ("train", 0), ("train", 191)]:
        a, b = trajectory_config(kinds, split, k), trajectory_config(stiff, split, k)
        assert b["params"]["E"] == pytest.approx(10 * a["params"]["E"], rel=1e-12)
        same = {key: value for key, value in a["params"].items() if key not in ("E", "mesh_size")}
        assert {key: b["params"][key] for key in same} == same and b["seed"] == a["seed"]


def test_a_body_spacing_meshes_the_body_at_that_spacing():
    """The spacing ``params.body_size`` of a press body is the one it is meshed at (gmsh's element
    size: the mean edge within 25% of it), from 1.5 mm (2000 nodes) to 5 mm (a hundred or two); the
    bodies and spacings the retired press_multires drew (docs/experiments.md)."""
    from datagen.scenes.press import body_mesh, params

    stiff = load_dataset_config(CONFIGS / "press_stiff_xl.yaml")
    for k, spacing in ((0, 0.004886), (1, 0.004781), (3, 0.001545), (4, 0.002466)):
        p = params({**trajectory_config(stiff, "train", k)["params"], "body_size": spacing, "min_nodes": 0})
        mesh = body_mesh(p)
        edges = mesh.cells[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        mean_edge = np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1).mean()
        assert 0.75 * p["body_size"] < mean_edge < 1.25 * p["body_size"]


def test_press_quickstart_draws_polygons_and_strokes_afresh_in_every_split():
    """The quickstart's bodies are random polygons and strokes in every split (no letters), softer
    and pressed deeper than press_kinds', and no test shape is a training one."""
    dconfig = load_dataset_config(CONFIGS / "press_quickstart.yaml")
    shapes = {split: [trajectory_config(dconfig, split, k)["params"] for k in range(dconfig["splits"][split])]
              for split in ("train", "test")}
    for split, bodies in shapes.items():
        assert all(p.get("polygon") is not None for p in bodies), split
        assert all(1e6 <= p["E"] <= 5e6 and 0.05 <= p["speed"] <= 0.08 for p in bodies), split
    train = {str(p["polygon"]) for p in shapes["train"]}
    assert not any(str(p["polygon"]) in train for p in shapes["test"])


def test_disks_start_apart_and_inside_the_box():
    dconfig = load_dataset_config(CONFIGS / "disks.yaml")
    for index in range(50):
        p = trajectory_config(dconfig, "train", index)["params"]
        c, r = np.asarray(p["centers"]), np.asarray(p["radii"])
        assert 2 <= len(r) <= 3
        assert ((c - r[:, None]) >= 0).all() and ((c + r[:, None]) <= 1).all()
        gaps = np.linalg.norm(c[:, None] - c[None], axis=-1) - r[:, None] - r[None]
        assert (gaps[~np.eye(len(r), dtype=bool)] > 0).all()


def test_glyph_test_letters_are_never_in_training():
    dconfig = load_dataset_config(CONFIGS / "glyphs.yaml")
    train = {c for i in range(60) for s in ("train", "valid") for c in trajectory_config(dconfig, s, i)["params"]["chars"]}
    test = {c for i in range(60) for c in trajectory_config(dconfig, "test", i)["params"]["chars"]}
    assert test <= set(dconfig["ranges"]["test_chars"]) and not train & test
    bad = {**dconfig, "ranges": {**dconfig["ranges"], "test_chars": "GA"}}
    with pytest.raises(ConfigError, match="ranges.test_chars shares 'A'"):
        trajectory_config(bad, "test", 0)


@pytest.mark.parametrize(("ranges", "message"), [
    ({"radius": [0.3, 0.1]}, r"ranges.radius must be a number or \[low, high\] with low <= high"),
    ({"radious": [0.1, 0.2]}, "unknown config key 'ranges.radious'; family 'disks' accepts: E, box, count,"),
    ({"radius": [0.45, 0.5]}, "ranges.radius: could not place"),
    ({"E": [-1.0, 2.0]}, "ranges.E must be positive"),
])
def test_bad_ranges_name_the_key(ranges, message):
    dconfig = load_dataset_config(CONFIGS / "disks_quick.yaml")
    with pytest.raises(ConfigError, match=message):
        trajectory_config({**dconfig, "ranges": {**dconfig["ranges"], **ranges}}, "train", 0)


def test_unknown_family_lists_the_choices():
    with pytest.raises(ConfigError, match="unknown family 'disk'.*choose one of balls, bracket, cantilever, disks, "
                       "glyphs, pendulum, press, press3d, shock_channel, wavy_channel"):
        get_family("disk")


def test_wavy_channel_body_can_be_any_glyph():
    t = simulate({"scene": "wavy_channel", "params": {"shape": "glyph:B", "radius": 0.5, "body_size": 0.06},
                  "output": {"frames": 3}})
    holes = t.mesh.n_components - (t.mesh.n_nodes - len(t.mesh.edges) + t.mesh.n_cells)
    assert holes == 2 and np.isfinite(t.positions).all()
    extent = np.ptp(t.mesh.nodes, axis=0)
    assert extent.max() == pytest.approx(1.0, rel=1e-9)  # fits in 2 * radius
    np.testing.assert_allclose((t.mesh.nodes.min(0) + t.mesh.nodes.max(0)) / 2, [1.0, 11.25], atol=1e-9)
    with pytest.raises(ConfigError, match="params.shape must be one of .* or 'glyph:<text>'"):
        simulate({"scene": "wavy_channel", "params": {"shape": "glyph:  "}})
