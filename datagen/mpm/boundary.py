"""Boundary conditions on background nodes, applied to the updated nodal velocities.

Walls lie on the conforming boundary of the background mesh (its outward normals) and act
on the boundary nodes and on their copies in the extra layer; on a regular grid they act
on the nodes at or beyond the faces of the grid's box. Kinds:

- ``sticky``: v = 0 on the wall. On a mesh with an extra layer the layer nodes beyond the
  wall are by default *mirror ghosts* (:class:`Mirror`): each takes minus the velocity
  interpolated at its reflection across the wall, so the velocity field is odd about the
  wall and vanishes on it. The ghosts are slaved to the nodes they mirror: the solver folds
  the mass, momentum and force the particles scatter to them back onto those nodes
  (:func:`fold_mirrors`) and the wall nodes' own momentum and force cancel, so the body sees
  its odd mirror image beyond the wall and the clamp sits on the wall to second order in h.
  With ``Wall(..., fold=False)`` the ghosts' velocities are only overwritten after the
  update: the fixed end of the vibrating bar then sits about 0.07 h beyond the wall, a
  frequency error linear in h. On a grid the nodes beyond a sticky box face are mirror
  ghosts the same way (reflected across the face's plane, multilinear interpolation there;
  those whose stencil leaves the box stay at rest). Holding the layer nodes at rest instead
  (``Wall(..., mirror=False)``) puts the effective clamp about 0.14 h
  outside the wall, where the odd extension of the motion would be negative: a softer clamp
  (a 2D bar clamped about 0.1 m too far out at 80 cells, a cantilever deflecting ~5% more at
  the 0.5 m mesh).
- ``slip``: the normal component is removed, v <- v - (v.n) n.
- ``separating``: only motion into the wall (v.n > 0 with n outward) is stopped, and the
  tangential velocity is reduced by Coulomb friction mu (v.n), down to zero.

Clamps (Dirichlet sets) hold every node inside a region at rest, e.g. a beam's fixed end.

Conditions apply in the order of the walls, then the clamps, then every mirror ghost (so the
ghosts see the final velocities of the nodes they mirror); moving rigid obstacles
(:mod:`~datagen.mpm.colliders`) act after the clamps and before the mirror ghosts. The mirrors
also act before the update: :func:`fold_mirrors` on the P2G sums, :func:`apply_mirrors` on the
velocities before the update (the FLIP increment of a ghost is then the mirror of its sources'
increment).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..layer import ExtendedMesh
from ..mesh import Mesh
from .kernels import Grid
from .locate import CellLocator, LocateStatus, locate

__all__ = [
    "Sticky", "Slip", "SeparatingSlip", "Mirror", "Wall", "Clamp", "WALL_KINDS",
    "mesh_conditions", "grid_conditions", "apply_conditions", "fold_mirrors", "apply_mirrors",
]


@dataclass(frozen=True, eq=False)
class Sticky:
    """Nodes held at rest. nodes: (n,) int64."""

    nodes: torch.Tensor

    def apply(self, v: torch.Tensor) -> torch.Tensor:
        """v: (d, N) nodal velocities by axis, modified in place and returned."""
        v[:, self.nodes] = 0.0
        return v


@dataclass(frozen=True, eq=False)
class Slip:
    """Nodes that may only move tangentially. nodes: (n,), normals: (d, n) unit outward."""

    nodes: torch.Tensor
    normals: torch.Tensor

    def apply(self, v: torch.Tensor) -> torch.Tensor:
        vi = v[:, self.nodes]
        v[:, self.nodes] = vi - (vi * self.normals).sum(0) * self.normals
        return v


@dataclass(frozen=True, eq=False)
class SeparatingSlip:
    """Nodes that may leave the wall freely but not enter it, with Coulomb friction."""

    nodes: torch.Tensor
    normals: torch.Tensor
    friction: float = 0.0

    def apply(self, v: torch.Tensor) -> torch.Tensor:
        vi = v[:, self.nodes]
        vn = (vi * self.normals).sum(0)
        tangential = vi - vn * self.normals
        speed = tangential.norm(dim=0)
        scale = torch.clamp(1.0 - self.friction * vn / torch.clamp(speed, min=1e-300), min=0.0)
        v[:, self.nodes] = torch.where(vn > 0, scale * tangential, vi)
        return v


@dataclass(frozen=True, eq=False)
class Mirror:
    """Ghost nodes beyond a sticky wall: v_ghost = -sum_k B_k v_k, the velocity interpolated at
    the ghost's reflection across the wall, negated (the odd extension of a field that
    vanishes on the wall).

    ghosts: (m,) int64; sources: (m, s) the nodes interpolating the velocity at each reflection
    (a mesh: the d+1 nodes of the physical cell holding it; a grid: the 2^d nodes around it);
    weights: (m, s) their interpolation weights there (barycentric / multilinear). n_outside:
    ghosts whose reflection fell outside the physical domain (held at rest; not listed here).
    wall: (w,) int64 the physical nodes on the wall, their own mirror images, for a folded
    mirror; None: the ghosts' velocities are only overwritten after the update (no fold).

    A folded mirror's ghosts are slaved to their sources: the solver folds their P2G sums back
    onto the sources before the velocity update (:meth:`fold`, the transpose of ``apply``; see
    :func:`fold_mirrors`) and mirrors the velocities before the update too (:func:`apply_mirrors`).
    """

    ghosts: torch.Tensor
    sources: torch.Tensor
    weights: torch.Tensor
    n_outside: int = 0
    wall: torch.Tensor | None = None

    def apply(self, v: torch.Tensor) -> torch.Tensor:
        v[:, self.ghosts] = -(v[:, self.sources] * self.weights).sum(-1)
        return v

    def fold(self, values: torch.Tensor, parity: torch.Tensor) -> torch.Tensor:
        """Add each ghost's node sums to its sources, parity * B_k times, and clear the ghost.

        values: (c, N) P2G sums, modified in place; parity: (c,) +1 for fields even about the
        wall (mass), -1 for odd ones (momentum, force), as ``apply`` extends the velocity.
        """
        ghost = values[:, self.ghosts] * parity[:, None]  # (c, m)
        share = ghost[:, :, None] * self.weights[None]  # (c, m, s)
        values.index_add_(1, self.sources.reshape(-1), share.reshape(values.shape[0], -1))
        values[:, self.ghosts] = 0.0
        return values


WALL_KINDS = {"sticky", "slip", "separating"}


@dataclass(frozen=True)
class Wall:
    """A wall on the part of the domain boundary picked by ``where``.

    where(points (n, d), normals (n, d)) -> (n,) bool, given boundary facet centroids and
    outward normals (mesh) or points on the box faces and their normals (grid).
    mirror: for ``sticky`` walls on a mesh with an extra layer (or on a grid), make the nodes
    beyond the wall mirror ghosts (:class:`Mirror`) rather than holding them at rest.
    fold: with ``mirror``, fold the ghosts' P2G sums onto the nodes they mirror
    (:func:`fold_mirrors`: the body sees its odd mirror image, the clamp sits on the wall to
    second order; the default); False only overwrites the ghosts' velocities after the update
    (the clamp then sits about 0.07 h beyond the wall).
    """

    kind: str
    where: Callable[[np.ndarray, np.ndarray], np.ndarray]
    friction: float = 0.0
    mirror: bool = True
    fold: bool = True

    def __post_init__(self):
        if self.kind not in WALL_KINDS:
            raise ValueError(f"wall kind must be one of {sorted(WALL_KINDS)}, got {self.kind!r}")


@dataclass(frozen=True)
class Clamp:
    """Every background node with ``where(points (n, d)) -> (n,) bool`` true is held at rest."""

    where: Callable[[np.ndarray], np.ndarray]


def _condition(kind: str, nodes: np.ndarray, normals: np.ndarray, friction: float, device, dtype):
    nodes_t = torch.as_tensor(nodes, dtype=torch.int64, device=device)
    normals_t = torch.as_tensor(np.ascontiguousarray(np.asarray(normals).T), dtype=dtype, device=device)
    if kind == "sticky":
        return Sticky(nodes_t)
    if kind == "slip":
        return Slip(nodes_t, normals_t)
    return SeparatingSlip(nodes_t, normals_t, float(friction))


def _wall_nodes(domain: Mesh, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) mask of the physical nodes on the chosen facets and their (N, d) summed outward normals
    (facet-measure weighted; zero off the wall)."""
    facets = domain.boundary_facets[chosen]
    weighted = domain.boundary_normals[chosen] * domain.boundary_facet_measures[chosen, None]
    acc = np.zeros_like(domain.nodes)
    for j in range(facets.shape[1]):
        np.add.at(acc, facets[:, j], weighted)
    on_wall = np.zeros(domain.n_nodes, dtype=bool)
    on_wall[facets.ravel()] = True
    return on_wall, acc


