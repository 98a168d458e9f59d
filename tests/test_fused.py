"""Many eulerian substeps in one compiled call (datagen.mpm.fused.advance) against the Python step,
feature by feature: walls (sticky with folded and overwritten mirror ghosts, slip, separating with
friction), clamps, colliders of every shape, gravity, damping, every elastic material, FLIP and PIC,
F-bar, the non-negative kernel of boundary cells; the errors; the thread count; what it leaves to
the Python step."""

import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch

from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mpm import Model, SimulationError, State, advance, cfl_time_step, fused, step
from datagen.mpm.boundary import Clamp, Wall
from datagen.mpm.colliders import Collider, Path
from datagen.mpm.kernels import MeshTables, umls_kernel
from datagen.mpm.locate import barycentric
from datagen.mpm.materials import NeoHookean
from datagen.scenes.base import Scene, lattice, lattice_mesh, make_material, vertex_volumes
from datagen.simulation import SOLVER_DEFAULTS, build_solver_model, simulate

pytestmark = pytest.mark.usefixtures("one_thread")


def grid_domain(lower, upper, h):
    """A structured simplex mesh with nodes every h on the box [lower, upper] (no gmsh)."""
    counts = np.round((np.asarray(upper, float) - lower) / h).astype(int) + 1
    axes = [np.linspace(lo, hi, n) for lo, hi, n in zip(lower, upper, counts, strict=True)]
    return lattice_mesh(np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], 1), tuple(counts))


def floor(c, n):
    return n[:, -1] < -0.5


def not_floor(c, n):
    return n[:, -1] >= -0.5


def left(points):
    return points[:, 0] <= 0.05 + 1e-9


# A block on the floor of a box (sticky floor or not, the other walls as given), pressed by a
# collider moving down into it, under gravity; each case switches on other features.
CASES = {
    "2d neo-hookean flip, folded floor, separating walls, disk, damping": dict(
        dim=2, material="neo_hookean", walls=[Wall("sticky", floor), Wall("separating", not_floor, 0.5)],
        collider=("disk", (0.12,)), damping=50.0),
    "2d linear pic, slip walls, clamp, box": dict(
        dim=2, material="linear", walls=[Wall("slip", lambda c, n: np.ones(len(c), bool))], clamps=[Clamp(left)],
        collider=("box", (0.1, 0.05)), transfer="pic"),
    "2d fixed corotated, overwritten mirrors, wedge, f-bar": dict(
        dim=2, material="fixed_corotated", walls=[Wall("sticky", floor, fold=False), Wall("separating", not_floor)],
        collider=("wedge", (0.1, 0.1)), fbar=True),
    "3d neo-hookean flip, folded floor, sphere": dict(
        dim=3, material="neo_hookean", walls=[Wall("sticky", floor), Wall("separating", not_floor, 0.3)],
        collider=("sphere", (0.12,))),
    "3d fixed corotated pic, box, f-bar, damping": dict(
        dim=3, material="fixed_corotated", walls=[Wall("sticky", floor), Wall("slip", not_floor)],
        collider=("box", (0.1, 0.1, 0.05)), transfer="pic", fbar=True, damping=20.0),
}


def case_model(dim, material, walls=(), clamps=(), collider=None, transfer="flip", fbar=False, damping=0.0,
               extra_layer=True, h=0.1, reference="eulerian"):
    """(model, state, dt) of a case: a 0.4 (x 0.4) x 0.3 block resting on the floor of a 1 (x 1) x 0.8 box."""
    lower = [0.3] * (dim - 1) + [0.0]
    upper = [0.7] * (dim - 1) + [0.3]
    domain = grid_domain([0.0] * dim, [1.0] * (dim - 1) + [0.8], h)
    points, counts, _ = lattice(lower, upper, h / 2 if dim == 2 else h / 1.5)
    body = lattice_mesh(points, counts)
    colliders = []
    if collider is not None:
        shape, size = collider
        # the path starts just above the block, off the lattice: no node lies exactly on the collider's
        # surface, where a contact test could go either way at round-off
        lowest = size[0] if shape in ("disk", "sphere") else (0.0 if shape == "wedge" else size[-1])
        start = [0.5037] * (dim - 1) + [0.3013 + lowest]
        end = list(start)
        end[-1] -= 0.5
        colliders = [Collider(shape, size, Path([0.0, 1.0], [start, end]), 0.3)]
    scene = Scene(domain=domain, body=body, x=body.nodes.copy(), v=np.zeros_like(body.nodes),
                  volume=vertex_volumes(body), materials=[(make_material(material, 2e4, 0.3, 1000.0), None)],
                  tracked=np.arange(body.n_nodes), walls=list(walls), clamps=list(clamps),
                  gravity=np.array([0.0] * (dim - 1) + [-9.81]), colliders=colliders, damping=damping)
    solver = {**SOLVER_DEFAULTS, "transfer": transfer, "fbar": fbar, "extra_layer": extra_layer,
              "reference": reference}
    model, state = build_solver_model(scene, solver)
    return model, state, cfl_time_step(model, state, 0.3)


