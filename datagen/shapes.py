"""Meshed shapes, made with the gmsh Python package; every function returns a :class:`Mesh`.

``size`` is the target (mean) edge length inside the shape; ``boundary_size`` (optional) a
finer target on the boundary, graded back to ``size`` over a distance of ``3 * size``. The same
arguments always give the same mesh (one meshing thread, fixed seed). gmsh is initialised
for the call and finalised after it (or, if the caller already initialised it, a separate
model is used and the caller's options are restored), so calls may repeat and run in worker
processes; gmsh's console output is silenced.
"""

from __future__ import annotations

import math
import signal
import threading
from collections.abc import Sequence
from contextlib import contextmanager

import numpy as np

from datagen.mesh import Mesh, MeshError

__all__ = ["rectangle", "disk", "annulus", "polygon", "wavy_channel", "glyph", "box", "sphere"]

_GMSH_LOCK = threading.Lock()
_GRADING_SIZES = 3.0  # boundary_size grows back to size over this many `size`s
# Field scale for tetrahedra so that the mean edge length matches `size`: measured mean edge
# over field size on spheres and cubes was 1.18 (coarse, surface-dominated) to 1.33 (fine).
_TET_SIZE_FACTOR = 0.78
_OPTIONS = {  # option -> value used for every mesh
    "General.Terminal": 0,
    "General.Verbosity": 0,
    "General.NumThreads": 1,
    "Mesh.RandomSeed": 1,
    "Mesh.Algorithm": 6,  # Frontal-Delaunay in 2D
    "Mesh.Algorithm3D": 1,  # Delaunay in 3D
    "Mesh.MeshSizeExtendFromBoundary": 0,
    "Mesh.MeshSizeFromPoints": 0,
    "Mesh.MeshSizeFromCurvature": 0,
}


@contextmanager
def _keep_signal_handlers():
    """gmsh's initialize/finalize reset the process's SIGTERM action behind Python's back (a
    trainer's save-on-SIGTERM would be lost): put Python's handlers back afterwards. The two
    signals are blocked meanwhile, so one that arrives in between waits for Python's handler
    instead of meeting gmsh's."""
    main = threading.current_thread() is threading.main_thread()
    signals = {signal.SIGINT, signal.SIGTERM}
    saved = {sig: signal.getsignal(sig) for sig in signals} if main else {}
    blocking = main and hasattr(signal, "pthread_sigmask")
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, signals) if blocking else None
    try:
        yield
    finally:
        for sig, handler in saved.items():
            if handler is not None:
                signal.signal(sig, handler)
        if blocking:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)


@contextmanager
def _gmsh_session(name: str):
    """A fresh gmsh model with our options, cleaned up afterwards whatever happens."""
    import gmsh

    with _GMSH_LOCK:
        owner = not gmsh.isInitialized()
        if owner:  # no SIGINT handler, no user config files: safe in workers, reproducible
            with _keep_signal_handlers():
                gmsh.initialize(readConfigFiles=False, interruptible=False)
        saved = {key: gmsh.option.getNumber(key) for key in _OPTIONS}
        for key, value in _OPTIONS.items():
            gmsh.option.setNumber(key, value)
        gmsh.model.add(name)
        try:
            yield gmsh
        except Exception as exc:
            if isinstance(exc, (MeshError, ValueError)):
                raise
            raise MeshError(f"gmsh could not mesh the {name}: {exc}") from None
        finally:
            gmsh.model.remove()
            if owner:
                with _keep_signal_handlers():
                    gmsh.finalize()
            else:
                for key, value in saved.items():
                    gmsh.option.setNumber(key, value)


def _check_sizes(size: float, boundary_size: float | None) -> None:
    if not (isinstance(size, (int, float)) and math.isfinite(size) and size > 0):
        raise ValueError(f"size must be a positive number, got {size!r}")
    if boundary_size is not None and not (math.isfinite(boundary_size) and 0 < boundary_size):
        raise ValueError(f"boundary_size must be a positive number or None, got {boundary_size!r}")


