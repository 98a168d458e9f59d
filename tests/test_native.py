"""The compiled UMLS kernel and slot transfers (datagen.mpm.native) against their torch reference."""

import warnings

import numpy as np
import pytest
import torch

from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mesh import Mesh
from datagen.mpm import Model, State, cfl_time_step, native, step
from datagen.mpm.inelastic import patch_average
from datagen.mpm.kernels import Grid, MeshTables, bspline_kernel, umls_kernel, umls_kernel_p2g
from datagen.mpm.locate import locate
from datagen.mpm.materials import NeoHookean
from datagen.mpm.slots import scatter, slot_sums


def test_the_compiled_library_builds_here():
    """The fast path must not fall back silently where the project runs (CI has gcc)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a failed build warns: fail with its message instead
        assert native.available(), "no compiled library: install a C compiler (gcc) or see datagen.mpm.native"


@pytest.fixture
def torch_only(monkeypatch):
    """Run the block with the compiled library switched off (the torch reference)."""
    def use_torch(block):
        with monkeypatch.context() as m:
            m.setattr(native, "library", lambda: None)
            return block()
    return use_torch


def _particles(mesh: Mesh, n: int, seed: int) -> torch.Tensor:
    """n random points in the mesh's bounding box and a few far outside it (lost particles)."""
    rng = np.random.default_rng(seed)
    lo, hi = mesh.nodes.min(0), mesh.nodes.max(0)
    x = lo + (hi - lo) * rng.random((n, mesh.dim))
    x[:3] = hi + 5.0
    return torch.tensor(x)


MESHES = {
    "line": lambda: Mesh(np.linspace(0.0, 1.0, 12)[:, None] ** 1.3, np.stack([np.arange(11), np.arange(1, 12)], 1)),
    "disk": lambda: shapes.disk(1.0, 0.15),
    "box": lambda: shapes.box((1.0, 0.8, 0.6), 0.2),
}


@pytest.mark.parametrize("name", list(MESHES))
@pytest.mark.parametrize("layer", [True, False])
@pytest.mark.parametrize("eta", [True, False])
def test_compiled_umls_kernel_equals_the_torch_kernel(name, layer, eta, torch_only):
    mesh = MESHES[name]()
    tables = MeshTables.build(with_extra_layer(mesh) if layer else mesh)
    x = _particles(mesh, 3000, seed=len(name))
    compiled = umls_kernel(tables, x, eta)
    reference = torch_only(lambda: umls_kernel(tables, x, eta))
    assert torch.equal(compiled.index, reference.index) and torch.equal(compiled.status, reference.status)
    assert compiled.n_lost >= 3  # the disk also loses its bounding box corners
    # measured: weights <= 2.8e-16 apart, gradients <= 8e-16 of the largest gradient, offsets equal
    assert float((compiled.weight - reference.weight).abs().max()) < 3e-15
    scale = float(reference.grad_axes.abs().max())
    assert float((compiled.grad_axes - reference.grad_axes).abs().max()) < 1e-14 * scale
    assert torch.equal(compiled.offset_axes, reference.offset_axes)
    if not layer and name != "line":  # boundary cells need the non-negative projection in both paths
        plain = umls_kernel(tables, x, eta, nonnegative=False)
        assert bool((plain.weight < 0).any()) and float(compiled.weight.min()) >= 0.0


def _slot_case(dim: int, seed: int = 0):
    mesh = shapes.rectangle(1.0, 0.7, 0.1) if dim == 2 else shapes.box((1.0, 0.8, 0.6), 0.2)
    tables = MeshTables.build(with_extra_layer(mesh))
    rng = np.random.default_rng(seed)
    x = torch.tensor(mesh.nodes.min(0) + (np.ptp(mesh.nodes, 0)) * rng.random((2000, dim)))
    k = umls_kernel(tables, x)
    g = torch.Generator().manual_seed(seed)
    p = len(x)
    mass, v = torch.rand(p, generator=g, dtype=torch.float64) + 0.5, torch.randn(p, dim, generator=g, dtype=torch.float64)
    coef, affine = (torch.randn(p, dim, dim, generator=g, dtype=torch.float64) for _ in range(2))
    field = torch.randn(2 * dim, tables.n_nodes, generator=g, dtype=torch.float64)
    return tables, k, mass, v, coef, affine, field


def _torch_p2g(k, mass, v, coef, affine, n_nodes):
    r = k.offset_axes
    vel = v.T[:, :, None] if affine is None else torch.einsum("pab,bpk->apk", affine, r) + v.T[:, :, None]
    wm = k.weight * mass[:, None]
    values = torch.cat([wm[None], wm * vel, torch.einsum("pab,bpk->apk", coef, k.grad_axes)])
    return scatter(k, values, n_nodes)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("apic", [False, True])
