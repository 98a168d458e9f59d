"""How far moving obstacles reach into a body: the node input of ``graph.penetration``.

A driven obstacle (an indenter, a punch) imposes where the body's surface must go; a graph
network told only where the obstacle's surface nodes are has to work out, from offsets to a
few of them, which body nodes lie inside the obstacle and how far. This module computes it
outright: for every node and every closed obstacle outline that is not a container (the
walls around the body), whether the node lies inside the outline where the obstacle will be
at the coming frame (winding number), and if so the vector to the nearest point of the outline
-- the displacement that would put the node back on the obstacle's surface, the kinematic
boundary condition of contact. Nodes outside every obstacle get 0.

Outlines are the connected components of the (subdivided) obstacle facets -- segments in 2D,
triangles in 3D; a component is a container when it encloses most of the body's rest nodes
(the box's walls), and it is then left out: a body is inside its container by design.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from bsms.graph.obstacles import KeptTree

__all__ = ["Penetration", "Clearance", "outlines", "winding_numbers", "inside_outline", "closest_points",
           "solid_winding_numbers", "closest_points_3d", "closest_on_facets"]


def winding_numbers(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,) winding number of the closed outline made of segments a[s] -> b[s] (S, 2) around each
    of ``points`` (P, 2): the sum of the signed angles the segments subtend, over 2 pi
    (+-1 inside a simple closed outline whatever its orientation's sign, 0 outside)."""
    u = a[None, :, :] - points[:, None, :]
    v = b[None, :, :] - points[:, None, :]
    cross = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    dot = (u * v).sum(-1)
    return np.arctan2(cross, dot).sum(1) / (2 * np.pi)


def inside_outline(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,) bool: whether each of ``points`` (P, 2) lies inside the closed outline of segments
    a[s] -> b[s] (S, 2), by the even-odd rule (a ray to +x crosses it an odd number of times;
    half-open in y, so a ray through a corner counts it once). For a simple outline this is
    ``abs(winding_numbers(...)) > 0.5`` at a seventh of its cost (no angles)."""
    py, ay, by = points[:, None, 1], a[None, :, 1], b[None, :, 1]
    straddles = (ay > py) != (by > py)
    rise = np.where(straddles, by - ay, 1.0)  # where it does not straddle the crossing is not used
    x = a[None, :, 0] + (py - ay) * (b[None, :, 0] - a[None, :, 0]) / rise
    return (straddles & (points[:, None, 0] < x)).sum(1) % 2 == 1


def _on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, S, d): the point of each segment a[s]-b[s] (S, d) nearest each point p (P, 1, d)."""
    ab = b - a
    length2 = np.maximum((ab * ab).sum(-1), np.finfo(float).tiny)
    t = np.clip(((p - a[None]) * ab[None]).sum(-1) / length2, 0.0, 1.0)  # (P, S)
    return a[None] + t[..., None] * ab[None]


# outlines with more segments than this are searched through a tree of their midpoints
PRUNE_SEGMENTS = 32


def closest_points(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, 2) the point of the segments a[s]-b[s] (S, 2) nearest each of ``points`` (P, 2) (of
    equally near segments, the first). Long outlines are pruned first, exactly: a point whose
    nearest segment midpoint is d away is within d of its nearest segment, so only segments whose
    midpoint lies within d + (longest segment) / 2 of it can be nearer."""
    if len(a) <= PRUNE_SEGMENTS or not len(points):
        candidates = _on_segments(points[:, None, :], a, b)
        nearest = ((candidates - points[:, None, :]) ** 2).sum(-1).argmin(1)
        return candidates[np.arange(len(points)), nearest]
    tree = cKDTree(0.5 * (a + b))
    reach = tree.query(points)[0] + 0.5 * np.sqrt(((b - a) ** 2).sum(-1).max()) * (1 + 1e-12)
    near = tree.query_ball_point(points, reach)
    counts = np.fromiter(map(len, near), np.int64, len(points))
    owner, segment = np.repeat(np.arange(len(points)), counts), np.concatenate(near).astype(np.int64)
    p, start, ab = points[owner], a[segment], b[segment] - a[segment]
    t = np.clip(((p - start) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), np.finfo(float).tiny), 0.0, 1.0)
    candidates = start + t[:, None] * ab
    order = np.lexsort((segment, ((candidates - p) ** 2).sum(-1), owner))  # by point, distance, segment
    return candidates[order[np.cumsum(counts) - counts]]


def solid_winding_numbers(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(P,) winding number of the closed surface of triangles (a, b, c)[s] (S, 3) around each of
    ``points`` (P, 3): the sum of the signed solid angles the triangles subtend (van Oosterom and
    Strackee's formula), over 4 pi (+-1 inside a closed surface, 0 outside)."""
    u, v, w = (x[None, :, :] - points[:, None, :] for x in (a, b, c))
    lu, lv, lw = (np.linalg.norm(x, axis=-1) for x in (u, v, w))
    triple = (u * np.cross(v, w)).sum(-1)
    below = lu * lv * lw + (u * v).sum(-1) * lw + (v * w).sum(-1) * lu + (w * u).sum(-1) * lv
    return 2 * np.arctan2(triple, below).sum(1) / (4 * np.pi)