def _mesh(gmsh, dim: int, size: float, boundary_size: float | None) -> Mesh:
    """Set the size field on the synchronised model, mesh it and return the top-dim simplices."""
    if dim == 3:  # gmsh's tetrahedra come out ~1.3x longer than the field asks for: calibrate
        size *= _TET_SIZE_FACTOR
        boundary_size = None if boundary_size is None else boundary_size * _TET_SIZE_FACTOR
    field = gmsh.model.mesh.field
    if boundary_size is None:
        background = field.add("MathEval")
        field.setString(background, "F", repr(float(size)))
    else:
        entities = gmsh.model.getEntities(dim)
        boundary = gmsh.model.getBoundary(entities, combined=True, oriented=False, recursive=False)
        distance = field.add("Distance")
        entity_list = "CurvesList" if dim == 2 else "SurfacesList"
        field.setNumbers(distance, entity_list, [abs(tag) for _, tag in boundary])
        field.setNumber(distance, "Sampling", 200)
        background = field.add("Threshold")
        field.setNumber(background, "InField", distance)
        field.setNumber(background, "SizeMin", boundary_size)
        field.setNumber(background, "SizeMax", size)
        field.setNumber(background, "DistMin", 0.0)
        field.setNumber(background, "DistMax", _GRADING_SIZES * size)
    field.setAsBackgroundMesh(background)
    gmsh.model.mesh.generate(dim)
    tags, coords, _ = gmsh.model.mesh.getNodes()
    element = {2: 2, 3: 4}[dim]  # gmsh element types: 3-node triangle, 4-node tetrahedron
    _, cell_tags = gmsh.model.mesh.getElementsByType(element)
    if cell_tags.size == 0:
        raise MeshError("gmsh produced no cells; is the shape larger than the element size?")
    order = np.argsort(tags)
    cells = order[np.searchsorted(tags[order], cell_tags.reshape(-1, dim + 1))]
    nodes = coords.reshape(-1, 3)[:, :dim]
    return Mesh.from_arrays(nodes, cells, drop_unused=True, orient=True)


def _occ_loop(gmsh, ring: np.ndarray) -> int:
    """Closed polyline through the (K, 2) points of ``ring`` as an OCC curve loop."""
    occ = gmsh.model.occ
    points = [occ.addPoint(float(x), float(y), 0.0) for x, y in ring]
    lines = [occ.addLine(points[i], points[(i + 1) % len(points)]) for i in range(len(points))]
    return occ.addCurveLoop(lines)


def _plane_with_holes(gmsh, outer: np.ndarray, holes: Sequence[np.ndarray]) -> int:
    loops = [_occ_loop(gmsh, outer)] + [_occ_loop(gmsh, hole) for hole in holes]
    return gmsh.model.occ.addPlaneSurface(loops)


def _as_ring(points, what: str) -> np.ndarray:
    ring = np.asarray(points, dtype=np.float64)
    if ring.ndim != 2 or ring.shape[1] != 2 or len(ring) < 3 or not np.isfinite(ring).all():
        raise ValueError(f"{what} must be a finite (K, 2) array with K >= 3 vertices; got shape {ring.shape}")
    if np.allclose(ring[0], ring[-1]):
        ring = ring[:-1]  # closing vertex repeated
    return ring


