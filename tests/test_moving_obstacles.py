"""Moving obstacles (kinematic, prescribed motion): trajectory format v2, the subdivision map that
moves the graph's obstacle nodes, their next-step velocity as a model input in training and in
rollouts, lean obstacles that follow them, and static data left exactly as it was."""

import h5py
import numpy as np
import pytest
import torch

from bsms.data import FrameDataset, GraphOptions, NodeType, Scenario
from bsms.graph.obstacles import subdivide_facets, subdivide_obstacles
from bsms.rollouts.rollout import rollout
from datagen.dataset import DatasetError, content_digest, is_complete, load, save
from datagen.metadata import dataset_metadata
from datagen.scenes.base import lattice, lattice_mesh
from datagen.trajectory import Trajectory

FRAME_DT = 0.05
# height of the indenter's tip over the frames: it comes down from far above the strip, presses
# close to it and goes back up (the velocity reverses between frames 6 and 7)
TIP = np.array([1.2, 1.0, 0.8, 0.6, 0.5, 0.35, 0.3, 0.35, 0.5, 0.6, 0.8, 1.0])
INDENTER = np.array([[0.2, 0.05], [0.5, 0.0], [0.8, 0.05]])  # a shallow V, tip at the origin
FLOOR = np.array([[-0.2, -0.1], [1.2, -0.1]])


def strip():
    """A 1 x 0.2 strip of 10 x 2 lattice points (edges 0.1), its left column clamped."""
    points, counts, _ = lattice([0.0, 0.0], [1.0, 0.2], 0.1)
    mesh = lattice_mesh(points, counts)
    node_type = np.where(mesh.nodes[:, 0] < 0.1, NodeType.CLAMPED, NodeType.FREE).astype(np.int64)
    return mesh, node_type


def make_trajectory(moving: bool = True) -> Trajectory:
    """The strip sagging a little under an indenter (``moving``) or under nothing that moves, with
    a static floor below it; obstacle nodes are the indenter's 3 then the floor's 2."""
    mesh, node_type = strip()
    times = FRAME_DT * np.arange(len(TIP))
    free = node_type == NodeType.FREE
    sag = np.zeros((len(times), mesh.n_nodes, 2))
    sag[:, free, 1] = -0.02 * np.sin(3 * times)[:, None] * mesh.nodes[free, 0]
    positions = mesh.nodes + sag
    velocities = np.gradient(positions, FRAME_DT, axis=0)
    velocities[:, ~free] = 0.0
    obstacle_nodes = np.concatenate([INDENTER + [0, TIP[0]], FLOOR])
    path = None
    if moving:
        path = np.repeat(obstacle_nodes[None], len(times), axis=0)
        path[:, :3, 1] = INDENTER[:, 1] + TIP[:, None]
    return Trajectory(
        mesh=mesh, positions=positions, velocities=velocities, times=times, diagnostics={}, wall_time=0.0,
        config={"scene": "hand_made", "params": {}}, dt=FRAME_DT / 4, substeps=4, n_particles=mesh.n_nodes,
        node_type=node_type, body_id=np.zeros(mesh.n_nodes, np.int64), obstacle_nodes=obstacle_nodes,
        obstacle_facets=np.array([[0, 1], [1, 2], [3, 4]]), obstacle_positions=path,
    )


# ----------------------------------------------------------------------------- file format
def test_format_v2_round_trip_is_bit_exact(tmp_path):
    trajectory = make_trajectory()
    path = save(tmp_path / "moving.h5", trajectory)
    back = load(path)
    assert back.obstacle_positions.dtype == np.float64
    np.testing.assert_array_equal(back.obstacle_positions, trajectory.obstacle_positions)
    np.testing.assert_array_equal(back.obstacle_nodes, trajectory.obstacle_nodes)
    np.testing.assert_array_equal(back.positions, trajectory.positions)
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == 2 and "frames/obstacle_positions" in f
    assert is_complete(path)
    assert content_digest(path) == content_digest(save(tmp_path / "again.h5", trajectory))
    assert content_digest(path) != content_digest(save(tmp_path / "static.h5", make_trajectory(moving=False)))
    static = load(tmp_path / "static.h5")
    assert static.obstacle_positions is None
    with h5py.File(tmp_path / "static.h5", "r") as f:
        assert "frames/obstacle_positions" not in f, "static obstacles store no positions per frame"


