"""Transfer kernels: MLS identities, UMLS App. C closed form, continuity across cell faces."""

import numpy as np
import pytest
import torch
from scipy import optimize

from datagen import shapes
from datagen.layer import with_extra_layer
from datagen.mesh import Mesh
from datagen.mpm.kernels import (
    Grid,
    MeshTables,
    bspline_kernel,
    linear_kernel,
    mls_linear_weights,
    nonnegative_mls,
    umls_kernel,
)


def _sample(mesh: Mesh, cells: np.ndarray, per_cell: int, seed: int = 0) -> np.ndarray:
    """Random points inside the given cells (Dirichlet barycentric coordinates)."""
    rng = np.random.default_rng(seed)
    cells = np.repeat(cells, per_cell)
    bary = rng.dirichlet(np.ones(mesh.dim + 1), size=cells.size)
    return np.einsum("pk,pkd->pd", bary, mesh.nodes[mesh.cells[cells]])


def _boundary_cells(mesh: Mesh) -> np.ndarray:
    return mesh.boundary_node_mask[mesh.cells].any(axis=1)


def _identity_errors(tables: MeshTables, k, x: torch.Tensor) -> tuple[float, float, float]:
    """Max errors of sum w = 1, sum w x_i = x_p and sum grad w (x) x_i = I."""
    xi = tables.nodes[k.index.clamp(min=0)]
    unity = (k.weight.sum(1) - 1).abs().max()
    linear = (torch.einsum("pk,pkd->pd", k.weight, xi) - x).abs().max()
    eye = torch.eye(x.shape[1], dtype=x.dtype)
    gradient = (torch.einsum("pki,pkj->pij", k.grad, xi) - eye).abs().max()
    return float(unity), float(linear), float(gradient)


MESHES = {
    "rectangle": lambda: shapes.rectangle(1.0, 0.7, 0.1),
    "disk": lambda: shapes.disk(1.0, 0.12),
    "box": lambda: shapes.box((1.0, 0.8, 0.6), 0.15),
    "sphere": lambda: shapes.sphere(1.0, 0.3),
}


@pytest.fixture(scope="module", params=list(MESHES))
def gmsh_mesh(request):
    return request.param, MESHES[request.param]()


# ----------------------------------------------------------------------------- item 1
# Bounds on (sum w - 1, sum w x_i - x_p, sum grad w x_i^T - I) per (mesh, extra layer), within 10x
# of the largest errors the tests below measured (bodies of size ~1): 4.4e-16 to 7.8e-16 for the
# first two and 2e-15 to 1.1e-14 for the gradients, except without the layer on the curved meshes,
# whose boundary particles' moment matrices are worse conditioned (disk 7.2e-13, sphere 6.4e-15,
# 6.3e-15, 1.2e-12).
IDENTITY_TOL = {
    ("rectangle", True): (4e-15, 3e-15, 4e-14), ("rectangle", False): (4e-15, 3e-15, 6e-14),
    ("disk", True): (4e-15, 5e-15, 3e-14), ("disk", False): (6e-15, 5e-15, 7e-12),
    ("box", True): (4e-15, 6e-15, 4e-14), ("box", False): (4e-15, 6e-15, 7e-14),
    ("sphere", True): (4e-15, 7e-15, 2e-14), ("sphere", False): (6e-14, 6e-14, 1e-11),
}


def _assert_identities(tables: MeshTables, k, x: torch.Tensor, tol: tuple[float, float, float]) -> None:
    errors = _identity_errors(tables, k, x)
    assert all(e < t for e, t in zip(errors, tol, strict=True)), f"identity errors {errors} above {tol}"


@pytest.mark.parametrize("layer", [False, True])
def test_partition_of_unity_and_linear_reproduction(gmsh_mesh, layer):
    name, mesh = gmsh_mesh
    tables = MeshTables.build(with_extra_layer(mesh) if layer else mesh)
    x = torch.tensor(_sample(mesh, np.arange(mesh.n_cells), 8))
    k = umls_kernel(tables, x)
    assert k.n_lost == 0
    _assert_identities(tables, k, x, IDENTITY_TOL[name, layer])
    boundary = torch.tensor(_boundary_cells(mesh)[k.cell.numpy()])
    assert boundary.sum() > 100  # boundary cells are part of the check