def _extend_to_layer(extended: ExtendedMesh, on_wall: np.ndarray, acc: np.ndarray):
    """Wall membership and normals of every node of the extended mesh.

    A node of the extra layer belongs to a wall when it shares an edge with a physical node
    of that wall, and takes the mean of their normals; this needs nothing of how the layer was
    built. (At a corner of two walls, layer nodes next to the corner node get both.)
    """
    n = on_wall.size
    adj = extended.mesh.adjacency()
    to_physical = adj[n:, :n].tocsr()
    member = np.concatenate([on_wall, (to_physical @ on_wall.astype(float)) > 0])
    layer_acc = to_physical @ acc
    # A layer node next to opposite faces of one wall (e.g. both slip walls of a strip one or
    # two cells high) gets normals that cancel: it takes its nearest wall neighbour's instead.
    size = np.linalg.norm(layer_acc, axis=1)
    scale = np.asarray(to_physical @ np.linalg.norm(acc, axis=1)).ravel()
    for row in np.flatnonzero(member[n:] & (size <= 1e-6 * scale)):
        cols = to_physical.indices[to_physical.indptr[row]:to_physical.indptr[row + 1]]
        cols = cols[on_wall[cols]]
        gap = np.linalg.norm(extended.mesh.nodes[cols] - extended.mesh.nodes[n + row], axis=1)
        layer_acc[row] = acc[cols[np.argmin(gap)]]
    return member, np.concatenate([acc, layer_acc])