def test_a_version_1_file_still_loads(tmp_path):
    """Version 1 was the same layout without the obstacle positions."""
    path = save(tmp_path / "v1.h5", make_trajectory())
    with h5py.File(path, "r+") as f:
        del f["frames/obstacle_positions"]
        f.attrs["format_version"] = 1
    back = load(path)
    assert back.obstacle_positions is None and is_complete(path)
    np.testing.assert_array_equal(back.obstacle_nodes, make_trajectory().obstacle_nodes)
    with h5py.File(path, "r+") as f:
        f["frames/obstacle_positions"] = make_trajectory().obstacle_positions
    with pytest.raises(DatasetError, match=r"v1\.h5 holds 'frames/obstacle_positions' but says format version 1"):
        load(path)


def test_bad_obstacle_positions_are_reported_by_file_name(tmp_path):
    trajectory = make_trajectory()
    path = save(tmp_path / "short.h5", trajectory)
    with h5py.File(path, "r+") as f:
        del f["frames/obstacle_positions"]
        f["frames/obstacle_positions"] = trajectory.obstacle_positions[:-1]
    with pytest.raises(DatasetError, match=r"short\.h5: 'frames/obstacle_positions' has shape \(11, 5, 2\), "
                                           r"expected \(12, 5, 2\)"):
        load(path)
    assert not is_complete(path)
    path = save(tmp_path / "nan.h5", trajectory)
    with h5py.File(path, "r+") as f:
        f["frames/obstacle_positions"][4, 0, 1] = np.nan
    with pytest.raises(DatasetError, match=r"nan\.h5: 'frames/obstacle_positions' holds NaN or inf from frame 4"):
        load(path)
    trajectory.obstacle_positions = trajectory.obstacle_positions[:, :4]
    with pytest.raises(ValueError, match=r"obstacle_positions has shape \(12, 4, 2\), expected \(12, 5, 2\)"):
        save(tmp_path / "never.h5", trajectory)
    assert not (tmp_path / "never.h5").exists()


def test_dataset_bounds_hold_the_moving_obstacles(tmp_path):
    save(tmp_path / "train" / "00000.h5", make_trajectory())
    meta = dataset_metadata(tmp_path, {"splits": {"train": 1}, "dataset": "d", "family": "f"})
    assert meta["format_version"] == 2
    assert meta["bounds"]["upper"][1] == pytest.approx(TIP.max() + 0.05, abs=1e-12)
    assert meta["bounds"]["lower"] == pytest.approx([-0.2, -0.1], abs=1e-12)