def _resample_chain(chain: np.ndarray, spacing: float) -> np.ndarray:
    """Points at equal arc length along the polyline ``chain`` (K, 2), ends kept, end excluded."""
    steps = np.linalg.norm(np.diff(chain, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    pieces = max(1, int(round(arc[-1] / spacing)))
    targets = np.linspace(0.0, arc[-1], pieces + 1)[:-1]
    return np.stack([np.interp(targets, arc, chain[:, k]) for k in range(2)], axis=1)


def _resample_ring(ring: np.ndarray, spacing: float, corner_degrees: float = 30.0) -> np.ndarray:
    """Resample a closed ring to about ``spacing``, keeping its corners exactly."""
    before = ring - np.roll(ring, 1, axis=0)
    after = np.roll(ring, -1, axis=0) - ring
    cos = (before * after).sum(1) / (np.linalg.norm(before, axis=1) * np.linalg.norm(after, axis=1))
    corners = np.flatnonzero(cos < math.cos(math.radians(corner_degrees)))
    if corners.size == 0:
        corners = np.array([0])
    out = []
    for a, b in zip(corners, np.roll(corners, -1), strict=True):
        stop = b if b > a else b + len(ring)
        chain = ring[np.arange(a, stop + 1) % len(ring)]
        out.append(_resample_chain(chain, spacing))
    return np.concatenate(out)


# --------------------------------------------------------------------------- 2D shapes
def rectangle(width: float = 1.0, height: float = 1.0, size: float = 0.1, *,
              origin: Sequence[float] = (0.0, 0.0), boundary_size: float | None = None) -> Mesh:
    """Triangulated rectangle ``[x0, x0+width] x [y0, y0+height]`` with ``origin = (x0, y0)``."""
    _check_sizes(size, boundary_size)
    if width <= 0 or height <= 0:
        raise ValueError(f"rectangle width and height must be positive, got {width}, {height}")
    with _gmsh_session("rectangle") as gmsh:
        gmsh.model.occ.addRectangle(float(origin[0]), float(origin[1]), 0.0, float(width), float(height))
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 2, size, boundary_size)


def disk(radius: float = 1.0, size: float = 0.1, *, center: Sequence[float] = (0.0, 0.0),
         boundary_size: float | None = None) -> Mesh:
    """Triangulated disk of ``radius`` around ``center``."""
    _check_sizes(size, boundary_size)
    if radius <= 0:
        raise ValueError(f"disk radius must be positive, got {radius}")
    with _gmsh_session("disk") as gmsh:
        gmsh.model.occ.addDisk(float(center[0]), float(center[1]), 0.0, float(radius), float(radius))
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 2, size, boundary_size)


def annulus(inner_radius: float = 0.5, outer_radius: float = 1.0, size: float = 0.1, *,
            center: Sequence[float] = (0.0, 0.0), boundary_size: float | None = None) -> Mesh:
    """Triangulated ring between ``inner_radius`` and ``outer_radius`` around ``center``."""
    _check_sizes(size, boundary_size)
    if not 0 < inner_radius < outer_radius:
        raise ValueError(f"annulus needs 0 < inner_radius < outer_radius, got {inner_radius}, {outer_radius}")
    cx, cy = float(center[0]), float(center[1])
    with _gmsh_session("annulus") as gmsh:
        occ = gmsh.model.occ
        outer = occ.addDisk(cx, cy, 0.0, float(outer_radius), float(outer_radius))
        inner = occ.addDisk(cx, cy, 0.0, float(inner_radius), float(inner_radius))
        occ.cut([(2, outer)], [(2, inner)])
        occ.synchronize()
        return _mesh(gmsh, 2, size, boundary_size)


def polygon(outer, holes: Sequence = (), size: float = 0.1, *, boundary_size: float | None = None) -> Mesh:
    """Triangulated polygon: ``outer`` (K, 2) ring of vertices, ``holes`` a list of rings inside it.

    Rings may be given in either orientation, closed or not. Every vertex becomes a mesh node.
    """
    _check_sizes(size, boundary_size)
    outer = _as_ring(outer, "polygon outer ring")
    holes = [_as_ring(hole, f"polygon hole {k}") for k, hole in enumerate(holes)]
    with _gmsh_session("polygon") as gmsh:
        _plane_with_holes(gmsh, outer, holes)
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 2, size, boundary_size)