def _mirror(domain: Mesh, extended: ExtendedMesh, on_wall: np.ndarray, ghosts: np.ndarray,
            normals: np.ndarray, locator: CellLocator, device, dtype, fold: bool = False) -> Mirror:
    """Mirror ghosts for the layer nodes ``ghosts`` of one sticky wall (physical nodes ``on_wall``).

    Each ghost is reflected across the plane through the mean of its neighbours on the wall,
    with its (unit) wall normal; a corner copy, whose only wall neighbour is the corner, is
    thus reflected through the corner. Reflections are located in the physical mesh.
    """
    n = domain.n_nodes
    adj = extended.mesh.adjacency()[ghosts][:, :n].multiply(on_wall[None, :].astype(float)).tocsr()
    count = np.asarray(adj.sum(axis=1)).ravel()
    anchor = (adj @ domain.nodes) / np.maximum(count, 1)[:, None]
    x = extended.mesh.nodes[ghosts]
    beyond = ((x - anchor) * normals).sum(1)
    reflected = x - 2.0 * beyond[:, None] * normals
    where = locate(locator, torch.as_tensor(reflected, dtype=dtype, device=locator.corner.device))
    inside = (where.status == int(LocateStatus.INSIDE)).cpu().numpy() & (count > 0)
    cells = torch.tensor(domain.cells, dtype=torch.int64, device=device)
    keep = torch.as_tensor(np.flatnonzero(inside), dtype=torch.int64, device=where.cell.device)
    return Mirror(
        ghosts=torch.as_tensor(ghosts[inside], dtype=torch.int64, device=device),
        sources=cells[where.cell[keep].to(device)],
        weights=where.bary[keep].to(device=device, dtype=dtype),
        n_outside=int((~inside).sum()),
        wall=torch.as_tensor(np.flatnonzero(on_wall), dtype=torch.int64, device=device) if fold else None,
    )


