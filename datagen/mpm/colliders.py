"""Moving rigid obstacles (kinematic colliders) that act on the material through the background nodes.

A :class:`Collider` is a rigid shape (2D: disk, box, wedge; 3D: sphere, box) translated along a
prescribed piecewise-linear :class:`Path`. Each step, every background node that carries mass
and lies inside the collider at the start of the step (signed distance phi <= 0) gets separating
contact with Coulomb friction relative to the collider's velocity u over the step: with
w = v - u and n the collider's outward normal there, a node moving into the collider
(w.n < 0) loses the normal part of w and its tangential part shrinks by mu |w.n| (down to
zero); a node moving out of it is left alone. This is the ``separating`` wall of
:mod:`~datagen.mpm.boundary` seen from the collider's own frame, so the material may leave the
obstacle freely but never sticks to it (:func:`~datagen.mpm.nodal.constrain` applies it).

Lengths are in metres, times in seconds, velocities in m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import ConvexHull

__all__ = ["Path", "Collider", "SHAPES"]

SHAPES = {2: ("disk", "box", "wedge"), 3: ("sphere", "box")}
_SIZES = {  # shape -> (number of size values for dimension d, what they are)
    "disk": (lambda d: 1, "(radius,)"), "sphere": (lambda d: 1, "(radius,)"),
    "box": (lambda d: d, "the half extents"), "wedge": (lambda d: 2, "(half_width, height)"),
}


@dataclass(frozen=True, eq=False)
class Path:
    """Piecewise-linear prescribed motion of a collider's reference point.

    times: (K,) strictly increasing, K >= 1; points: (K, d) the positions at those times. The
    position is interpolated linearly between them and held before times[0] and after times[-1].
    """

    times: np.ndarray
    points: np.ndarray

    def __post_init__(self):
        times = np.array(self.times, dtype=float, ndmin=1)
        points = np.array(self.points, dtype=float)
        if times.ndim != 1:
            raise ValueError(f"collider path times must be a 1D array, got shape {times.shape}")
        if points.ndim != 2 or points.shape[0] != times.shape[0]:
            raise ValueError(f"collider path points must be (K, d) with one point per time: {times.shape[0]} "
                             f"times, points of shape {points.shape}")
        if times.shape[0] < 1:
            raise ValueError("collider path needs at least one time and point")
        if not (np.isfinite(times).all() and np.isfinite(points).all()):
            raise ValueError("collider path times and points must be finite")
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"collider path times must be strictly increasing, got {times.tolist()}")
        for name, value in (("times", times), ("points", points)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def dim(self) -> int:
        return self.points.shape[1]

    def position(self, t: float) -> np.ndarray:
        """(d,) the reference point at time t (clamped to the first/last point outside the times)."""
        return np.array([np.interp(float(t), self.times, self.points[:, k]) for k in range(self.dim)])

    def velocity(self, t0: float, t1: float) -> np.ndarray:
        """(d,) the mean velocity over [t0, t1]: (position(t1) - position(t0)) / (t1 - t0)."""
        if not t1 > t0:
            raise ValueError(f"collider path velocity needs t1 > t0, got t0={t0}, t1={t1}")
        return (self.position(t1) - self.position(t0)) / (t1 - t0)


@dataclass(frozen=True, eq=False)
class Collider:
    """A rigid obstacle moved along ``path``, acting on background nodes (see the module docstring).

    shape: 2D 'disk' | 'box' | 'wedge'; 3D 'sphere' | 'box'. size: disk/sphere (radius,); box the d
    half extents; wedge (half_width, height), the triangle with vertices (0, 0) (the apex, pointing
    down -y), (-half_width, height) and (half_width, height) in local coordinates. path: the
    position of the local origin (disk/sphere/box: the centre; wedge: the apex). friction: the
    Coulomb coefficient mu >= 0 of the contact (inf: no sliding while in contact).
    """

    shape: str
    size: tuple
    path: Path
    friction: float = 0.0

    def __post_init__(self):
        if not isinstance(self.path, Path):
            raise ValueError(f"collider path must be a Path, got {type(self.path).__name__}")
        d = self.path.dim
        if d not in SHAPES:
            raise ValueError(f"colliders move in 2D or 3D, but the path points are {d}D")
        if self.shape not in SHAPES[d]:
            raise ValueError(f"unknown collider shape {self.shape!r} in {d}D; choose one of {list(SHAPES[d])}")
        count, meaning = _SIZES[self.shape]
        try:
            size = tuple(float(s) for s in np.array(self.size, dtype=float, ndmin=1).ravel())
        except (TypeError, ValueError):
            raise ValueError(f"collider {self.shape!r} size must be numbers, got {self.size!r}") from None
        if len(size) != count(d):
            raise ValueError(f"collider {self.shape!r} in {d}D needs size = {meaning}: {count(d)} value(s), "
                             f"got {len(size)}: {self.size!r}")
        if not all(math.isfinite(s) and s > 0 for s in size):
            raise ValueError(f"collider {self.shape!r} size values must be positive and finite, got {self.size!r}")
        try:
            friction = float(self.friction)
        except (TypeError, ValueError):
            friction = math.nan
        if not friction >= 0:
            raise ValueError(f"collider friction must be a number >= 0, got {self.friction!r}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "friction", friction)

    @property
    def dim(self) -> int:
        return self.path.dim

    def lowest(self) -> float:
        """The smallest local y of the shape (disk/sphere: -radius, box: -half_y, wedge: 0, the apex)."""
        if self.shape == "wedge":
            return 0.0
        return -float(self.size[0] if self.shape in ("disk", "sphere") else self.size[1])

    def signed_distance(self, points: torch.Tensor, t: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact signed Euclidean distance to the collider at time t, and its gradient.

        points: (N, d). Returns phi (N,) (negative inside) and the outward unit normal (N, d)
        (grad phi; where it is not unique, e.g. at a disk's centre or on a box's diagonal
        planes inside, one of the candidates).
        """
        centre = torch.as_tensor(self.path.position(t), dtype=points.dtype, device=points.device)
        p = points - centre
        if self.shape in ("disk", "sphere"):
            return _ball_distance(p, self.size[0])
        if self.shape == "box":
            return _box_distance(p, torch.tensor(self.size, dtype=p.dtype, device=p.device))
        return _polygon_distance(p, torch.as_tensor(_wedge_corners(*self.size), dtype=p.dtype, device=p.device))

    def apply(self, v: torch.Tensor, q: torch.Tensor, t: float, dt: float) -> torch.Tensor:
        """Separating contact with Coulomb friction on nodal velocities v (d, N) of nodes at q (d, N).

        Nodes inside the collider at time t (phi <= 0) with w = v - u, u = path.velocity(t, t + dt),
        moving into it (w.n < 0) get v = u + w_t max(0, 1 + mu (w.n) / |w_t|): the normal part of w
        removed, its tangential part w_t reduced by Coulomb friction. Modified in place and returned.
        """
        centre = torch.as_tensor(self.path.position(t), dtype=q.dtype, device=q.device)
        near = ((q - centre[:, None]).norm(dim=0) <= self._reach() * (1 + 1e-9)).nonzero()[:, 0]
        if not len(near):
            return v
        phi, normal = self.signed_distance(q[:, near].T, t)
        nodes = near[phi <= 0]
        if not len(nodes):
            return v
        n = normal[phi <= 0].T  # (d, m)
        u = torch.as_tensor(self.path.velocity(t, t + dt), dtype=v.dtype, device=v.device)[:, None]
        w = v[:, nodes] - u
        wn = (w * n).sum(0)
        tangential = w - wn * n
        speed = tangential.norm(dim=0)
        scale = torch.clamp(1.0 + self.friction * wn / _nonzero(speed), min=0.0)
        v[:, nodes] = u + torch.where(wn < 0, scale * tangential, w)
        return v

    def _reach(self) -> float:
        """The largest distance from the local origin to a point of the shape."""
        if self.shape == "wedge":
            return math.hypot(*self.size)
        return math.sqrt(sum(s * s for s in self.size))

    def surface(self, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        """The collider's boundary at path.points[0] as obstacle geometry.

        Returns nodes (M, d) and facets (F, d) into them: segments in 2D (counter-clockwise, the
        collider on the left of each), triangles in 3D (ordered so that (b - a) x (c - a) points
        out of the collider), as :attr:`~datagen.mesh.Mesh.boundary_facets` orders a body's
        boundary. No facet edge is longer than ``spacing``; a disk is an inscribed polygon, a
        sphere a subdivided icosahedron with its nodes on the sphere.
        """
        if not (isinstance(spacing, (int, float)) and math.isfinite(spacing) and spacing > 0):
            raise ValueError(f"collider surface spacing must be a positive number, got {spacing!r}")
        if self.shape == "disk":
            count = _disk_segments(self.size[0], spacing)
            angle = 2 * np.pi * np.arange(count) / count
            nodes, facets = _closed_polygon(self.size[0] * np.stack([np.cos(angle), np.sin(angle)], 1))
        elif self.shape in ("box", "wedge") and self.dim == 2:
            corners = _wedge_corners(*self.size) if self.shape == "wedge" else _rectangle_corners(*self.size)
            nodes, facets = _closed_polygon(_subdivide_outline(corners, spacing))
        elif self.shape == "sphere":
            nodes, facets = _sphere_surface(self.size[0], spacing)
        else:
            nodes, facets = _box_surface(np.asarray(self.size), spacing)
        return nodes + self.path.points[0], facets


# ----------------------------------------------------------------------------- signed distances
def _nonzero(length: torch.Tensor) -> torch.Tensor:
    """``length`` with its zeros replaced by 1, to divide by where the quotient is then discarded."""
    return torch.where(length > 0, length, torch.ones_like(length))


def _ball_distance(p: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """phi (N,) and normal (N, d) of the disk/sphere of ``radius`` at the origin; p: (N, d)."""
    r = p.norm(dim=1)
    axis = torch.zeros_like(p)
    axis[:, 0] = 1.0
    normal = torch.where((r > 0)[:, None], p / _nonzero(r)[:, None], axis)
    return r - radius, normal


def _box_distance(p: torch.Tensor, half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """phi (N,) and normal (N, d) of the box [-half, half]; p: (N, d), half: (d,).

    Outside, the distance to the nearest point of the box (a face, edge or corner); inside, minus
    the distance to the nearest face, whose normal is the gradient.
    """
    sign = torch.where(p >= 0, 1.0, -1.0).to(p.dtype)
    excess = p.abs() - half  # (N, d): > 0 on the axes where p is beyond the box
    beyond = torch.clamp(excess, min=0.0)
    outside = beyond.norm(dim=1)
    deepest, axis = excess.max(dim=1)
    face = torch.zeros_like(p).scatter_(1, axis[:, None], 1.0) * sign
    normal = torch.where((outside > 0)[:, None], sign * beyond / _nonzero(outside)[:, None], face)
    return outside + torch.clamp(deepest, max=0.0), normal


def _polygon_distance(p: torch.Tensor, corners: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """phi (N,) and normal (N, 2) of the convex polygon with counter-clockwise ``corners`` (V, 2).

    Outside, the distance to the nearest edge segment; inside, the largest (least negative)
    signed distance to an edge's line, which for a convex polygon is minus the distance to
    the boundary.
    """
    edge = torch.roll(corners, -1, dims=0) - corners  # (V, 2)
    length = edge.norm(dim=1)
    out = torch.stack([edge[:, 1], -edge[:, 0]], 1) / length[:, None]  # outward for counter-clockwise corners
    rel = p[:, None, :] - corners[None]  # (N, V, 2)
    height = (rel * out).sum(-1)  # (N, V) signed distance to each edge's line
    along = torch.clamp((rel * edge).sum(-1) / length**2, 0.0, 1.0)
    gap = rel - along[..., None] * edge  # from the nearest point of each edge segment
    dist = gap.norm(dim=-1)
    nearest, k = dist.min(dim=1)
    highest, j = height.max(dim=1)
    inside = highest <= 0
    rows = torch.arange(len(p), device=p.device)
    away = gap[rows, k] / _nonzero(nearest)[:, None]
    return torch.where(inside, highest, nearest), torch.where(inside[:, None], out[j], away)


def _wedge_corners(half_width: float, height: float) -> np.ndarray:
    """(3, 2) the wedge's corners counter-clockwise from the apex at the origin."""
    return np.array([[0.0, 0.0], [half_width, height], [-half_width, height]])


def _rectangle_corners(half_x: float, half_y: float) -> np.ndarray:
    return np.array([[-half_x, -half_y], [half_x, -half_y], [half_x, half_y], [-half_x, half_y]])


# ----------------------------------------------------------------------------- surfaces
def _pieces(length: float, spacing: float) -> int:
    """The fewest equal pieces of a segment of ``length`` no longer than ``spacing``."""
    return max(1, math.ceil(length / spacing - 1e-9))


def _disk_segments(radius: float, spacing: float) -> int:
    """Sides of the inscribed regular polygon (at least 6) whose chords 2 r sin(pi / n) <= spacing."""
    if spacing >= 2 * radius:
        return 6
    return max(6, math.ceil(math.pi / math.asin(spacing / (2 * radius)) - 1e-9))


def _subdivide_outline(corners: np.ndarray, spacing: float) -> np.ndarray:
    """(M, 2) the closed outline through ``corners`` (V, 2) with every side cut into pieces <= spacing."""
    points = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        n = _pieces(float(np.linalg.norm(b - a)), spacing)
        points.append(a + np.arange(n)[:, None] / n * (b - a))
    return np.concatenate(points)


def _closed_polygon(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (M, 2) and segments (M, 2) joining consecutive points, the last back to the first."""
    count = len(points)
    return points, np.stack([np.arange(count), (np.arange(count) + 1) % count], 1).astype(np.int64)


def _merged(points: np.ndarray, triangles: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident points (within 1e-9 scale) and orient every triangle outwards (convex shape
    around the origin). points: (n, 3); triangles: (F, 3) into them."""
    keys = np.round(points / (1e-9 * scale)).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    nodes, facets = points[first], inverse.ravel()[triangles]
    a, b, c = (nodes[facets[:, k]] for k in range(3))
    inward = (np.cross(b - a, c - a) * (a + b + c)).sum(1) < 0
    facets[inward] = facets[inward][:, [0, 2, 1]]
    return nodes, facets.astype(np.int64)


def _max_edge(nodes: np.ndarray, facets: np.ndarray) -> float:
    return float(max(np.linalg.norm(nodes[facets[:, k]] - nodes[facets[:, (k + 1) % 3]], axis=1).max()
                     for k in range(3)))


def _sphere_surface(radius: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """A geodesic sphere: each icosahedron face cut into f^2 triangles, the nodes pushed onto the
    sphere; f the smallest frequency whose longest edge is <= spacing."""
    golden = (1 + math.sqrt(5)) / 2
    base = np.array([[0, s1, s2 * golden] for s1 in (-1, 1) for s2 in (-1, 1)], float)
    ico = np.concatenate([np.roll(base, k, axis=1) for k in range(3)])  # the 12 icosahedron vertices
    faces = ConvexHull(ico).simplices
    frequency = 1
    while True:
        i, j = (a.ravel() for a in np.meshgrid(np.arange(frequency + 1), np.arange(frequency + 1), indexing="ij"))
        keep = i + j <= frequency
        i, j = i[keep], j[keep]
        local = {(a, b): k for k, (a, b) in enumerate(zip(i.tolist(), j.tolist(), strict=True))}
        small = [(local[a, b], local[a + 1, b], local[a, b + 1]) for a, b in local if a + b < frequency]
        small += [(local[a + 1, b], local[a + 1, b + 1], local[a, b + 1]) for a, b in local if a + b < frequency - 1]
        small = np.asarray(small)
        a, b, c = (ico[faces[:, k]][:, None, :] for k in range(3))
        points = a + (i[None, :, None] * (b - a) + j[None, :, None] * (c - a)) / frequency  # (20, n, 3)
        triangles = (small[None] + len(i) * np.arange(len(faces))[:, None, None]).reshape(-1, 3)
        points = points.reshape(-1, 3)
        points = radius * points / np.linalg.norm(points, axis=1, keepdims=True)
        nodes, facets = _merged(points, triangles, radius)
        if _max_edge(nodes, facets) <= spacing:
            return nodes, facets
        frequency += 1


def _box_surface(half: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The box [-half, half] (3D): every face a grid of squares cut into two triangles, the grid along
    each axis the same on every face (so that the faces share their edge nodes), every triangle's
    diagonal <= spacing."""
    counts = [_pieces(2 * h * math.sqrt(2), spacing) for h in half]
    points, triangles = [], []
    for axis in range(3):
        u, w = [k for k in range(3) if k != axis]
        gu, gw = np.meshgrid(np.linspace(-half[u], half[u], counts[u] + 1),
                             np.linspace(-half[w], half[w], counts[w] + 1), indexing="ij")
        idx = np.arange(gu.size).reshape(gu.shape)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        quad = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        for sign in (-1.0, 1.0):
            face = np.zeros((gu.size, 3))
            face[:, u], face[:, w], face[:, axis] = gu.ravel(), gw.ravel(), sign * half[axis]
            triangles.append(quad + sum(len(p) for p in points))
            points.append(face)
    return _merged(np.concatenate(points), np.concatenate(triangles), float(np.linalg.norm(half)))