def python_steps(model, state, dt, n):
    for _ in range(n):
        state = step(model, state, dt)
    return state


def assert_same_cells(model, got, expected):
    """The containing cells agree, except for particles on a face two cells share (the lattice
    particles of the 3D cases lie on the mesh's diagonal planes), which both searches may assign
    to either cell; the UMLS kernel is continuous there, so the states still agree."""
    differ = (got.cell != expected.cell).nonzero()[:, 0]
    assert len(differ) < 0.1 * len(got.cell)
    for cells in (got.cell[differ], expected.cell[differ]):
        inside = barycentric(model.background.locator, cells, got.x[differ]).min(1).values
        assert len(differ) == 0 or float(inside.min()) >= -1e-10


def gap(a, b) -> dict:
    return {name: float((getattr(a, name) - getattr(b, name)).abs().max()) for name in ("x", "v", "F")}


@pytest.mark.parametrize("name", list(CASES))
def test_compiled_substeps_equal_the_python_step(name):
    model, state, dt = case_model(**CASES[name])
    assert fused.applies(model, state)
    n = 60 if model.dim == 2 else 30  # the collider reaches the block after about 20 steps
    expected = python_steps(model, state, dt, n)
    got = advance(model, state, dt, n)
    assert got.step == expected.step == n and got.time == expected.time
    assert_same_cells(model, got, expected)
    # measured <= 3.3e-16 m in x, 3.7e-15 m/s in v, 1.3e-15 in F over all cases
    assert gap(got, expected)["x"] < 3e-15 and gap(got, expected)["v"] < 3e-14 and gap(got, expected)["F"] < 1e-14
    # every feature of the case acts: without the collider, or without the walls (the block then
    # falls out of the box), the result differs
    for lesser in (replace(model, colliders=()), replace(model, conditions=())):
        try:
            assert gap(advance(lesser, state, dt, n), got)["x"] > 1e-7
        except SimulationError as error:
            assert "left the mesh" in str(error)


def test_the_thread_count_does_not_change_the_result():
    model, state, dt = case_model(**CASES["2d neo-hookean flip, folded floor, separating walls, disk, damping"])
    one = advance(model, state, dt, 40)
    torch.set_num_threads(2)  # the one_thread fixture restores the count after the test
    two = advance(model, state, dt, 40)
    assert all(torch.equal(getattr(one, k), getattr(two, k)) for k in ("x", "v", "F", "cell"))


def test_boundary_cells_get_the_non_negative_kernel_as_in_python():
    """Without the extra layer the MLS weights of boundary cells go negative; the compiled substeps
    replace them by the closest non-negative kernel, as the Python step does."""
    model, state, dt = case_model(2, "neo_hookean", [Wall("separating", floor)], extra_layer=False)
    state = replace(state, x=state.x - torch.tensor([0.0, 0.02], dtype=torch.float64))  # 5 mm above the mesh's edge
    plain = umls_kernel(model.background, state.x, nonnegative=False)
    assert int((plain.weight < 0).any(1).sum()) >= 6  # measured 8 of 48 particles
    expected, got = python_steps(model, state, dt, 30), advance(model, state, dt, 30)
    assert gap(got, expected)["x"] < 1e-15 and gap(got, expected)["v"] < 5e-15  # measured 1.1e-16, 5.0e-16


def test_a_lost_particle_raises_the_python_steps_error():
    model, state, dt = case_model(2, "neo_hookean")
    v = state.v.clone()
    v[0] = torch.tensor([0.0, 4.0 / (20 * dt)])  # leaves the 1 m box within 20 steps
    state = replace(state, v=v)
    with pytest.raises(SimulationError) as expected:
        python_steps(model, state, dt, 40)
    with pytest.raises(SimulationError) as got:
        advance(model, state, dt, 40)
    assert str(got.value) == str(expected.value) and "1 of 48 particles left the mesh" in str(got.value)