def mesh_conditions(domain: Mesh, extended: ExtendedMesh | None, walls, clamps, *,
                    device="cpu", dtype=torch.float64) -> list:
    """Conditions on the background nodes of ``domain`` (+ its extra layer, if given).

    ``extended`` must number the physical nodes first, as ``with_extra_layer`` does. The layer
    nodes of a sticky wall are held at rest in the wall's turn and, unless the wall says
    ``mirror=False``, overwritten as mirror ghosts after all other conditions.
    """
    centroids = domain.nodes[domain.boundary_facets].mean(axis=1)
    whole = extended.mesh if extended is not None else domain
    out, mirrors, locator = [], [], None
    for wall in walls:
        chosen = np.asarray(wall.where(centroids, domain.boundary_normals), dtype=bool)
        on_wall, acc = _wall_nodes(domain, chosen)
        member = on_wall
        if extended is not None:
            member, acc = _extend_to_layer(extended, on_wall, acc)
        nodes = np.flatnonzero(member)
        normals = acc[nodes] / np.linalg.norm(acc[nodes], axis=1, keepdims=True)
        out.append(_condition(wall.kind, nodes, normals, wall.friction, device, dtype))
        layer = nodes >= domain.n_nodes
        if wall.kind == "sticky" and wall.mirror and extended is not None and layer.any():
            locator = locator or CellLocator.build(domain, device=device, dtype=dtype)
            mirrors.append(_mirror(domain, extended, on_wall, nodes[layer], normals[layer], locator, device, dtype,
                                   fold=wall.fold))
    for clamp in clamps:
        nodes = np.flatnonzero(np.asarray(clamp.where(whole.nodes), dtype=bool))
        out.append(Sticky(torch.as_tensor(nodes, dtype=torch.int64, device=device)))
    return out + mirrors


def grid_conditions(grid: Grid, lower, upper, walls, clamps, *, device="cpu", dtype=torch.float64) -> list:
    """Conditions on a grid covering the box [lower, upper]: wall nodes are those on or beyond a face."""
    nodes = grid.nodes()
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    tol = 1e-9 * grid.spacing
    faces = []  # (node ids, normal) per box face
    for axis in range(grid.dim):
        low, high = nodes[:, axis] <= lower[axis] + tol, nodes[:, axis] >= upper[axis] - tol
        for sign, beyond in ((-1.0, low), (1.0, high)):
            normal = np.zeros(grid.dim)
            normal[axis] = sign
            faces.append((np.flatnonzero(beyond), normal))
    out, mirrors = [], []
    for wall in walls:
        for ids, normal in faces:
            on_face = np.clip(nodes[ids], lower, upper)
            normals = np.broadcast_to(normal, on_face.shape)
            chosen = ids[np.asarray(wall.where(on_face, normals), dtype=bool)]
            if chosen.size:
                chosen_normals = normals[: chosen.size]
                out.append(_condition(wall.kind, chosen, chosen_normals, wall.friction, device, dtype))
                if wall.kind == "sticky" and wall.mirror:
                    mirror = _grid_mirror(grid, nodes, chosen, normal, lower, upper, tol, wall.fold, device, dtype)
                    if mirror is not None:
                        mirrors.append(mirror)
    for clamp in clamps:
        ids = np.flatnonzero(np.asarray(clamp.where(nodes), dtype=bool))
        out.append(Sticky(torch.as_tensor(ids, dtype=torch.int64, device=device)))
    return out + mirrors