def wavy_channel(amplitude: float = 1.0, omega1: float = math.pi / 5, omega2: float = math.pi / 20,
                 width: float = 2.0, length: float = 20.0, size: float = 0.1, *,
                 inlet: float = 4.0, outlet: float = 1.0, boundary_size: float | None = None) -> Mesh:
    """The wavy channel of UMLS-MPM §3.4 (UMLS eq. 36), triangulated.

    Left wall ``x_l(y) = amplitude * sin(omega1 y) sin(omega2 y)`` for ``0 < y <= length`` and
    ``x_l = 0`` otherwise; right wall ``x_r = x_l + width``. The channel runs from
    ``y = -outlet`` to ``y = length + inlet`` (straight sections at both ends). The paper's
    case is the default (A = 1 m, omega1 = pi/5, omega2 = pi/20, width 2 m, length 20 m).
    """
    _check_sizes(size, boundary_size)
    if width <= 0 or length <= 0 or inlet < 0 or outlet < 0:
        raise ValueError("wavy_channel needs width > 0, length > 0, inlet >= 0 and outlet >= 0")
    def wall(y):  # UMLS eq. 36
        return np.where((y > 0) & (y <= length), amplitude * np.sin(omega1 * y) * np.sin(omega2 * y), 0.0)

    dense = np.concatenate([[-outlet], np.linspace(0.0, length, 4000), [length + inlet]])
    y = _resample_chain(np.stack([wall(dense), dense], axis=1), min(size, boundary_size or size))[:, 1]
    y = np.append(y, length + inlet)
    left = np.stack([wall(y), y], axis=1)  # nodes exactly on the analytic wall
    ring = np.vstack([left, (left + [width, 0.0])[::-1]])  # up the left wall, down the right
    if np.any(np.diff(left[:, 1]) <= 0):
        raise ValueError("wavy_channel wall is not a function of y; lower the amplitude or frequencies")
    with _gmsh_session("wavy channel") as gmsh:
        _plane_with_holes(gmsh, ring, [])
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 2, size, boundary_size)


def _bezier(control: np.ndarray, samples: int) -> np.ndarray:
    """Points of the Bezier curve with (k+1, 2) ``control`` at t in (0, 1]."""
    t = np.linspace(0.0, 1.0, samples + 1)[1:, None]
    k = len(control) - 1
    return sum(math.comb(k, i) * t**i * (1 - t) ** (k - i) * control[i] for i in range(k + 1))