# ----------------------------------------------------------------------------- subdivision map
def rotation(dim: int, angle: float) -> np.ndarray:
    r = np.eye(dim)
    r[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    return r


@pytest.mark.parametrize("dim", [2, 3])
def test_the_subdivision_map_moves_subdivided_nodes_exactly(dim):
    if dim == 2:
        nodes, facets = np.concatenate([INDENTER, FLOOR]), np.array([[0, 1], [1, 2], [3, 4]])
    else:  # a unit square of two triangles and a tilted triangle sharing an edge with it
        nodes = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 1.6, 0.7]], float)
        facets = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 4]])
    sub = subdivide_obstacles(nodes, facets, 0.2)
    fine_nodes, fine_facets = subdivide_facets(nodes, facets, 0.2)
    assert np.array_equal(sub.nodes, fine_nodes) and np.array_equal(sub.facets, fine_facets)
    assert sub.weights.shape == (len(fine_nodes), len(nodes)) and len(fine_nodes) > 2 * len(nodes)
    assert np.array_equal(sub.moved(nodes), fine_nodes), "at rest: the stored geometry's points, bit for bit"
    np.testing.assert_allclose(sub.weights @ nodes, fine_nodes, rtol=0, atol=1e-15)  # measured: 1.1e-16, 0
    np.testing.assert_allclose(sub.weights.sum(axis=1), 1.0, rtol=0, atol=1e-15)
    assert (sub.weights.data >= 0).all()
    frames = []
    for k, angle in enumerate((0.0, 0.4, -1.3)):
        turn, shift = rotation(dim, angle), np.linspace(0.3, -0.7, dim) * k
        frames.append((nodes @ turn.T + shift, fine_nodes @ turn.T + shift))
    moved = sub.moved(np.stack([f for f, _ in frames]))  # (T, M, d) at once
    assert moved.shape == (3, len(fine_nodes), dim)
    np.testing.assert_allclose(moved, np.stack([g for _, g in frames]), rtol=0, atol=2e-15)  # measured: 4.4e-16 (2D, 3D)
    with pytest.raises(ValueError, match=f"give \\(..., {len(nodes)}, {dim}\\) positions"):
        sub.moved(nodes[:-1])


def test_scenario_positions_place_moving_obstacles_and_keep_static_ones_at_rest():
    trajectory = make_trajectory()
    scenario = Scenario.from_trajectory(trajectory, GraphOptions(levels=2))
    assert scenario.obstacle_geometry is not None and scenario.n_nodes - scenario.n_body == 13
    static = scenario.positions(trajectory.positions)
    n = scenario.n_body
    assert np.array_equal(static[:, :n], trajectory.positions), "body rows are the trajectory's"
    assert np.array_equal(static[:, n:], np.broadcast_to(scenario.rest_pos[n:], static[:, n:].shape)), "obstacles at rest"
    moving = scenario.positions(trajectory.positions, trajectory.obstacle_positions)
    assert np.array_equal(moving[:, : scenario.n_body], trajectory.positions)
    assert np.array_equal(moving[0], static[0]), "frame 0 is the rest geometry, bit for bit"
    rise = moving[:, scenario.n_body:] - scenario.rest_pos[scenario.n_body:]
    on_indenter = np.abs(rise[:, :, 1] - (TIP - TIP[0])[:, None]) < 1e-14
    assert on_indenter.all(axis=0).sum() == 5, "the indenter's 5 subdivided nodes follow it"
    assert (rise[:, ~on_indenter.all(axis=0)] == 0).all(), "the floor's 8 stay put"
    with pytest.raises(ValueError, match="for the same frames"):
        scenario.positions(trajectory.positions[:3], trajectory.obstacle_positions[:4])


# ----------------------------------------------------------------------------- training samples
def kinematic_rows(graph, scenario_nodes: np.ndarray) -> np.ndarray:
    """Rows of ``graph`` holding the given scenario nodes."""
    nodes = graph.scenario_nodes.numpy()
    return np.flatnonzero(np.isin(nodes, scenario_nodes))


def indenter_nodes(scenario) -> np.ndarray:
    """Scenario nodes of the subdivided indenter: those placed by its 3 stored nodes alone."""
    weights = scenario.obstacle_geometry.weights.toarray()
    return scenario.n_body + np.flatnonzero(weights[:, 3:].sum(axis=1) == 0)