def test_extra_layer_keeps_weights_nonnegative(gmsh_mesh):
    """UMLS §2.3.5: boundary cells without the layer give negative weights; the layer removes them.

    Plain MLS (nonnegative=False) with the layer is non-negative in every cell of the 2D meshes,
    corners included, and in the interior cells of the 3D ones. In 3D boundary cells one layer
    cannot reach as far out as the B-spline support reaches in (datagen/layer.py explains it):
    near convex creases and curved faces a few far inner nodes keep weights down to about -1e-4.
    The test pins how small, how rare and where they are. The kernel the solver uses
    (nonnegative=True, the default) replaces exactly those rows by the closest non-negative
    kernel, so it has no weight below 0 anywhere.
    """
    name, mesh = gmsh_mesh
    bare, layered = MeshTables.build(mesh), MeshTables.build(with_extra_layer(mesh))
    boundary = _boundary_cells(mesh)
    interior = torch.tensor(_sample(mesh, np.flatnonzero(~boundary), 10, seed=3))
    assert umls_kernel(layered, interior, nonnegative=False).weight.min() >= -1e-10
    edge = torch.tensor(_sample(mesh, np.flatnonzero(boundary), 10, seed=4))
    assert umls_kernel(bare, edge, nonnegative=False).weight.min() < -1e-2  # UMLS Fig. 5
    k = umls_kernel(layered, edge)
    assert k.weight.min() >= 0.0
    _assert_identities(layered, k, edge, IDENTITY_TOL[name, True])
    plain = umls_kernel(layered, edge, nonnegative=False)
    if mesh.dim == 2:
        assert plain.weight.min() >= 0.0
        assert torch.equal(k.weight, plain.weight) and torch.equal(k.grad, plain.grad)
        return
    negative = (plain.weight < 0).any(dim=1).numpy()
    # measured: smallest weight -9.4e-5 (box) / -1.9e-5 (sphere), in 0.099% / 0.018% of the particles,
    # the worst at 6.6e-4 / 1.1e-4 of the particle's largest weight
    lowest, share, ratio = {"box": (-3e-4, 0.002, 2e-3), "sphere": (-1e-4, 5e-4, 5e-4)}[name]
    assert plain.weight.min() >= lowest
    assert negative.mean() < share
    # the far inner nodes of the sample, never the nearby ones: each such weight is a tiny fraction
    # of the particle's largest weight
    worst = torch.where(plain.weight < 0, -plain.weight, 0.0).amax(dim=1)
    assert (worst <= ratio * plain.weight.amax(dim=1)).all()
    # the projection changes those rows by as much as their negative weights (measured: exactly), no more
    change = (k.weight - plain.weight).abs().amax(dim=1)
    assert float(change.max()) <= 2 * float(worst.max())
    x = edge.numpy()[negative]
    if name == "box":  # within one element (0.15) of a crease: two walls closer than that
        walls = np.sort(np.minimum(x, np.array([1.0, 0.8, 0.6]) - x), axis=1)
        assert (walls[:, 1] < 0.15).all()
    else:  # sphere (element size 0.3): within one element of the surface
        assert (np.linalg.norm(x, axis=1) > 0.7).all()


def test_nonnegative_kernel_on_meshes_without_the_layer(gmsh_mesh):
    """Without the layer a third of the boundary particles need the projection: all weights
    are >= 0, the identities stay exact and the other particles' kernels are untouched."""
    name, mesh = gmsh_mesh
    bare = MeshTables.build(mesh)
    x = torch.tensor(_sample(mesh, np.flatnonzero(_boundary_cells(mesh)), 10, seed=4))
    plain, k = umls_kernel(bare, x, nonnegative=False), umls_kernel(bare, x)
    fixed = (plain.weight < 0).any(dim=1)
    assert fixed.float().mean() > 0.2
    assert k.weight.min() >= 0.0
    _assert_identities(bare, k, x, IDENTITY_TOL[name, False])
    assert torch.equal(k.weight[~fixed], plain.weight[~fixed]) and torch.equal(k.grad[~fixed], plain.grad[~fixed])
    assert ((k.weight[fixed] == 0) & (plain.weight[fixed] != 0)).any(dim=1).all()  # nodes were dropped