def test_compiled_p2g_and_g2p_equal_the_slot_sums_in_torch(dim, apic, torch_only):
    tables, k, mass, v, coef, affine, field = _slot_case(dim)
    affine = affine if apic else None
    sums = native.p2g(k, mass, v, coef, affine, tables.n_nodes)
    reference = _torch_p2g(k, mass, v, coef, affine, tables.n_nodes)
    assert sums.shape == (1 + 2 * dim, tables.n_nodes)
    assert float((sums - reference).abs().max()) < 1e-13 * float(reference.abs().max())  # measured ~1e-15
    compiled = slot_sums(k, field, moments=apic)
    expected = torch_only(lambda: slot_sums(k, field, moments=apic))
    for got, want in zip(compiled, expected, strict=True):
        if want is None:
            assert got is None
            continue
        assert float((got - want).abs().max()) < 1e-13 * float(want.abs().max())


def test_compiled_sums_do_not_depend_on_the_thread_count_and_conserve_mass_and_momentum():
    """Node sums over fixed particle blocks added in a fixed order: 1 and 2 threads give the same
    bits (datasets stay reproducible), and the sums carry the particles' total mass and momentum
    (partition of unity) to round-off."""
    tables, k, mass, v, coef, affine, field = _slot_case(3, seed=1)
    before = torch.get_num_threads()
    try:
        results = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            results.append((native.p2g(k, mass, v, coef, affine, tables.n_nodes),
                            native.patch_average(k, v[:, 0], mass, tables.n_nodes)))
    finally:
        torch.set_num_threads(before)
    (first, average), (second, average2) = results
    assert torch.equal(first, second) and torch.equal(average, average2)
    assert abs(float(first[0].sum() - mass.sum())) < 1e-12 * float(mass.sum())
    # with APIC the affine part sums to C_p sum_i w (x_i - x_p) = 0 (linear reproduction)
    momentum = (mass[:, None] * v).sum(0)
    assert float((first[1:4].sum(1) - momentum).abs().max()) < 1e-11 * float((mass[:, None] * v.abs()).sum())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("layer", [True, False])
def test_fused_kernel_and_p2g_equal_the_kernel_then_p2g(dim, layer, torch_only):
    """umls_kernel_p2g: the same kernel as umls_kernel, and its sums plus the share of the particles
    it left out (those whose kernel was made non-negative) equal the compiled P2G of that kernel
    and the torch P2G; lost particles add nothing. Without the extra layer boundary particles are
    left out; the sums do not depend on the thread count."""
    mesh = shapes.rectangle(1.0, 0.7, 0.1) if dim == 2 else shapes.box((1.0, 0.8, 0.6), 0.2)
    tables = MeshTables.build(with_extra_layer(mesh) if layer else mesh)
    x = _particles(mesh, 2500, seed=dim)
    g = torch.Generator().manual_seed(dim)
    mass = torch.rand(len(x), generator=g, dtype=torch.float64) + 0.5
    v, coef = torch.randn(len(x), dim, generator=g, dtype=torch.float64), torch.randn(len(x), dim, dim, generator=g,
                                                                                        dtype=torch.float64)
    before = torch.get_num_threads()
    try:
        runs = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            runs.append(umls_kernel_p2g(tables, x, mass, v, coef, tables.n_nodes))
    finally:
        torch.set_num_threads(before)
    (k, sums, left_out), (_, sums2, left_out2) = runs
    assert torch.equal(sums, sums2) and torch.equal(left_out, left_out2)
    plain = umls_kernel(tables, x)
    assert torch.equal(k.index, plain.index) and torch.equal(k.weight, plain.weight)
    assert torch.equal(k.grad_axes, plain.grad_axes) and k.n_lost >= 3
    negative = (umls_kernel(tables, x, nonnegative=False).weight < 0).any(1).nonzero().squeeze(1)
    assert torch.equal(left_out, negative) and (layer or len(left_out) > 0)
    rows = k.select(left_out)
    total = sums + native.p2g(rows, mass[left_out], v[left_out], coef[left_out], None, tables.n_nodes)
    reference = native.p2g(k, mass, v, coef, None, tables.n_nodes)
    in_torch = _torch_p2g(k, mass, v, coef, None, tables.n_nodes)
    scale = float(in_torch.abs().max())
    assert float((total - reference).abs().max()) < 1e-13 * scale  # measured ~1e-16
    assert float((total - in_torch).abs().max()) < 1e-13 * scale
    assert torch_only(lambda: umls_kernel_p2g(tables, x, mass, v, coef, tables.n_nodes))[1:] == (None, None)