def closest_points_3d(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(P, 3) the point of the triangles (a, b, c)[s] (S, 3) nearest each of ``points`` (P, 3): the
    nearest of each triangle's interior projection (where it falls inside) and of its edges."""
    p = points[:, None, :]
    normal = np.cross(b - a, c - a)
    unit = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), np.finfo(float).tiny)
    projected = p - ((p - a[None]) * unit[None]).sum(-1, keepdims=True) * unit[None]  # (P, S, 3)
    inside = np.ones(projected.shape[:2], bool)
    for x, y in ((a, b), (b, c), (c, a)):  # on the inner side of every edge
        inside &= (np.cross(y - x, projected - x[None]) * normal[None]).sum(-1) >= 0
    candidates, distances = [], []
    for x, y in ((a, b), (b, c), (c, a)):
        on_edge = _on_segments(p, x, y)
        candidates.append(on_edge)
        distances.append(((on_edge - p) ** 2).sum(-1))
    candidates.append(projected)
    distances.append(np.where(inside, ((projected - p) ** 2).sum(-1), np.inf))
    candidates, distances = np.stack(candidates, 2), np.stack(distances, 2)  # (P, S, 4, 3), (P, S, 4)
    flat = distances.reshape(len(points), -1).argmin(1)
    return candidates.reshape(len(points), -1, 3)[np.arange(len(points)), flat]


def _inside(points, corners) -> np.ndarray:
    if len(corners) == 2:
        return inside_outline(points, *corners)
    return np.abs(solid_winding_numbers(points, *corners)) > 0.5


def closest_on_facets(points: np.ndarray, corners: list[np.ndarray]) -> np.ndarray:
    """(P, d) the point of the facets whose corners are ``corners`` (d arrays (S, d): segments in
    2D, triangles in 3D) nearest each of ``points`` (P, d)."""
    return closest_points(points, *corners) if len(corners) == 2 else closest_points_3d(points, *corners)