def _random_clouds(dim: int, rows: int, k: int, seed: int):
    """Node offsets r (dim, R, K) around a particle at 0, skewed so that MLS weights go negative,
    whose first dim+1 nodes are a simplex containing 0; sample weights d; the simplex's hat."""
    rng = np.random.default_rng(seed)
    r = rng.normal(size=(rows, k, dim)) + np.array([1.5] + [0.0] * (dim - 1))
    bary = 0.3 / (dim + 1) + 0.7 * rng.dirichlet(np.ones(dim + 1), size=rows)
    simplex = r[:, : dim + 1].copy()
    simplex[:, dim] = -np.einsum("rn,rnd->rd", bary[:, :dim], simplex[:, :dim]) / bary[:, dim:]
    r[:, : dim + 1] = simplex
    d = rng.uniform(0.05, 1.0, size=(rows, k))
    d[:, -1] = 0.0  # an empty slot
    spans = simplex[:, 1:] - simplex[:, :1]  # gradients of the barycentric coordinates
    rest = np.linalg.inv(np.swapaxes(spans, 1, 2))
    hat_grad = np.zeros((rows, k, dim))
    hat_grad[:, : dim + 1] = np.concatenate([-rest.sum(axis=1, keepdims=True), rest], axis=1)
    hat = np.zeros((rows, k))
    hat[:, : dim + 1] = bary
    as_t = torch.tensor
    return as_t(r.transpose(2, 0, 1).copy()), as_t(d), as_t(hat), as_t(hat_grad.transpose(2, 0, 1).copy())


def _qp_by_slsqp(d: np.ndarray, r: np.ndarray):
    """min sum w^2 / (2 d) subject to sum w = 1, sum w r = 0, w >= 0, by SLSQP."""
    constraints = np.vstack([np.ones(d.size), r])
    target = np.r_[1.0, np.zeros(r.shape[0])]
    return optimize.minimize(
        lambda v: 0.5 * np.sum(v * v / d), np.full(d.size, 1 / d.size), jac=lambda v: v / d,
        method="SLSQP", bounds=[(0, None)] * d.size,
        constraints={"type": "eq", "fun": lambda v: constraints @ v - target, "jac": lambda v: constraints},
        options={"ftol": 1e-14, "maxiter": 500})


# (sum w - 1, scaled sum w r, sum grad w r^T - I) of nonnegative_mls per dimension, 10x the
# measured 6.7e-16/1.7e-16/6.7e-16 (1D), 7.5e-15/8.0e-14/1.1e-12 (2D), 4.9e-14/3.3e-13/2.5e-12 (3D)
NONNEGATIVE_TOL = {1: (6e-15, 1.5e-15, 6e-15), 2: (7e-14, 8e-13, 1e-11), 3: (4e-13, 3e-12, 2e-11)}


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_nonnegative_mls_solves_the_constrained_least_squares(dim):
    """nonnegative_mls is the minimiser of sum w^2/d under linear reproduction and w >= 0: KKT
    conditions to round-off, and the same optimum as a general-purpose QP solver."""
    r, d, hat, hat_grad = _random_clouds(dim, 300, 10, seed=dim)
    plain, _ = mls_linear_weights(d, r)
    need = (plain < 0).any(dim=1)
    assert need.float().mean() > 0.3
    w, g = nonnegative_mls(d, r, hat, hat_grad)
    unity, linear, gradient = NONNEGATIVE_TOL[dim]
    assert w.min() >= 0.0
    assert float((w.sum(1) - 1).abs().max()) < unity
    scale = r.abs().amax(dim=(0, 2))  # the simplex's last vertex can lie far out
    assert float((torch.einsum("rk,ark->ra", w, r).abs().amax(dim=1) / scale).max()) < linear
    eye = torch.einsum("ark,brk->rab", g, r) - torch.eye(dim, dtype=r.dtype)
    assert float(eye.abs().max()) < gradient
    # KKT: w is MLS on its support A, and the fit of A is < 0 at every other sampled node
    active = w > 0
    fit, _ = mls_linear_weights(d * active, r, evaluate=d)
    assert float((fit - w)[active].abs().max()) < 1e-15
    assert float(fit[~active & (d > 0)].max()) < 0.0
    # rows where MLS is non-negative are MLS itself
    assert torch.equal(w[~need], plain[~need])
    # a general QP solver agrees on a few rows (to its own tolerance: measured 5.8e-8 at most)
    for row in np.flatnonzero(need.numpy())[:5]:
        keep = d[row].numpy() > 0
        result = _qp_by_slsqp(d[row].numpy()[keep], r[:, row].numpy()[:, keep])
        assert result.success
        np.testing.assert_allclose(w[row].numpy()[keep], result.x, atol=5e-7)


