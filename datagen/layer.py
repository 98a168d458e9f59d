"""One layer of cells outside a mesh's boundary (UMLS-MPM §2.3.5, built automatically).

MLS kernels of particles in boundary cells degenerate when the mesh ends there: with no ring
of nodes on the outer side, weights of interior nodes turn negative (UMLS Fig. 5). The layer
gives every boundary node neighbours outside, placed like the inside is sampled:

- Each boundary node is copied outwards once per *cluster* of its facets, a cluster being a
  set of facets joined across smooth or concave edges. Smooth parts of the boundary thus get
  one copy per node along the (mitred) mean normal.
- Along a convex crease (2D: at a convex corner) the facets on either side use their own
  copies, and a mitred *bisector* copy fills the gap: a fan of two triangles at a 2D corner,
  two wedge prisms along each 3D crease edge.
- A 3D corner where three or more clusters meet gets an *apex* copy, coned over the wedges'
  end caps.
- Prisms (quads in 2D) are split into simplices by the minimum-vertex rule (Dompierre et al.
  1999), which depends only on the four nodes of a shared quad, so the layer is conforming.

What one layer cannot do in 3D: the B-spline support of the UMLS kernel (1.5 h, h the longest
edge, about 2.4 mean edges on gmsh meshes) reaches two rings inwards but only one layer
outwards. Near a flat face eta keeps the deep inner nodes small and all weights stay
non-negative; near a convex crease the copies of the side face also pull the weighted centre
of the samples inwards (they extend down the side, while beyond the crease there is only the
single row of bisector copies), so plain MLS gives the far inner nodes of a few particles
weights of about -1e-5 to -3e-4 (about 0.1% of the particles in boundary cells, all within one
element of a crease or, on coarse spheres, of the curved surface). Thickness 0.5 to 2, longer
or shorter crease copies, and linking every boundary node to all copies of its prisms were
measured and do not remove them (thickness 0.85 to 1.0 is best); 2D has no such case. The
kernel therefore projects those rows onto the closest non-negative, linearly exact kernel
(:func:`datagen.mpm.kernels.nonnegative_mls`); with the layer that changes them by about the
size of the negative weights.

Walls act on the layer too (datagen/mpm/boundary.py): a layer node next to a wall node takes
that wall's condition. Beyond a sticky wall the layer nodes are mirror ghosts, minus the
velocity at their reflection inside the mesh, so the clamp sits on the wall; holding them at
rest instead would clamp O(h) outside it (the odd extension of the motion is not zero there):
a 2D bar clamped about 0.1 m too far out at 80 cells, a cantilever about 5% too soft.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from datagen.mesh import Mesh
from datagen.simplex import MeshError, name_first, signed_measures, simplex_quality

__all__ = ["ExtendedMesh", "with_extra_layer"]

FEATURE_DEGREES = 35.0  # facet normals further apart than this across a convex edge form a crease
_MAX_STRETCH = 2.0  # mitred offsets are at most this many times the layer thickness


@dataclass(frozen=True, eq=False)
class ExtendedMesh:
    """A mesh with one layer of cells added outside its boundary (see :func:`with_extra_layer`).

    The physical mesh's nodes and cells keep their indices and come first; the layer's
    nodes and cells follow.
    """

    mesh: Mesh
    """The whole mesh: physical nodes/cells first, then the layer."""
    node_outside: np.ndarray
    """(N',) True for nodes outside the physical domain."""
    cell_outside: np.ndarray
    """(C',) True for cells of the extra layer."""

    @property
    def n_physical_nodes(self) -> int:
        return int((~self.node_outside).sum())

    @property
    def n_physical_cells(self) -> int:
        return int((~self.cell_outside).sum())


@dataclass
class _Creases:
    """Boundary topology used by the layer.

    slot_cluster: (F, d) cluster id of each (facet, local node); cluster_node: (K,) its node.
    creases: (R, 4) rows (a, b, f1, f2): crease edge a-b (b = a in 2D) between facets f1, f2.
    """

    slot_cluster: np.ndarray
    cluster_node: np.ndarray
    creases: np.ndarray


def _facet_pairs(facets: np.ndarray, n_nodes: int) -> np.ndarray:
    """(P, 4) rows (a, b, f1, f2): facets f1, f2 share the ridge a-b (2D: the node a = b)."""
    f, d = facets.shape
    local = [(0, 0)] if d == 1 else ([(0, 0), (1, 1)] if d == 2 else [(0, 1), (1, 2), (2, 0)])
    if d == 2:  # ridges of boundary segments are their nodes
        ridges = np.concatenate([facets[:, [0, 0]], facets[:, [1, 1]]])
    else:
        ridges = np.concatenate([np.sort(facets[:, [j, k]], axis=1) for j, k in local])
    owner = np.tile(np.arange(f), len(local))
    keys = ridges[:, 0] * n_nodes + ridges[:, 1]
    order = np.argsort(keys, kind="stable")
    keys, ridges, owner = keys[order], ridges[order], owner[order]
    # Pair equal keys two by two (a ridge shared by 2k facets, non-manifold, gives k pairs).
    run_start = np.maximum.accumulate(np.where(np.r_[True, keys[1:] != keys[:-1]], np.arange(keys.size), 0))
    position = np.arange(keys.size) - run_start
    first = np.flatnonzero((position[:-1] % 2 == 0) & (keys[:-1] == keys[1:]))
    return np.stack([ridges[first, 0], ridges[first, 1], owner[first], owner[first + 1]], axis=1)


def _is_crease(mesh: Mesh, pairs: np.ndarray) -> np.ndarray:
    """(P,) True where the two facets meet at a convex edge sharper than FEATURE_DEGREES."""
    normals, facets, x = mesh.boundary_normals, mesh.boundary_facets, mesh.nodes
    n1, n2 = normals[pairs[:, 2]], normals[pairs[:, 3]]
    sharp = (n1 * n2).sum(axis=1) < np.cos(np.radians(FEATURE_DEGREES))
    f2 = facets[pairs[:, 3]]
    off_ridge = (f2 != pairs[:, :1]) & (f2 != pairs[:, 1:2])
    other = x[np.where(off_ridge.any(axis=1), f2[np.arange(len(f2)), off_ridge.argmax(axis=1)], pairs[:, 0])]
    convex = ((other - x[pairs[:, 0]]) * n1).sum(axis=1) < 0
    return sharp & convex


def _clusters(facets: np.ndarray, pairs: np.ndarray, joined: np.ndarray) -> np.ndarray:
    """(F, d) cluster id per (facet, node) slot: slots of one node linked across joined ridges."""
    f, d = facets.shape
    slot = np.arange(f * d).reshape(f, d)
    links = []
    for end in (0, 1):
        node = pairs[joined, end]
        s1 = slot[pairs[joined, 2], (facets[pairs[joined, 2]] == node[:, None]).argmax(axis=1)]
        s2 = slot[pairs[joined, 3], (facets[pairs[joined, 3]] == node[:, None]).argmax(axis=1)]
        links.append(np.stack([s1, s2]))
    links = np.concatenate(links, axis=1)
    graph = sp.coo_matrix((np.ones(links.shape[1]), (links[0], links[1])), shape=(f * d, f * d))
    _, labels = csgraph.connected_components(graph, directed=False)
    return labels.reshape(f, d)


def _creases(mesh: Mesh) -> _Creases:
    """Cluster the boundary facets around each node and find the convex creases between clusters.

    A crease must separate different clusters at both of its ends; one that does not (a
    crease fading out into a smooth surface) is treated as smooth and clustering repeats.
    """
    facets = mesh.boundary_facets
    pairs = _facet_pairs(facets, mesh.n_nodes)
    crease = _is_crease(mesh, pairs) if mesh.dim > 1 else np.zeros(len(pairs), dtype=bool)
    while True:
        cluster = _clusters(facets, pairs, ~crease)
        ends = [(facets[pairs[:, k]] == pairs[:, end, None]).argmax(axis=1) for end in (0, 1) for k in (2, 3)]
        c = [cluster[pairs[:, 2 + i % 2], ends[i]] for i in range(4)]
        valid = crease & (c[0] != c[1]) & (c[2] != c[3])
        if (valid == crease).all():
            break
        crease = valid
    _, compact = np.unique(cluster, return_inverse=True)
    compact = compact.reshape(cluster.shape)
    cluster_node = np.zeros(compact.max() + 1, dtype=np.int64)
    cluster_node[compact.ravel()] = facets.ravel()
    return _Creases(compact, cluster_node, pairs[crease])


# ----------------------------------------------------------------------------- geometry
def _node_spacing(mesh: Mesh) -> np.ndarray:
    """(N,) mean length of each node's edges."""
    spacing = np.zeros(mesh.n_nodes)
    np.add.at(spacing, mesh.edges[:, 0], mesh.edge_lengths)
    np.add.at(spacing, mesh.edges[:, 1], mesh.edge_lengths)
    return spacing / np.maximum(mesh.node_degree, 1)


@dataclass
class _Copies:
    """Outside nodes: ``node`` (M,) they copy, ``offset`` (M, d) from it, ids from ``first``."""

    node: np.ndarray
    offset: np.ndarray
    cluster: np.ndarray  # (K,) id of the copy of each cluster
    bisector: dict  # (node, cluster, cluster) -> id
    apex: dict  # node -> id


def _copies(mesh: Mesh, creases: _Creases, thickness: float) -> _Copies:
    facets, normals = mesh.boundary_facets, mesh.boundary_normals
    n_clusters = creases.cluster_node.size
    dir_sum = np.zeros((n_clusters, mesh.dim))
    for j in range(facets.shape[1]):
        np.add.at(dir_sum, creases.slot_cluster[:, j], normals)
    cluster_dir = dir_sum / np.maximum(np.linalg.norm(dir_sum, axis=1, keepdims=True), 1e-300)
    alignment = np.full(n_clusters, np.inf)
    for j in range(facets.shape[1]):
        np.minimum.at(alignment, creases.slot_cluster[:, j], (cluster_dir[creases.slot_cluster[:, j]] * normals).sum(1))
    cusps = np.unique(creases.cluster_node[alignment < 0.1])
    if cusps.size:
        raise MeshError(
            f"cannot add an extra layer: boundary {name_first(cusps, 'nodes')} are cusps whose facets "
            "face opposite ways; smooth the geometry or refine the mesh there"
        )
    spacing = thickness * _node_spacing(mesh)
    nodes = [creases.cluster_node]
    offsets = [(spacing[creases.cluster_node] / np.maximum(alignment, 1 / _MAX_STRETCH))[:, None] * cluster_dir]
    next_id = n_clusters
    bisector, apex = {}, {}
    groups = _joined_clusters(mesh, creases)
    for kind, table in (("bisector", bisector), ("apex", apex)):
        for key, members in groups[kind].items():
            direction = cluster_dir[list(members)].sum(axis=0)
            direction /= np.linalg.norm(direction)
            align = min(float(cluster_dir[k] @ direction) for k in members)
            node = int(creases.cluster_node[members[0]])
            nodes.append(np.array([node]))
            offsets.append((spacing[node] / max(align, 1 / _MAX_STRETCH) * direction)[None, :])
            table[key] = next_id
            next_id += 1
    return _Copies(np.concatenate(nodes), np.concatenate(offsets), np.arange(n_clusters), bisector, apex)


def _joined_clusters(mesh: Mesh, creases: _Creases) -> dict:
    """Clusters meeting at creases: 'bisector' (node, c1, c2) -> (c1, c2) per crease end, and
    'apex' node -> its clusters for 3D nodes where three or more clusters meet."""
    bisector = {}
    for a, b, f1, f2 in creases.creases:
        for node in {int(a), int(b)}:
            c1, c2 = sorted((_cluster_at(creases, mesh, f1, node), _cluster_at(creases, mesh, f2, node)))
            bisector[(node, c1, c2)] = (c1, c2)
    apex = {}
    if mesh.dim == 3:
        per_node: dict[int, set] = {}
        for node, c1, c2 in bisector:
            per_node.setdefault(node, set()).update((c1, c2))
        apex = {node: tuple(sorted(members)) for node, members in sorted(per_node.items()) if len(members) >= 3}
    return {"bisector": dict(sorted(bisector.items())), "apex": apex}


def _cluster_at(creases: _Creases, mesh: Mesh, facet: int, node: int) -> int:
    local = int(np.flatnonzero(mesh.boundary_facets[facet] == node)[0])
    return int(creases.slot_cluster[facet, local])


# ----------------------------------------------------------------------------- cells
# Vertex orders of a prism (0 1 2 bottom, 3 4 5 above them) that bring vertex k to position 0.
_PRISM_TURNS = np.array([[0, 1, 2, 3, 4, 5], [1, 2, 0, 4, 5, 3], [2, 0, 1, 5, 3, 4],
                         [3, 5, 4, 0, 2, 1], [4, 3, 5, 1, 0, 2], [5, 4, 3, 2, 1, 0]])


def split_prisms(prisms: np.ndarray) -> np.ndarray:
    """(n, 6) prisms -> (3n, 4) tetrahedra, each quad face cut from its smallest vertex.

    Dompierre et al. (1999): turn the prism so that its smallest vertex V0 comes first; the
    two quads through V0 are cut from V0, the third by the smaller of min(V1, V5) and
    min(V2, V4). A quad shared by two prisms is cut the same way in both.
    """
    v = np.take_along_axis(prisms, _PRISM_TURNS[np.argmin(prisms, axis=1)], axis=1)
    first = np.minimum(v[:, 1], v[:, 5]) < np.minimum(v[:, 2], v[:, 4])
    a = np.stack([v[:, [0, 1, 2, 5]], v[:, [0, 1, 5, 4]], v[:, [0, 4, 5, 3]]], axis=1)
    b = np.stack([v[:, [0, 1, 2, 4]], v[:, [0, 4, 2, 5]], v[:, [0, 4, 5, 3]]], axis=1)
    return np.where(first[:, None, None], a, b).reshape(-1, 4)


def split_quads(quads: np.ndarray) -> np.ndarray:
    """(n, 4) quads (a, b, a', b'), a' beside a and b' beside b -> (2n, 3) triangles cut from the smallest vertex."""
    a, b, ta, tb = quads.T
    from_a = np.minimum(a, tb) < np.minimum(b, ta)
    one = np.where(from_a[:, None], np.stack([a, b, tb], 1), np.stack([a, b, ta], 1))
    two = np.where(from_a[:, None], np.stack([a, tb, ta], 1), np.stack([b, tb, ta], 1))
    return np.concatenate([one, two])


def _layer_cells(mesh: Mesh, creases: _Creases, copies: _Copies) -> np.ndarray:
    """Cells of the layer, in the extended numbering (copy k is node N + k)."""
    n, d = mesh.n_nodes, mesh.dim
    top = n + copies.cluster[creases.slot_cluster]  # (F, d) the copy above each facet node
    bottom = mesh.boundary_facets
    if d == 1:
        return np.concatenate([bottom, top], axis=1)
    if d == 2:
        parts = [split_quads(np.concatenate([bottom, top], axis=1))]
    else:
        parts = [split_prisms(np.concatenate([bottom, top], axis=1))]
    fans, wedges = [], []
    for a, b, f1, f2 in creases.creases:
        ends = []
        for node in (int(a), int(b)):
            c1, c2 = _cluster_at(creases, mesh, f1, node), _cluster_at(creases, mesh, f2, node)
            ends.append((node, n + c1, n + copies.bisector[(node, *sorted((c1, c2)))], n + c2))
        (a0, a1, a12, a2), (b0, b1, b12, b2) = ends
        if d == 2:
            fans += [(a0, a1, a12), (a0, a12, a2)]
        else:
            wedges += [(a0, a1, a12, b0, b1, b12), (a0, a12, a2, b0, b12, b2)]
            for v, v1, v12, v2 in ends:
                if v in copies.apex:
                    fans += [(v, v1, v12, n + copies.apex[v]), (v, v12, v2, n + copies.apex[v])]
    if wedges:
        parts.append(split_prisms(np.array(wedges, dtype=np.int64)))
    if fans:
        parts.append(np.array(fans, dtype=np.int64))
    return np.concatenate(parts)


def with_extra_layer(mesh: Mesh, thickness: float = 1.0, min_quality: float = 0.1) -> ExtendedMesh:
    """Add one layer of cells outside the boundary of ``mesh`` (see the module docstring).

    thickness: offset of the copies in units of the mean length of the copied node's edges
        (mitred at corners); the solver uses the same default. With it, plain MLS weights of
        particles in boundary cells are non-negative in 2D; in 3D a few are slightly negative
        within one element of convex creases and curved boundaries, whatever the thickness
        (measured in tests/test_kernels.py, explained in the module docstring), and the
        UMLS kernel projects them (``umls_kernel(..., nonnegative=True)``).
    min_quality: layer cells below this quality get the offsets of their outside nodes
        halved (up to eight times), e.g. inside holes narrower than the layer.

    Returns an :class:`ExtendedMesh`; the physical nodes and cells keep their indices.
    Raises MeshError at cusps too sharp to offset, or if the layer has degenerate cells.
    """
    if not thickness > 0:
        raise ValueError(f"thickness must be positive, got {thickness}")
    n = mesh.n_nodes
    creases = _creases(mesh)
    copies = _copies(mesh, creases, thickness)
    layer = _layer_cells(mesh, creases, copies)
    scale = np.ones(copies.node.size)
    for _ in range(8):
        nodes = np.concatenate([mesh.nodes, mesh.nodes[copies.node] + scale[:, None] * copies.offset])
        flip = signed_measures(nodes, layer) < 0
        layer[flip, -2:] = layer[flip][:, [-1, -2]]
        squeezed = layer[simplex_quality(nodes, layer) < min_quality]
        if squeezed.size == 0:
            break
        scale[np.unique(squeezed[squeezed >= n]) - n] *= 0.5
    try:
        extended = Mesh(nodes, np.concatenate([mesh.cells, layer], axis=0))
    except MeshError as exc:
        raise MeshError(f"the extra layer is invalid ({exc}); the boundary is too irregular for it") from None
    node_outside = np.zeros(extended.n_nodes, dtype=bool)
    node_outside[n:] = True
    cell_outside = np.zeros(extended.n_cells, dtype=bool)
    cell_outside[mesh.n_cells:] = True
    return ExtendedMesh(extended, node_outside, cell_outside)