def test_training_samples_see_obstacles_where_they_are_and_where_they_go(tmp_path):
    trajectory = make_trajectory()
    dataset = FrameDataset([save(tmp_path / "t.h5", trajectory)], GraphOptions(levels=2, obstacle_margin=None))
    scenario = dataset.scenarios[0]
    moved = scenario.obstacle_geometry.moved(trajectory.obstacle_positions)  # (T, 13, 2)
    obstacles = np.arange(scenario.n_body, scenario.n_nodes)
    clamped = np.flatnonzero(scenario.node_type == NodeType.CLAMPED)
    for t in range(len(dataset)):
        graph = dataset[t]
        rows = kinematic_rows(graph, obstacles)
        assert len(rows) == 13
        np.testing.assert_array_equal(graph.pos[rows].numpy(), moved[t].astype(np.float32))
        expected = (moved[t + 1] - moved[t]) / FRAME_DT
        np.testing.assert_allclose(graph.velocity[rows].numpy(), expected, rtol=1e-6, atol=1e-6)
        assert (graph.velocity[kinematic_rows(graph, clamped)] == 0).all()
    # at frame 6 the tip is lowest: its velocity is already the coming step's, upwards
    indenter = indenter_nodes(scenario)
    assert len(indenter) == 5
    assert dataset[6].velocity[kinematic_rows(dataset[6], indenter), 1].numpy() == pytest.approx(np.ones(5))
    assert dataset[5].velocity[kinematic_rows(dataset[5], indenter), 1].numpy() == pytest.approx(-np.ones(5))


def test_lean_graphs_take_the_indenter_only_when_it_is_near(tmp_path):
    dataset = FrameDataset([save(tmp_path / "t.h5", make_trajectory())], GraphOptions(levels=3))
    scenario = dataset.scenarios[0]
    indenter = indenter_nodes(scenario)
    counts, positions = [], dataset.positions[0]
    for t in range(len(dataset)):
        graph = dataset[t]
        counts.append(len(kinematic_rows(graph, indenter)))
        gap = np.linalg.norm(positions[t, indenter][:, None] - positions[t, : scenario.n_body], axis=-1).min()
        near = gap <= scenario.contact_radius  # the default reach (obstacle_margin 0)
        assert abs(gap - scenario.contact_radius) > 0.04, "no frame is a close call"
        receivers = graph.scenario_nodes[graph.contact_index_0[1]].numpy()
        assert (counts[-1] > 0) == near and np.isin(receivers, indenter).any() == near, (t, counts[-1], gap)
    assert counts[:5] == [0] * 5 and counts[5:8] == [5, 5, 5] and counts[8:] == [0] * 3, counts


def test_static_obstacles_give_the_same_graphs_as_before(tmp_path):
    """Old inputs: every node's velocity the backward difference (frame 0: the stored one),
    obstacles at rest. Static clamped and obstacle nodes have 0 either way, bit for bit -- also
    from a version 2 file whose obstacle positions stand still."""
    trajectory = make_trajectory(moving=False)
    still = make_trajectory(moving=False)
    still.obstacle_positions = np.repeat(still.obstacle_nodes[None], len(still.times), axis=0)
    files = [save(tmp_path / "static.h5", trajectory), save(tmp_path / "still.h5", still)]
    dataset = FrameDataset(files, GraphOptions(levels=3))
    for k in range(2):
        scenario = dataset.scenarios[k]
        positions = scenario.full(trajectory.positions)
        velocities = np.concatenate([scenario.full(trajectory.velocities[:1], 0.0), np.diff(positions, axis=0) / FRAME_DT])
        for t in range(len(trajectory.times) - 1):
            new = dataset[k * (len(trajectory.times) - 1) + t]
            old = scenario.graph(positions[t], velocities[t], velocities[t + 1] - velocities[t])
            assert set(new.keys()) == set(old.keys())
            for key in old.keys():
                assert torch.equal(torch.as_tensor(new[key]), torch.as_tensor(old[key])), (k, t, key)


