"""The holes of a 2D triangle mesh and the pin that fits one (the pendulum's given plates).

A hole is a closed boundary loop that runs clockwise (:attr:`datagen.mesh.Mesh.boundary_facets`
keeps the domain on the left: outer boundaries run counter-clockwise, holes clockwise). The pin
that fits a hole is the largest disk centred inside it with no node of the mesh inside it
(:func:`largest_disk`): the material points of an MPM body are its nodes, so that is the largest
rigid pin the body's particles leave room for -- for a hole whose nodes lie on a circle, that
circle, as the pendulum family drills its holes. How far such a pin could move about in the hole
is its :func:`play`.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import QhullError, Voronoi, cKDTree

from .config import ConfigError
from .mesh import Mesh

__all__ = ["clearance", "boundary_loops", "holes", "signed_area", "largest_disk", "edge_depth", "play"]

GRID = 41  # extra candidate centres per axis over a hole's bounding box (where no Voronoi vertex lies inside)
PLAY_GRID = 161  # candidate centres per axis of the pin's play


def clearance(ring: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) the distance from each of ``points`` (P, 2) to the closed outline ``ring`` (K, 2), negative
    outside it (even-odd rule)."""
    a, b = ring[None], np.roll(ring, -1, axis=0)[None]
    ab, ap = b - a, points[:, None] - a
    t = np.clip((ap * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    distance = np.linalg.norm(ap - t[..., None] * ab, axis=-1).min(1)
    y = points[:, 1:2]
    crosses = (a[..., 1] > y) != (b[..., 1] > y)
    at = a[..., 0] + (y - a[..., 1]) * ab[..., 0] / np.where(crosses, ab[..., 1], 1.0)
    inside = np.count_nonzero(crosses & (points[:, :1] < at), axis=1) % 2 == 1
    return np.where(inside, distance, -distance)


def signed_area(ring: np.ndarray) -> float:
    """The area enclosed by the closed ring (K, 2), positive where it runs counter-clockwise."""
    x, y = ring.T
    return 0.5 * float(x @ np.roll(y, -1) - y @ np.roll(x, -1))


def boundary_loops(mesh: Mesh) -> list[np.ndarray]:
    """Each closed boundary loop of the 2D triangle mesh as its node indices in order, the mesh on
    their left; ConfigError where the boundary touches itself at a node (two loops through it)."""
    following: dict[int, int] = {}
    for a, b in mesh.boundary_facets.tolist():
        if a in following:
            raise ConfigError(f"the mesh's boundary passes twice through node {a} (at "
                              f"{np.round(mesh.nodes[a], 6).tolist()}): two pieces or a hole touch there; mesh the "
                              "plate so that its outline and its holes are apart")
        following[a] = b
    loops, seen = [], set()
    for start in following:
        if start in seen:
            continue
        loop, node = [], start
        while node not in seen:
            seen.add(node)
            loop.append(node)
            node = following[node]
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def holes(mesh: Mesh) -> list[np.ndarray]:
    """The mesh's holes (its clockwise boundary loops), largest enclosed area first."""
    found = [loop for loop in boundary_loops(mesh) if signed_area(mesh.nodes[loop]) < 0]
    return sorted(found, key=lambda loop: signed_area(mesh.nodes[loop]))


def _candidates(ring: np.ndarray) -> np.ndarray:
    """Centres to try inside the hole ``ring``: the Voronoi vertices of its nodes (where the largest
    empty disk among them is centred), its nodes' mean and a grid over its bounding box."""
    points = [ring.mean(0, keepdims=True)]
    try:
        points.append(Voronoi(ring).vertices)
    except (QhullError, ValueError):  # fewer than four nodes or all on a line: the grid alone
        pass
    axes = [np.linspace(lo, hi, GRID) for lo, hi in zip(ring.min(0), ring.max(0), strict=True)]
    points.append(np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], 1))
    points = np.concatenate(points)
    return points[clearance(ring, points) > 0]


def largest_disk(mesh: Mesh, loop: np.ndarray) -> tuple[np.ndarray, float]:
    """The centre (2,) and radius of the largest disk centred inside the hole ``loop`` (node indices)
    with no node of ``mesh`` inside it."""
    points = _candidates(mesh.nodes[loop])
    if not len(points):
        raise ConfigError("a hole of the mesh encloses no area")
    radius, _ = cKDTree(mesh.nodes).query(points)
    best = int(np.argmax(radius))
    return points[best], float(radius[best])


def edge_depth(mesh: Mesh, loop: np.ndarray, centre: np.ndarray, radius: float) -> float:
    """How far the disk (``centre``, ``radius``) reaches past the hole's straight edges (0 where it
    stays inside them): the pin of a hole meshed as a polygon through its nodes crosses its chords."""
    return max(0.0, radius - float(np.abs(clearance(mesh.nodes[loop], np.asarray(centre)[None]))[0]))


def play(mesh: Mesh, loop: np.ndarray, centre: np.ndarray, radius: float, overlap: float) -> float:
    """How far the pin (``centre``, ``radius``) can move about in the hole ``loop`` with no node of the
    mesh deeper than ``overlap`` inside it: the largest distance from ``centre`` to a point of the
    region (connected to it) where a pin of that radius overlaps the plate's nodes by ``overlap`` at
    most, on a grid of PLAY_GRID points a side over the hole's bounding box (0: a snug fit)."""
    ring = mesh.nodes[loop]
    lower, upper = ring.min(0), ring.max(0)
    axes = [np.linspace(lo, hi, PLAY_GRID) for lo, hi in zip(lower, upper, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    free = cKDTree(mesh.nodes).query(grid)[0] >= radius - overlap
    free[free] = clearance(ring, grid[free]) > 0
    free = free.reshape(PLAY_GRID, PLAY_GRID)
    labels, _ = ndimage.label(free)
    step = (upper - lower) / (PLAY_GRID - 1)
    home = tuple(np.clip(np.round((np.asarray(centre) - lower) / step).astype(int), 0, PLAY_GRID - 1))
    if not labels[home]:
        return 0.0
    reach = np.linalg.norm(grid[labels.reshape(-1) == labels[home]] - centre, axis=1)
    return float(reach.max())