def _grid_mirror(grid: Grid, nodes: np.ndarray, chosen: np.ndarray, normal: np.ndarray, lower, upper, tol: float,
                 fold: bool, device, dtype) -> Mirror | None:
    """Mirror ghosts for the grid nodes of a sticky box face beyond it: each reflects across the
    face's plane and takes minus the multilinear interpolation of the velocity there (the nodes
    on the plane are the wall). Ghosts whose stencil is not all inside the box stay at rest."""
    axis = int(np.flatnonzero(normal)[0])
    plane = upper[axis] if normal[axis] > 0 else lower[axis]
    beyond = chosen[np.abs(nodes[chosen, axis] - plane) > tol]
    wall = chosen[np.abs(nodes[chosen, axis] - plane) <= tol]
    if beyond.size == 0:
        return None
    reflected = nodes[beyond].copy()
    reflected[:, axis] = 2.0 * plane - reflected[:, axis]
    scaled = (reflected - np.asarray(grid.origin)) / grid.spacing
    base = np.floor(scaled + 1e-9).astype(np.int64)
    frac = np.clip(scaled - base, 0.0, 1.0)
    frac[frac < 1e-9] = 0.0
    corners = np.array(np.meshgrid(*[[0, 1]] * grid.dim, indexing="ij")).reshape(grid.dim, -1).T  # (2^d, d)
    index = base[:, None, :] + corners[None]  # (m, 2^d, d)
    weights = np.prod(np.where(corners[None] == 1, frac[:, None, :], 1.0 - frac[:, None, :]), axis=-1)
    shape = np.asarray(grid.shape)
    index = np.clip(index, 0, shape - 1)
    position = np.asarray(grid.origin) + grid.spacing * index
    inside = ((position >= lower - tol) & (position <= upper + tol)).all(-1) | (weights == 0)
    keep = inside.all(axis=1)
    strides = np.array([int(np.prod(shape[k + 1:])) for k in range(grid.dim)])
    as_t = lambda a, dt: torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=device)  # noqa: E731
    return Mirror(
        ghosts=as_t(beyond[keep], torch.int64), sources=as_t((index[keep] * strides).sum(-1), torch.int64),
        weights=as_t(weights[keep], dtype), n_outside=int((~keep).sum()),
        wall=as_t(wall, torch.int64) if fold else None,
    )


def apply_conditions(v: torch.Tensor, conditions) -> torch.Tensor:
    """Apply every condition in order to nodal velocities ``v: (d, N)`` (modified in place)."""
    for condition in conditions:
        v = condition.apply(v)
    return v


def fold_mirrors(values: torch.Tensor, conditions, parity) -> torch.Tensor:
    """Fold the P2G node sums of every :class:`Mirror` among ``conditions`` onto the nodes it mirrors.

    values: (c, N) sums over particles (mass, momentum, force), modified in place and returned;
    parity: (c,) +1 for the rows even about the wall (mass), -1 for the odd ones (momentum, force).
    Mirrors without ``wall`` (``Wall(..., fold=False)``) are left alone.

    A ghost's velocity is slaved to its sources (v_g = -sum_k B_k v_k), so the sums the particles
    scatter to it belong to them: m_k += B_k m_g, p_k -= B_k p_g, f_k -= B_k f_g (the transpose
    of the constraint, row-sum lumped). A wall node is its own mirror image, so its odd sums
    cancel (p = f = 0). This is the odd reflection of the body across the wall: in 1D with the
    wall on a node the sums equal those of the body plus its mirror image exactly. Overwriting
    the ghosts after the update instead, with their sums dropped, leaves the nodes next to the
    wall without the mirror's share of the force while the particles' strain still sees the
    ghosts' velocities: the fixed end of the vibrating bar then sits about 0.07 h beyond the
    wall (a frequency error linear in h) and FLIP gains energy there.
    """
    mirrors = _folded(conditions)
    if not mirrors:
        return values
    parity = torch.as_tensor(parity, dtype=values.dtype, device=values.device)
    for mirror in mirrors:
        mirror.fold(values, parity)
    odd = (parity < 0).nonzero()[:, 0]
    for mirror in mirrors:
        values[odd[:, None], mirror.wall[None, :]] = 0.0
    return values


def apply_mirrors(v: torch.Tensor, conditions) -> torch.Tensor:
    """Apply the folded :class:`Mirror` conditions among ``conditions`` to ``v: (d, N)`` (in place)."""
    for mirror in _folded(conditions):
        v = mirror.apply(v)
    return v


def _folded(conditions) -> list[Mirror]:
    return [c for c in conditions if isinstance(c, Mirror) and c.wall is not None]