def _text_rings(text: str, height: float, font: str) -> list[np.ndarray]:
    """Closed outlines of ``text`` (curves flattened finely), in matplotlib's text units."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.path import Path
    from matplotlib.textpath import TextPath

    path = TextPath((0.0, 0.0), text, size=height, prop=FontProperties(family=font))
    rings, current = [], []
    for vertices, code in path.iter_segments(curves=True, simplify=False):
        vertices = vertices.reshape(-1, 2)
        if code == Path.MOVETO:
            if len(current) >= 3:
                rings.append(np.array(current))
            current = [vertices[0]]
        elif code == Path.LINETO:
            current.append(vertices[0])
        elif code in (Path.CURVE3, Path.CURVE4):
            current.extend(_bezier(np.vstack([current[-1], vertices]), 16))
        elif code == Path.CLOSEPOLY:
            if len(current) >= 3:
                rings.append(np.array(current))
            current = []
    return [_as_ring(ring, "glyph outline") for ring in rings]


def _nest(rings: list[np.ndarray]) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """Group rings into (outer, holes) by containment depth: even depth = outer, odd = hole."""
    from matplotlib.path import Path

    paths = [Path(ring) for ring in rings]
    containers = [
        [j for j, other in enumerate(paths) if j != i and other.contains_point(rings[i][0])]
        for i in range(len(rings))
    ]
    depth = [len(c) for c in containers]
    shapes = {i: (rings[i], []) for i in range(len(rings)) if depth[i] % 2 == 0}
    for i, found in enumerate(containers):
        if depth[i] % 2 == 1:
            parent = max(found, key=lambda j: depth[j])
            shapes[parent][1].append(rings[i])
    return [shapes[i] for i in sorted(shapes)]


def glyph(text: str, size: float = 0.03, *, height: float = 1.0, boundary_size: float | None = None,
          font: str = "DejaVu Sans") -> Mesh:
    """Triangulated outlines of ``text`` from one of matplotlib's bundled fonts; holes are kept.

    ``height`` is the font size (em height) in mesh units; the text starts at the origin on
    its baseline. Separate letters (and the dot of an 'i') are separate mesh components.
    Outline curves are resampled to the boundary size with corners kept.
    """
    _check_sizes(size, boundary_size)
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"glyph text must be a non-empty string, got {text!r}")
    spacing = boundary_size or size
    shapes = []
    for outer, holes in _nest(_text_rings(text, height, font)):
        rings = [_resample_ring(ring, spacing) for ring in [outer, *holes]]
        if min(len(r) for r in rings) < 3:
            raise ValueError(f"glyph {text!r}: size {spacing} is too coarse for height {height}")
        shapes.append((rings[0], rings[1:]))
    with _gmsh_session("glyph") as gmsh:
        surfaces = [(2, _plane_with_holes(gmsh, outer, holes)) for outer, holes in shapes]
        if len(surfaces) > 1:  # letters that touch or overlap become one piece
            gmsh.model.occ.fuse(surfaces[:1], surfaces[1:])
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 2, size, boundary_size)


# --------------------------------------------------------------------------- 3D shapes
def box(extent: Sequence[float] = (1.0, 1.0, 1.0), size: float = 0.1, *,
        origin: Sequence[float] = (0.0, 0.0, 0.0), boundary_size: float | None = None) -> Mesh:
    """Tetrahedralised box with corner ``origin`` and edge lengths ``extent``."""
    _check_sizes(size, boundary_size)
    if len(extent) != 3 or min(extent) <= 0:
        raise ValueError(f"box extent must be three positive lengths, got {extent}")
    with _gmsh_session("box") as gmsh:
        gmsh.model.occ.addBox(*map(float, origin), *map(float, extent))
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 3, size, boundary_size)


def sphere(radius: float = 1.0, size: float = 0.1, *, center: Sequence[float] = (0.0, 0.0, 0.0),
           boundary_size: float | None = None) -> Mesh:
    """Tetrahedralised ball of ``radius`` around ``center``."""
    _check_sizes(size, boundary_size)
    if radius <= 0:
        raise ValueError(f"sphere radius must be positive, got {radius}")
    with _gmsh_session("sphere") as gmsh:
        gmsh.model.occ.addSphere(*map(float, center), float(radius))
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 3, size, boundary_size)


def _occ_tetrahedron(gmsh, corners: np.ndarray) -> int:
    """An OCC volume bounded by the four triangles of the tetrahedron ``corners`` (4, 3)."""
    occ = gmsh.model.occ
    points = [occ.addPoint(*map(float, c)) for c in corners]
    lines = {}
    for a in range(4):
        for b in range(a + 1, 4):
            lines[a, b] = occ.addLine(points[a], points[b])
    faces = []
    for a, b, c in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
        loop = occ.addCurveLoop([lines[a, b], lines[b, c], lines[a, c]])
        faces.append(occ.addPlaneSurface([loop]))
    return occ.addVolume([occ.addSurfaceLoop(faces)])


def star(radius: float = 1.0, size: float = 0.1, *, center: Sequence[float] = (0.0, 0.0, 0.0)) -> Mesh:
    """Tetrahedralised stella octangula (two interpenetrating regular tetrahedra, a shape of sharp
    tips and re-entrant edges) whose eight tips lie at distance ``radius`` from ``center``."""
    _check_sizes(size, None)
    if radius <= 0:
        raise ValueError(f"star radius must be positive, got {radius}")
    even = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) * radius / math.sqrt(3.0)
    center = np.asarray(center, float)
    with _gmsh_session("star") as gmsh:
        a = _occ_tetrahedron(gmsh, center + even)
        b = _occ_tetrahedron(gmsh, center - even)
        gmsh.model.occ.fuse([(3, a)], [(3, b)])
        gmsh.model.occ.synchronize()
        return _mesh(gmsh, 3, size, None)