def test_a_non_finite_state_raises_the_python_steps_error():
    model, state, dt = case_model(2, "neo_hookean")
    F = state.F.clone()
    F[5] = torch.tensor([[1.0, 0.0], [0.0, -1.0]])  # det F < 0: ln J is NaN
    state = replace(state, F=F)
    with pytest.raises(SimulationError, match="non-finite") as expected:
        step(model, state, dt)
    with pytest.raises(SimulationError) as got:
        advance(model, state, dt, 10)
    assert str(got.value) == str(expected.value)


@pytest.mark.parametrize("change", [
    dict(transfer="apic"), dict(transfer="musl"), dict(kernel="linear"), dict(grips=("grip",)), dict(materials="fluid"),
])
def test_what_is_not_compiled_steps_in_python(change):
    model, state, dt = case_model(2, "neo_hookean", [Wall("sticky", floor)])
    if "grips" in change:
        from datagen.mpm import Grip
        change = {"grips": (Grip(torch.arange(3), lambda t: (0.0, 0.1)),)}
    if change.get("materials") == "fluid":
        change = {"materials": ((make_material("fluid", 2e4, 0.3, 1000.0), None),)}
    model = replace(model, **change)
    assert not fused.applies(model, state)
    expected, got = python_steps(model, state, dt, 5), advance(model, state, dt, 5)
    assert all(torch.equal(getattr(got, k), getattr(expected, k)) for k in ("x", "v", "F")) and got.step == 5


def test_bsms_fused_0_switches_it_off(monkeypatch):
    model, state, dt = case_model(2, "neo_hookean")
    assert fused.applies(model, state)
    monkeypatch.setenv("BSMS_FUSED", "0")
    assert not fused.applies(model, state)
    assert torch.equal(advance(model, state, dt, 3).x, python_steps(model, state, dt, 3).x)


def test_collider_times_follow_the_python_clock():
    """Each substep sees its collider where the Python step would: at t_k = t_0 + dt + ... + dt."""
    model, state, dt = case_model(**CASES["2d neo-hookean flip, folded floor, separating walls, disk, damping"])
    state = replace(state, time=-17 * dt)  # a settling pre-roll's clock, crossing the path's start at 0
    (centre, velocity), = fused._collider_paths(model, state.time, dt, 40)
    t = state.time
    for k in range(40):
        path = model.colliders[0].path
        assert np.array_equal(centre[k], path.position(t)) and np.array_equal(velocity[k], path.velocity(t, t + dt))
        t = t + dt
    assert math.isclose(t, 23 * dt, rel_tol=1e-12)


def test_a_press_trajectory_equals_the_one_of_python_steps(monkeypatch):
    """A bonded letter settled under gravity and pressed by a box through simulate(): the frames,
    made by the compiled substeps, equal those of one Python step per substep to round-off."""
    config = {"scene": "press", "params": {"E": 2e4, "body_size": 0.01, "mesh_size": 0.02, "size": 0.12, "char": "A",
                                           "indenter": "box", "indenter_size": [0.03, 0.01], "gap": 0.001,
                                           "speed": 0.1, "base": "bonded", "damping": 100.0, "settle_time": 0.02},
              "solver": {"cfl": 0.5, "threads": 1}, "output": {"frames": 4, "frame_interval": 0.01}}
    compiled = simulate(config)
    monkeypatch.setenv("BSMS_FUSED", "0")
    python = simulate(config)
    motion = np.abs(python.positions[-1] - python.positions[0]).max()
    assert motion > 1e-3  # pressed by about 3 mm
    assert np.abs(compiled.positions - python.positions).max() < 3e-16  # measured 2.8e-17 m
    np.testing.assert_array_equal(compiled.times, python.times)


def test_the_plans_z_order_renumbering_changes_no_bit(monkeypatch):
    """The compiled substeps renumber nodes and cells along a Z-order curve for memory locality;
    slot and bucket orders are kept, so the result is bitwise that of the mesh's own numbering."""
    model, state, dt = case_model(**CASES["3d neo-hookean flip, folded floor, sphere"])
    order = fused._z_order(model.node_positions.numpy())
    assert torch.equal(order.sort().values, torch.arange(model.n_nodes)) and not torch.equal(order, order.sort().values)
    renumbered = advance(model, state, dt, 20)
    monkeypatch.setattr(fused, "_z_order", lambda points: torch.arange(len(points)))
    fused._plans.clear()
    plain = advance(model, state, dt, 20)
    fused._plans.clear()
    assert all(torch.equal(getattr(renumbered, k), getattr(plain, k)) for k in ("x", "v", "F", "cell"))