@pytest.mark.parametrize("transfer", ["flip", "musl", "apic"])
def test_steps_with_the_compiled_loops_follow_the_torch_steps(transfer, torch_only):
    """Twenty steps of a spinning elastic block crossing cells near the walls of a box (the fused
    kernel + P2G pass for FLIP and MUSL, the separate loops for APIC) stay on the torch steps to
    round-off."""
    mesh = shapes.rectangle(1.0, 1.0, 0.1)
    tables = MeshTables.build(with_extra_layer(mesh))
    material = NeoHookean(1e4, 0.3, 1000.0)
    g = np.stack(np.meshgrid(np.linspace(0.08, 0.92, 22), np.linspace(0.08, 0.92, 22)), -1).reshape(-1, 2)
    x = torch.tensor(g)
    v = torch.stack([-(x[:, 1] - 0.5), x[:, 0] - 0.5], 1) * 2.0
    gravity = torch.tensor([0.0, -9.81], dtype=torch.float64)
    model = Model(tables, "umls", transfer, ((material, None),), (), gravity, tables.nodes,
                  mesh.edge_length_stats.min)
    start = State.at_rest_shape(x, v, torch.full((len(x),), (0.84 / 21) ** 2, dtype=torch.float64), 1000.0)
    dt = cfl_time_step(model, start, 0.3)

    def run():
        state = start
        for _ in range(20):
            state = step(model, state, dt)
        return state

    compiled, reference = run(), torch_only(run)
    assert float((compiled.x - start.x).abs().max()) > 0.05  # particles crossed cells
    # measured: x 2.2e-16 m apart, v 4.8e-16 to 7.6e-16 relative, F 5.6e-16 to 7.8e-16
    assert float((compiled.x - reference.x).abs().max()) < 2e-15
    assert float((compiled.v - reference.v).abs().max()) < 5e-15 * float(reference.v.abs().max())
    assert float((compiled.F - reference.F).abs().max()) < 5e-15


def test_grid_kernels_use_the_compiled_transfers_too(torch_only):
    grid = Grid.covering(np.zeros(2), np.ones(2), 0.1)
    x = torch.rand(500, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * 0.8 + 0.1
    k = bspline_kernel(grid, x)
    field = torch.randn(4, grid.n_nodes, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    got = slot_sums(k, field, moments=True)
    want = torch_only(lambda: slot_sums(k, field, moments=True))
    for a, b in zip(got, want, strict=True):
        assert float((a - b).abs().max()) < 1e-13 * float(b.abs().max())


def test_a_failing_compiler_warns_once_and_leaves_the_torch_kernel(monkeypatch, tmp_path):
    native.library.cache_clear()
    monkeypatch.setenv("BSMS_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "false")
    try:
        with pytest.warns(RuntimeWarning, match=r"could not build the compiled UMLS kernel \(false failed"):
            assert native.library() is None
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert native.library() is None  # cached: no second warning
            mesh = shapes.rectangle(1.0, 1.0, 0.25)
            k = umls_kernel(MeshTables.build(with_extra_layer(mesh)), torch.tensor([[0.5, 0.5]], dtype=torch.float64))
        assert abs(float(k.weight.sum()) - 1.0) < 1e-15
        assert not list(tmp_path.rglob("*.so"))  # nothing half-written left behind
        monkeypatch.setenv("BSMS_NATIVE", "0")
        native.library.cache_clear()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert native.library() is None  # switched off: silent
    finally:
        native.library.cache_clear()


@pytest.mark.parametrize("name", ["disk", "box"])
def test_compiled_guess_test_of_locate_equals_torch(name, torch_only):
    mesh = MESHES[name]()
    tables = MeshTables.build(mesh)
    x = _particles(mesh, 3000, seed=7)
    x[3] = float("nan")
    guess = locate(tables.locator, x).cell
    moved = x + 0.005 * torch.randn(x.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(8))
    guess[10:20] = -1
    got = locate(tables.locator, moved, guess)
    want = torch_only(lambda: locate(tables.locator, moved, guess))
    assert torch.equal(got.cell, want.cell) and torch.equal(got.status, want.status)
    assert float((got.bary - want.bary).abs().max()) < 1e-15
    assert len(x) // 2 < int((got.cell == guess).sum()) < len(x) - 20  # most particles stayed in their cell


def test_compiled_patch_average_equals_torch(torch_only):
    tables, k, mass, v, coef, affine, field = _slot_case(2, seed=2)
    value = 1.0 + 0.1 * v[:, 0]
    got = patch_average(k, value, mass, tables.n_nodes)
    want = torch_only(lambda: patch_average(k, value, mass, tables.n_nodes))
    assert float((got - want).abs().max()) < 1e-14
    constant = patch_average(k, torch.full_like(value, 0.75), mass, tables.n_nodes)
    assert float((constant - 0.75).abs().max()) < 1e-15  # an average of a constant is that constant
