"""How far moving obstacles reach into a body: the node input of ``graph.penetration``.

A driven obstacle (an indenter, a punch) imposes where the body's surface must go; a graph
network told only where the obstacle's surface nodes are has to work out, from offsets to a
few of them, which body nodes lie inside the obstacle and how far. This module computes it
outright: for every node and every closed obstacle outline that is not a container (the
walls around the body), whether the node lies inside the outline where the obstacle will be
at the coming frame (winding number), and if so the vector to the nearest point of the outline
-- the displacement that would put the node back on the obstacle's surface, the kinematic
boundary condition of contact. Nodes outside every obstacle get 0.

Outlines are the connected components of the (subdivided) obstacle facets; a component is a
container when it encloses most of the body's rest nodes (the box's walls), and it is then
left out: a body is inside its container by design. 2D (segment outlines) only.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

__all__ = ["Penetration", "winding_numbers", "closest_points"]


def winding_numbers(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,) winding number of the closed outline made of segments a[s] -> b[s] (S, 2) around each
    of ``points`` (P, 2): the sum of the signed angles the segments subtend, over 2 pi
    (+-1 inside a simple closed outline whatever its orientation's sign, 0 outside)."""
    u = a[None, :, :] - points[:, None, :]
    v = b[None, :, :] - points[:, None, :]
    cross = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    dot = (u * v).sum(-1)
    return np.arctan2(cross, dot).sum(1) / (2 * np.pi)


def closest_points(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, 2) the point of the segments a[s]-b[s] (S, 2) nearest each of ``points`` (P, 2)."""
    ab = b - a
    length2 = np.maximum((ab * ab).sum(-1), np.finfo(float).tiny)
    t = np.clip(((points[:, None, :] - a[None]) * ab[None]).sum(-1) / length2, 0.0, 1.0)  # (P, S)
    candidates = a[None] + t[..., None] * ab[None]
    nearest = ((candidates - points[:, None, :]) ** 2).sum(-1).argmin(1)
    return candidates[np.arange(len(points)), nearest]


class Penetration:
    """The penetration input of one scenario.

    rest: (N, 2) rest positions of all scenario nodes; facets: (F, 2) obstacle segments in
    scenario node indices; n_body: body node count (nodes before it are the body's)."""

    def __init__(self, rest: np.ndarray, facets: np.ndarray, n_body: int):
        if rest.shape[1] != 2:
            raise ValueError(f"graph.penetration is built for 2D scenes (closed segment outlines); this scene is "
                             f"{rest.shape[1]}D: set graph.penetration: false")
        facets = np.asarray(facets, np.int64).reshape(-1, 2)
        n = len(rest)
        self.outlines: list[np.ndarray] = []
        if len(facets) == 0:
            return
        graph = sparse.coo_matrix((np.ones(len(facets)), (facets[:, 0], facets[:, 1])), shape=(n, n))
        _, labels = connected_components(graph, directed=False)
        body = rest[:n_body]
        for label in np.unique(labels[facets[:, 0]]):
            outline = facets[labels[facets[:, 0]] == label]
            inside = np.abs(winding_numbers(body, rest[outline[:, 0]], rest[outline[:, 1]])) > 0.5
            if inside.mean() <= 0.5:  # not a container
                self.outlines.append(outline)

    def __call__(self, pos: np.ndarray, coming: np.ndarray, free: np.ndarray) -> np.ndarray:
        """(N, 2): for free nodes at ``pos`` inside an obstacle outline placed at ``coming`` (N, 2:
        where every node will be at the coming frame; only obstacle rows are read), the vector to
        the outline's nearest point; 0 elsewhere."""
        out = np.zeros_like(pos, dtype=np.float64)
        points = np.flatnonzero(free)
        for outline in self.outlines:
            a, b = coming[outline[:, 0]], coming[outline[:, 1]]
            low, high = np.minimum(a, b).min(0), np.maximum(a, b).max(0)
            near = points[np.all((pos[points] >= low) & (pos[points] <= high), axis=1)]  # only these can be inside
            inside = near[np.abs(winding_numbers(pos[near], a, b)) > 0.5]
            if len(inside):
                out[inside] += closest_points(pos[inside], a, b) - pos[inside]
        return out