@pytest.mark.parametrize("reference", ["total", "adaptive"])
@pytest.mark.parametrize("name", list(CASES))
def test_a_ulmpm_substeps_equal_the_python_step(name, reference):
    """The A-ULMPM modes: between updates of the reference configuration the compiled substeps
    move the nodes, act with the wall planes on the moved nodes (the floor's nodes are in the
    kernel's support from the start, so the planes act every step) and the pinned conditions, and
    stop after a substep that makes an update due; the Python step rebuilds."""
    model, state, dt = case_model(**CASES[name], reference=reference)
    assert fused.applies(model, state) and model.wall_planes
    n = 60 if model.dim == 2 else 30
    expected, got = python_steps(model, state, dt, n), advance(model, state, dt, n)
    # measured <= 2.5e-16 m in x, 3.1e-15 m/s in v, 8.9e-16 in F; the same rebuilds (total 1, adaptive 4-38)
    assert gap(got, expected)["x"] < 3e-15 and gap(got, expected)["v"] < 3e-14 and gap(got, expected)["F"] < 1e-14
    assert got.reference.rebuilds == expected.reference.rebuilds and got.step == n and got.time == expected.time
    assert float((got.reference.nodes - expected.reference.nodes).abs().max()) < 1e-15
    assert abs(got.reference.drift - expected.reference.drift) < 1e-15


def test_the_contact_trigger_fires_in_the_compiled_substeps():
    """Two blocks flying at each other in the adaptive mode (tests/test_reference_modes.py): the
    compiled substeps detect the approach and hand the rebuild to Python, so they collide."""
    xa, _, spacing = lattice([0.3, 0.9], [0.5, 1.1], 0.025)
    x = np.concatenate([xa, xa + np.array([0.5, 0.0])])
    v = np.zeros_like(x)
    v[: len(xa), 0], v[len(xa):, 0] = 1.5, -1.5
    tables = MeshTables.build(with_extra_layer(shapes.rectangle(2.0, 2.0, 0.05)))
    model = Model(tables, "umls", "flip", ((NeoHookean(200.0, 0.3, 1.0), None),), (),
                  torch.zeros(2, dtype=torch.float64), tables.nodes, 0.04, reference="adaptive")
    state = State.at_rest_shape(x, v, np.full(len(x), np.prod(spacing)), 1.0)
    assert fused.applies(model, state)
    expected, got = python_steps(model, state, 7e-4, 250), advance(model, state, 7e-4, 250)
    assert got.reference.contact_rebuilds == expected.reference.contact_rebuilds > 0  # measured 39 of 79 rebuilds
    assert got.reference.rebuilds == expected.reference.rebuilds
    assert float(got.v[: len(xa), 0].mean()) < -0.5  # they hit and bounced back
    assert gap(got, expected)["x"] < 2e-15 and gap(got, expected)["v"] < 1e-13  # measured 2.2e-16, 1.3e-14


def test_a_header_left_out_warns_once_and_the_python_step_runs(monkeypatch, tmp_path):
    """An install without one of the headers substeps.c includes: one warning that names it, then
    the Python step, as without a compiler (no FileNotFoundError at the first simulation)."""
    csrc = tmp_path / "csrc"
    csrc.mkdir()
    for file in (fused.SOURCE, *fused.DEPENDS):
        if file.name != "nodes.h":
            (csrc / file.name).write_bytes(file.read_bytes())
    monkeypatch.setattr(fused, "SOURCE", csrc / fused.SOURCE.name)
    monkeypatch.setattr(fused, "DEPENDS", tuple(csrc / file.name for file in fused.DEPENDS))
    monkeypatch.setenv("BSMS_CACHE", str(tmp_path / "cache"))
    fused.library.cache_clear()
    try:
        model, state, dt = case_model(2, "neo_hookean", [Wall("sticky", floor)])
        with pytest.warns(RuntimeWarning, match=r"^could not build the compiled substeps \(cannot read .*/csrc/nodes\.h: "
                          r"No such file or directory\); each substep runs through the Python step, several times "
                          r"slower\. Set BSMS_NATIVE=0 to silence this$"):
            assert not fused.applies(model, state)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            got = advance(model, state, dt, 3)  # cached: no second warning
        assert torch.equal(got.x, python_steps(model, state, dt, 3).x)
        assert not list((tmp_path / "cache").rglob("substeps-*"))
    finally:
        fused.library.cache_clear()