def test_identities_in_one_dimension_and_for_the_other_kernels():
    mesh = Mesh(np.cumsum(np.r_[0.0, np.random.default_rng(0).uniform(0.5, 1.5, 12)])[:, None],
                np.stack([np.arange(12), np.arange(1, 13)], axis=1))
    tables = MeshTables.build(with_extra_layer(mesh))
    x = torch.tensor(_sample(mesh, np.arange(mesh.n_cells), 20))  # up to 12 m: measured 3.3e-16, 3.6e-15, 4.4e-15
    _assert_identities(tables, umls_kernel(tables, x), x, (3e-15, 3e-14, 4e-14))
    square = shapes.rectangle(1.0, 1.0, 0.2)
    tables = MeshTables.build(square)
    y = torch.tensor(_sample(square, np.arange(square.n_cells), 5))  # measured 1.1e-16, 1.1e-16, 1.1e-15
    _assert_identities(tables, linear_kernel(tables, y), y, (1e-15, 1e-15, 1e-14))
    grid = Grid((-0.5, -0.5), 0.1, (21, 21))
    z = torch.rand(500, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.3
    k = bspline_kernel(grid, z)
    nodes = torch.tensor(grid.nodes())
    assert k.n_lost == 0 and (k.weight >= 0).all()
    # measured 2.2e-16, 4.4e-16, 4.9e-15
    assert float((k.weight.sum(1) - 1).abs().max()) < 2e-15
    assert float((torch.einsum("pk,pkd->pd", k.weight, nodes[k.index]) - z).abs().max()) < 4e-15
    gradient = torch.einsum("pki,pkj->pij", k.grad, nodes[k.index]) - torch.eye(2, dtype=z.dtype)
    assert float(gradient.abs().max()) < 4e-14


# ----------------------------------------------------------------------------- item 2
def _closed_form_node2(x: np.ndarray) -> np.ndarray:
    """UMLS App. C eq. 46, first two pieces: node 2's weight on a uniform mesh of unit cells."""
    first = 0.25 * (0.5 - x) ** 2 * x / (x**5 - 6 * x**4 + 13.5 * x**3 - 13.75 * x**2 + 6.3125 * x - 0.5625)
    num = -(x**6) + 5 * x**5 - 9.5 * x**4 + 8.5 * x**3 - 3.3125 * x**2 + 0.3125 * x + 0.0625
    den = -(x**5) + 4 * x**4 - 5.5 * x**3 + 3.25 * x**2 - 1.3125 * x + 1.0625
    return np.where(x <= 1.0, first, num / den)


@pytest.fixture(scope="module")
def unit_line():
    """Nodes at -4, ..., 8 (node 2 is index 6): uniform unit cells around the tested range."""
    nodes = np.arange(-4.0, 9.0)[:, None]
    return MeshTables.build(Mesh(nodes, np.stack([np.arange(12), np.arange(1, 13)], axis=1)))


def _dense(k, n_nodes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-particle weights (P, N) and gradients (P, N, d) over all nodes."""
    p, d = k.index.shape[0], k.grad.shape[-1]
    index = k.index.clamp(min=0)
    w = torch.zeros(p, n_nodes, dtype=k.weight.dtype).scatter_add_(1, index, k.weight)
    g = torch.zeros(p, n_nodes, d, dtype=k.weight.dtype)
    g.scatter_add_(1, index[..., None].expand(-1, -1, d), k.grad)
    return w, g


def test_umls_weight_matches_appendix_c_closed_form(unit_line):
    x = np.concatenate([np.linspace(0.5, 1.0, 401)[1:], np.linspace(1.0, 1.5, 401)[1:]])
    w, _ = _dense(umls_kernel(unit_line, torch.tensor(x[:, None])), unit_line.n_nodes)
    np.testing.assert_allclose(w[:, 6].numpy(), _closed_form_node2(x), rtol=0, atol=2e-13)  # measured 2.3e-14


def test_umls_kernel_is_mirror_symmetric_on_a_uniform_mesh(unit_line):
    x = np.random.default_rng(0).uniform(-2.0, 6.0, 400)  # mirror about node 2 (x = 2)
    w, g = _dense(umls_kernel(unit_line, torch.tensor(x[:, None])), unit_line.n_nodes)
    wm, gm = _dense(umls_kernel(unit_line, torch.tensor(4.0 - x[:, None])), unit_line.n_nodes)
    flip = torch.arange(unit_line.n_nodes).flip(0)  # node at 2 + s  <->  node at 2 - s
    np.testing.assert_allclose(w.numpy(), wm[:, flip].numpy(), rtol=0, atol=3e-15)  # measured 3.3e-16
    np.testing.assert_allclose(g.numpy(), -gm[:, flip].numpy(), rtol=0, atol=4e-15)  # measured 4.4e-16


# ----------------------------------------------------------------------------- item 3
def _interior_faces(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Faces shared by two cells: (F, d) node ids and (F, 2) the two cells."""
    d, k = mesh.dim, mesh.dim + 1
    local = np.array([[m for m in range(k) if m != j] for j in range(k)])
    faces = np.sort(mesh.cells[:, local].reshape(-1, d), axis=1)
    owner = np.repeat(np.arange(mesh.n_cells), k)
    _, inverse, counts = np.unique(faces, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    pairs = order[counts[inverse[order]] == 2].reshape(-1, 2)
    return faces[pairs[:, 0]], owner[pairs]


def _crossings(mesh: Mesh, n: int, seed: int):
    """n random face crossings: points 5e-8 before and after a face, inside the two cells."""
    rng = np.random.default_rng(seed)
    faces, cells = _interior_faces(mesh)
    pick = rng.choice(len(faces), size=min(n, len(faces)), replace=False)
    faces, cells = faces[pick], cells[pick]
    corners = mesh.nodes[faces]  # (F, d, d)
    bary = 0.2 / mesh.dim + 0.8 * rng.dirichlet(np.ones(mesh.dim), size=len(faces))
    on_face = np.einsum("fk,fkd->fd", bary, corners)
    if mesh.dim == 2:
        tangent = corners[:, 1] - corners[:, 0]
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    else:
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    first_centre = mesh.nodes[mesh.cells[cells[:, 0]]].mean(axis=1)
    normal *= np.sign(((on_face - first_centre) * normal).sum(1))[:, None]
    h_local = np.linalg.norm(mesh.nodes[mesh.cells[cells]][:, :, :, None] -
                             mesh.nodes[mesh.cells[cells]][:, :, None, :], axis=-1).reshape(len(faces), -1)
    h_local = h_local[h_local > 0].reshape(len(faces), -1).mean(axis=1)
    return on_face - 5e-8 * normal, on_face + 5e-8 * normal, cells, h_local


# Largest jumps of the weights and of h * |grad w| when a particle moves 1e-7 across a face,
# 10x the measured 5.6e-7 and 1.3e-6 (2D), 1.6e-7 and 5.9e-7 (3D); on the meshes without the
# layer, for the particles that need the non-negative projection: 8.6e-7 and 1.4e-6 (2D),
# 5.4e-7 and 1.3e-6 (3D).
JUMP_TOL = {2: {"layer": (5e-6, 1e-5), "bare": (8e-6, 1.4e-5)}, 3: {"layer": (1.5e-6, 5e-6), "bare": (5e-6, 1.2e-5)}}


@pytest.fixture(scope="module", params=["2d", "3d"])
def crossing_mesh(request):
    if request.param == "2d":
        mesh = shapes.polygon([(0, 0), (1.5, 0), (1.5, 1.0), (0.6, 1.3), (0, 1.0)], size=0.09)
    else:
        mesh = shapes.box((1.0, 1.0, 1.0), 0.2)
    return mesh, MeshTables.build(with_extra_layer(mesh))


def _jumps(mesh, tables, eta: bool, n: int = 400):
    before, after, cells, h_local = _crossings(mesh, n, seed=7)
    k0 = umls_kernel(tables, torch.tensor(before), eta=eta)
    k1 = umls_kernel(tables, torch.tensor(after), eta=eta)
    # the two points really are in the two cells that share the face
    assert np.array_equal(k0.cell.numpy(), cells[:, 0]) and np.array_equal(k1.cell.numpy(), cells[:, 1])
    w0, g0 = _dense(k0, tables.n_nodes)
    w1, g1 = _dense(k1, tables.n_nodes)
    dw = (w1 - w0).abs().amax(dim=1).numpy()
    dg = (g1 - g0).norm(dim=-1).amax(dim=1).numpy()
    return dw, dg, h_local


def test_umls_kernel_is_continuous_across_faces(crossing_mesh):
    mesh, tables = crossing_mesh
    dw, dg, h_local = _jumps(mesh, tables, eta=True)
    assert len(dw) >= 300
    weight_tol, gradient_tol = JUMP_TOL[mesh.dim]["layer"]
    assert dw.max() < weight_tol
    assert (dg * h_local).max() < gradient_tol


def test_without_eta_the_kernel_jumps_across_faces(crossing_mesh):
    """The ablation of UMLS Fig. 7: dropping eta makes weights or gradients jump at every crossing
    (measured: all of them by >= 1e-2, over 1e4 times the jumps with eta; median 0.03 in 2D, 0.08 in 3D)."""
    mesh, tables = crossing_mesh
    dw, dg, h_local = _jumps(mesh, tables, eta=False)
    jump = np.maximum(dw, dg * h_local)
    assert (jump >= 1e-2).mean() >= 0.95
    assert np.median(jump) >= 0.015


def test_nonnegative_kernel_is_continuous_across_faces(crossing_mesh):
    """On the mesh without the layer, where many particles near the boundary need the
    projection, weights and gradients stay continuous across faces (item 3's bounds)."""
    mesh, _ = crossing_mesh
    bare = MeshTables.build(mesh)
    parts = [_crossings(mesh, 100_000, seed=seed) for seed in range(8, 16)]  # 8 points on every face
    before, after, cells, h_local = (np.concatenate(part) for part in zip(*parts, strict=True))
    plain = umls_kernel(bare, torch.tensor(before), nonnegative=False)
    near = (plain.weight < 0).any(dim=1).numpy()
    assert near.sum() >= 100
    k0 = umls_kernel(bare, torch.tensor(before[near]))
    k1 = umls_kernel(bare, torch.tensor(after[near]))
    assert np.array_equal(k0.cell.numpy(), cells[near, 0]) and np.array_equal(k1.cell.numpy(), cells[near, 1])
    w0, g0 = _dense(k0, bare.n_nodes)
    w1, g1 = _dense(k1, bare.n_nodes)
    weight_tol, gradient_tol = JUMP_TOL[mesh.dim]["bare"]
    assert float((w1 - w0).abs().max()) < weight_tol
    assert ((g1 - g0).norm(dim=-1).amax(dim=1).numpy() * h_local[near]).max() < gradient_tol