def outlines(rest: np.ndarray, facets: np.ndarray, n_body: int,
             what: str = "graph.penetration") -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The closed obstacle outlines of ``facets`` (F, d) (segments in 2D, triangles in 3D, in
    scenario node indices; ``rest`` (N, d) of all scenario nodes, the first ``n_body`` the body's):
    (obstacles, containers), each a list of the facets of one connected component; a component
    is a container when it encloses most of the body's rest nodes (the walls around the body).
    ValueError naming ``what`` (the option that asked) where the facets do not fit the dimension."""
    dim = rest.shape[1]
    facets = np.asarray(facets, np.int64)
    facets = facets.reshape(len(facets), -1) if facets.size else np.zeros((0, dim), np.int64)
    if dim not in (2, 3) or (len(facets) and facets.shape[1] != dim):
        raise ValueError(f"{what} needs closed obstacle outlines of {dim}-node facets in a {dim}D scene (segments "
                         f"in 2D, triangles in 3D), got facets of {facets.shape[1]} nodes")
    obstacles, containers = [], []
    if len(facets) == 0:
        return obstacles, containers
    n = len(rest)
    pairs = np.concatenate([facets[:, [i, (i + 1) % dim]] for i in range(dim)])
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    body = rest[:n_body][:: max(1, n_body // 256)]  # enough of them to tell a container
    for label in np.unique(labels[facets[:, 0]]):
        outline = facets[labels[facets[:, 0]] == label]
        inside = _inside(body, [rest[outline[:, i]] for i in range(dim)])
        (containers if inside.mean() > 0.5 else obstacles).append(outline)
    return obstacles, containers


class Penetration:
    """The penetration input of one scenario.

    rest: (N, d) rest positions of all scenario nodes; facets: (F, d) obstacle segments (2D) or
    triangles (3D) in scenario node indices; n_body: body node count (nodes before it are the
    body's)."""

    def __init__(self, rest: np.ndarray, facets: np.ndarray, n_body: int):
        self.outlines, _ = outlines(rest, facets, n_body)

    def __call__(self, pos: np.ndarray, coming: np.ndarray, free: np.ndarray) -> np.ndarray:
        """(N, d): for free nodes at ``pos`` inside an obstacle outline placed at ``coming`` (N, d:
        where every node will be at the coming frame; only obstacle rows are read), the vector to
        the outline's nearest point; 0 elsewhere."""
        out = np.zeros_like(pos, dtype=np.float64)
        points = np.flatnonzero(free)
        for outline in self.outlines:
            corners = [coming[outline[:, i]] for i in range(outline.shape[1])]
            low, high = coming[outline.ravel()].min(0), coming[outline.ravel()].max(0)
            near = points[np.all((pos[points] >= low) & (pos[points] <= high), axis=1)]  # only these can be inside
            inside = near[_inside(pos[near], corners)]
            if not len(inside):
                continue
            out[inside] += closest_on_facets(pos[inside], corners) - pos[inside]
        return out


class Clearance:
    """The clearance input of one scenario (``graph.clearance``): where the container's walls are,
    per node, in place of the container's nodes and contact edges.

    rest: (N, d) rest positions of all scenario nodes; facets: (F, d) obstacle facets in scenario
    node indices; n_body: body node count; radius: the contact radius. ``excluded``: the scenario
    nodes of the container (the obstacle nodes a frame's graph leaves out)."""

    def __init__(self, rest: np.ndarray, facets: np.ndarray, n_body: int, radius: float):
        _, containers = outlines(rest, facets, n_body, "graph.clearance")
        self.radius = float(radius)
        self.facets = np.concatenate(containers) if containers else np.zeros((0, rest.shape[1]), np.int64)
        self.excluded = np.unique(self.facets)
        self._walls = KeptTree()  # of the container's nodes
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (key, free, out) of the last call

    def __call__(self, pos: np.ndarray, free: np.ndarray) -> np.ndarray:
        """(N, d): for free nodes at ``pos`` (all scenario nodes, the container's included) within
        the contact radius of the container, the vector to its nearest point; 0 elsewhere. The
        last answer is kept, keyed by what it depends on (the free nodes and the container, not the
        moving obstacles): frames from rest (``graph.from_rest``) ask the same every time."""
        key = np.concatenate([pos[free], pos[self.excluded]]) if len(self.facets) else np.zeros((0, pos.shape[1]))
        if self._last is not None and np.array_equal(self._last[1], free) and np.array_equal(self._last[0], key):
            return self._last[2].copy()
        out = np.zeros_like(pos, dtype=np.float64)
        if len(self.facets):
            corners = [pos[self.facets[:, i]] for i in range(self.facets.shape[1])]
            sides = zip(corners, corners[1:] + corners[:1], strict=True)
            size = max(np.linalg.norm(a - b, axis=1).max() for a, b in sides)  # the longest facet edge
            bound = self.radius + size  # a point within the radius of a facet: this near its corners and middle
            points = np.flatnonzero(free)
            distance, _ = self._walls(pos[self.excluded]).query(pos[points], distance_upper_bound=bound)
            near = points[np.isfinite(distance)]
            if len(near):
                reach, _ = cKDTree(pos[near]).query(sum(corners) / len(corners), distance_upper_bound=bound)
                facets = np.isfinite(reach)  # only the facets within reach of these nodes
                offset = closest_on_facets(pos[near], [c[facets] for c in corners]) - pos[near]
                close = np.linalg.norm(offset, axis=1) <= self.radius
                out[near[close]] = offset[close]
        self._last = (key, np.array(free, copy=True), out.copy())
        return out
