"""Cell location: hash candidates + barycentric test, with explicit statuses for lost particles."""

import numpy as np
import pytest
import torch

from datagen import shapes
from datagen.mesh import Mesh
from datagen.mpm.locate import CellLocator, LocateStatus, barycentric, locate


@pytest.fixture(scope="module", params=["2d", "3d"])
def mesh(request):
    if request.param == "2d":
        return shapes.polygon([(0, 0), (2, 0), (2, 1), (1, 1.6), (0, 1)], size=0.11)
    return shapes.sphere(1.0, 0.3)


def _brute_force(mesh: Mesh, x: np.ndarray) -> np.ndarray:
    """Index of the cell where each point is deepest (max of min barycentric), or -1."""
    loc = CellLocator.build(mesh)
    cells = torch.arange(mesh.n_cells)
    bary = barycentric(loc, cells[None, :].expand(len(x), -1), torch.tensor(x)[:, None, :])
    depth = bary.min(dim=-1).values
    best = depth.argmax(dim=1).numpy()
    return np.where(depth.max(dim=1).values.numpy() >= -1e-10, best, -1)


def test_locates_every_point_like_brute_force(mesh):
    rng = np.random.default_rng(1)
    lo, hi = mesh.nodes.min(0), mesh.nodes.max(0)
    x = rng.uniform(lo - 0.2, hi + 0.2, size=(3000, mesh.dim))
    where = locate(CellLocator.build(mesh), torch.tensor(x))
    expected = _brute_force(mesh, x)
    np.testing.assert_array_equal(where.cell.numpy(), expected)
    inside = expected >= 0
    assert inside.sum() > 500 and (~inside).sum() > 100
    assert (where.status.numpy()[~inside] == LocateStatus.OUTSIDE).all()
    assert (where.status.numpy()[inside] == LocateStatus.INSIDE).all()
    bary = where.bary.numpy()[inside]
    assert bary.min() >= 0.0  # points strictly inside a cell have positive coordinates there
    np.testing.assert_allclose(bary.sum(1), 1.0, rtol=0, atol=2e-15)  # measured 2.2e-16
    rebuilt = np.einsum("pk,pkd->pd", bary, mesh.nodes[mesh.cells[expected[inside]]])
    np.testing.assert_allclose(rebuilt, x[inside], rtol=0, atol=2e-15)  # measured 2.2e-16


def test_points_on_nodes_and_faces_are_found(mesh):
    # Mesh nodes lie on several cells at once: each must still get a valid containing cell.
    where = locate(CellLocator.build(mesh), torch.tensor(mesh.nodes))
    assert where.n_lost == 0
    assert (where.bary.numpy() >= -1e-15).all()  # measured: all >= 0
    corners = mesh.cells[where.cell.numpy()]  # each node is a corner of its cell, with coordinate 1
    at = np.argmax(where.bary.numpy(), axis=1)
    np.testing.assert_array_equal(corners[np.arange(mesh.n_nodes), at], np.arange(mesh.n_nodes))
    np.testing.assert_allclose(where.bary.numpy().max(1), 1.0, rtol=0, atol=2e-15)


def test_lost_particles_are_reported_not_dropped(mesh):
    x = torch.tensor(np.vstack([mesh.nodes.mean(0), mesh.nodes.max(0) + 5.0, [np.nan] * mesh.dim]))
    where = locate(CellLocator.build(mesh), x)
    assert where.cell.shape == (3,) and where.n_lost == 2
    assert where.status.tolist() == [LocateStatus.INSIDE, LocateStatus.OUTSIDE, LocateStatus.NONFINITE]
    assert where.cell[1:].tolist() == [-1, -1]


def test_guess_gives_the_same_answer(mesh):
    rng = np.random.default_rng(2)
    x = torch.tensor(rng.uniform(mesh.nodes.min(0), mesh.nodes.max(0), size=(500, mesh.dim)))
    loc = CellLocator.build(mesh)
    first = locate(loc, x)
    wrong_guess = torch.randint(0, mesh.n_cells, (len(x),), generator=torch.Generator().manual_seed(0))
    for guess in (first.cell, wrong_guess):
        again = locate(loc, x, guess=guess)
        assert torch.equal(again.status, first.status)
        inside = first.status == LocateStatus.INSIDE
        # A point on a shared face may legitimately land in either cell; its position must agree.
        np.testing.assert_allclose(_position(mesh, again)[inside], x[inside].numpy(), rtol=0, atol=2e-15)


def _position(mesh, where):
    cells = mesh.cells[where.cell.clamp(min=0).numpy()]
    return np.einsum("pk,pkd->pd", where.bary.numpy(), mesh.nodes[cells])


def test_one_dimensional_segments():
    mesh = Mesh(np.array([[0.0], [0.5], [1.5], [2.0]]), np.array([[0, 1], [1, 2], [2, 3]]))
    x = torch.tensor([[0.25], [1.0], [1.9], [2.5], [-0.1]], dtype=torch.float64)
    where = locate(CellLocator.build(mesh), x)
    assert where.cell.tolist() == [0, 1, 2, -1, -1]
    assert where.status.tolist() == [LocateStatus.INSIDE] * 3 + [LocateStatus.OUTSIDE] * 2
    np.testing.assert_allclose(where.bary[:3].numpy(), [[0.5, 0.5], [0.5, 0.5], [0.2, 0.8]], rtol=0, atol=2e-15)