# ----------------------------------------------------------------------------- rollouts
class Recorder(torch.nn.Module):
    """A 'model' that changes nothing and records the velocities and nodes of every graph it sees."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(()))
        self.seen = []

    def velocity_change(self, graph, precision="f32"):
        self.seen.append((graph.scenario_nodes.numpy().copy(), graph.velocity.double().numpy().copy()))
        return torch.zeros_like(graph.velocity)


def test_rollouts_prescribe_the_obstacle_path_and_show_the_model_its_velocity(tmp_path):
    trajectory = make_trajectory()
    options = GraphOptions(levels=2, obstacle_margin=None)
    scenario = Scenario.from_trajectory(trajectory, options)
    known = scenario.positions(trajectory.positions, trajectory.obstacle_positions)
    initial = scenario.full(trajectory.velocities[:1], 0.0)[0]
    model = Recorder()
    steps = len(TIP) - 1
    result = rollout(model, scenario, known[0], initial, steps, known, warmup=0)
    kinematic = scenario.kinematic
    assert np.array_equal(result.positions[:, kinematic], known[:, kinematic]), "exactly on the prescribed path"
    assert len(model.seen) == steps
    dataset = FrameDataset([save(tmp_path / "t.h5", trajectory)], options)
    for t, (nodes, velocity) in enumerate(model.seen):
        rows = np.flatnonzero(kinematic[nodes])
        expected = (known[t + 1, nodes[rows]] - known[t, nodes[rows]]) / FRAME_DT
        np.testing.assert_allclose(velocity[rows], expected, rtol=0, atol=1e-5)
        trained = dataset[t]  # the same input as the training sample of that frame
        assert np.array_equal(trained.scenario_nodes.numpy(), nodes)
        np.testing.assert_array_equal(trained.velocity[rows].double().numpy(), velocity[rows])
    tip = np.flatnonzero(np.isin(model.seen[6][0], indenter_nodes(scenario)))
    assert model.seen[6][1][tip, 1] == pytest.approx(np.ones(5)), "at the lowest point it already goes up"
    # without known positions kinematic nodes stay where they start, seen standing still
    still = rollout(model, scenario, known[0], initial, 3, None, warmup=0)
    assert np.array_equal(still.positions[:, kinematic], np.repeat(known[:1, kinematic], 4, axis=0))
    assert all((velocity[kinematic[nodes]] == 0).all() for nodes, velocity in model.seen[-3:])


# ----------------------------------------------------------------------------- infer and pictures
def test_infer_prescribes_the_scene_obstacle_path_where_the_scene_has_one():
    from types import SimpleNamespace

    from bsms.infer import _obstacle_path

    trajectory = make_trajectory()
    scene = SimpleNamespace(obstacle_nodes=trajectory.obstacle_nodes,
                            obstacle_positions=lambda times: trajectory.obstacle_positions[: len(times)])
    path = _obstacle_path(scene, 5, FRAME_DT)
    assert np.array_equal(path, trajectory.obstacle_positions[:6])
    assert _obstacle_path(SimpleNamespace(obstacle_nodes=trajectory.obstacle_nodes), 5, FRAME_DT) is None, \
        "a scene that cannot say where its obstacles go keeps them static"
    assert _obstacle_path(SimpleNamespace(obstacle_nodes=trajectory.obstacle_nodes,
                                          obstacle_positions=lambda times: None), 5, FRAME_DT) is None


def test_rollout_gifs_draw_obstacles_where_they_are_in_each_frame(tmp_path):
    from bsms.rollouts.viz import rollout_gif

    trajectory = make_trajectory()
    body, facets = trajectory.positions[:4], trajectory.obstacle_facets
    gif = rollout_gif(trajectory.mesh.cells, body, tmp_path / "moving.gif", truth=body,
                      obstacles=(trajectory.obstacle_positions[:4], facets), frame_dt=FRAME_DT)
    assert gif.stat().st_size > 0
    with pytest.raises(ValueError, match=r"for each of the 4 frames drawn"):
        rollout_gif(trajectory.mesh.cells, body, tmp_path / "short.gif",
                    obstacles=(trajectory.obstacle_positions[:3], facets))
