"""Transfer kernels: MLS identities, UMLS App. C closed form, continuity across cell faces."""

import numpy as np
import pytest
import torch

from datagen import shapes
from datagen.mesh import Mesh, with_extra_layer
from datagen.mpm.kernels import Grid, MeshTables, bspline_kernel, linear_kernel, umls_kernel


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
@pytest.mark.parametrize("layer", [False, True])
def test_partition_of_unity_and_linear_reproduction(gmsh_mesh, layer):
    _, mesh = gmsh_mesh
    tables = MeshTables.build(with_extra_layer(mesh) if layer else mesh)
    x = torch.tensor(_sample(mesh, np.arange(mesh.n_cells), 8))
    k = umls_kernel(tables, x)
    assert k.n_lost == 0
    assert max(_identity_errors(tables, k, x)) < 1e-10
    boundary = torch.tensor(_boundary_cells(mesh)[k.cell.numpy()])
    assert boundary.sum() > 100  # boundary cells are part of the check


def test_extra_layer_keeps_weights_nonnegative(gmsh_mesh):
    """UMLS §2.3.5: boundary cells without the layer give negative weights; the layer removes them.

    Strict (no weight below -1e-10) in every cell of the 2D meshes, corners included, and in
    the interior cells of the 3D ones. In 3D boundary cells one layer cannot reach as far out
    as the B-spline support reaches in (datagen/layer.py explains it): near convex creases and
    curved faces a few far inner nodes keep weights down to about -2e-4, whatever the layer
    thickness. This is the tightest bound we measured, not the property we want; the test pins
    how small, how rare and where they are, so that any growth shows.
    """
    name, mesh = gmsh_mesh
    bare, layered = MeshTables.build(mesh), MeshTables.build(with_extra_layer(mesh))
    boundary = _boundary_cells(mesh)
    interior = torch.tensor(_sample(mesh, np.flatnonzero(~boundary), 10, seed=3))
    assert umls_kernel(layered, interior).weight.min() >= -1e-10
    edge = torch.tensor(_sample(mesh, np.flatnonzero(boundary), 10, seed=4))
    assert umls_kernel(bare, edge).weight.min() < -1e-2  # the degeneration the layer fixes (UMLS Fig. 5)
    k = umls_kernel(layered, edge)
    if mesh.dim == 2:
        assert k.weight.min() >= -1e-10
        return
    negative = (k.weight < -1e-10).any(dim=1).numpy()
    assert k.weight.min() >= -5e-4
    assert negative.mean() < 0.002
    # the far inner nodes of the sample, never the nearby ones: each such weight is below 1% of
    # the particle's largest weight
    worst = torch.where(k.weight < -1e-10, -k.weight, 0.0).amax(dim=1)
    assert (worst <= 0.01 * k.weight.amax(dim=1)).all()
    x = edge.numpy()[negative]
    if name == "box":  # within one element (0.15) of a crease: two walls closer than that
        walls = np.sort(np.minimum(x, np.array([1.0, 0.8, 0.6]) - x), axis=1)
        assert (walls[:, 1] < 0.15).all()
    else:  # sphere (element size 0.3): within one element of the surface
        assert (np.linalg.norm(x, axis=1) > 0.7).all()


def test_identities_in_one_dimension_and_for_the_other_kernels():
    mesh = Mesh(np.cumsum(np.r_[0.0, np.random.default_rng(0).uniform(0.5, 1.5, 12)])[:, None],
                np.stack([np.arange(12), np.arange(1, 13)], axis=1))
    tables = MeshTables.build(with_extra_layer(mesh))
    x = torch.tensor(_sample(mesh, np.arange(mesh.n_cells), 20))
    assert max(_identity_errors(tables, umls_kernel(tables, x), x)) < 1e-10
    square = shapes.rectangle(1.0, 1.0, 0.2)
    tables = MeshTables.build(square)
    y = torch.tensor(_sample(square, np.arange(square.n_cells), 5))
    assert max(_identity_errors(tables, linear_kernel(tables, y), y)) < 1e-12
    grid = Grid((-0.5, -0.5), 0.1, (21, 21))
    z = torch.rand(500, 2, dtype=torch.float64) * 1.6 - 0.3
    k = bspline_kernel(grid, z)
    nodes = torch.tensor(grid.nodes())
    assert k.n_lost == 0 and (k.weight >= 0).all()
    assert float((k.weight.sum(1) - 1).abs().max()) < 1e-12
    assert float((torch.einsum("pk,pkd->pd", k.weight, nodes[k.index]) - z).abs().max()) < 1e-12
    gradient = torch.einsum("pki,pkj->pij", k.grad, nodes[k.index]) - torch.eye(2, dtype=z.dtype)
    assert float(gradient.abs().max()) < 1e-12


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
    np.testing.assert_allclose(w[:, 6].numpy(), _closed_form_node2(x), rtol=0, atol=1e-10)


def test_umls_kernel_is_mirror_symmetric_on_a_uniform_mesh(unit_line):
    x = np.random.default_rng(0).uniform(-2.0, 6.0, 400)  # mirror about node 2 (x = 2)
    w, g = _dense(umls_kernel(unit_line, torch.tensor(x[:, None])), unit_line.n_nodes)
    wm, gm = _dense(umls_kernel(unit_line, torch.tensor(4.0 - x[:, None])), unit_line.n_nodes)
    flip = torch.arange(unit_line.n_nodes).flip(0)  # node at 2 + s  <->  node at 2 - s
    np.testing.assert_allclose(w.numpy(), wm[:, flip].numpy(), atol=1e-12)
    np.testing.assert_allclose(g.numpy(), -gm[:, flip].numpy(), atol=1e-12)


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
    assert dw.max() < 1e-4
    assert (dg * h_local).max() < 1e-4


def test_without_eta_the_kernel_jumps_across_faces(crossing_mesh):
    """The ablation of UMLS Fig. 7: dropping eta makes weights or gradients jump."""
    mesh, tables = crossing_mesh
    dw, dg, h_local = _jumps(mesh, tables, eta=False)
    jumped = np.maximum(dw, dg * h_local) >= 1e-2
    assert jumped.mean() >= 0.25
