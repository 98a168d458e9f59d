"""Transfer kernels: per particle, padded node indices, weights w_ip and gradients grad w_ip.

Every kernel returns a :class:`KernelResult` with ``index (P, K)`` (-1 = empty slot),
``weight (P, K)`` and ``grad (P, K, d)``; empty slots have weight and gradient exactly 0.

- :func:`umls_kernel` — UMLS-MPM (UMLS §2.3): MLS with a linear basis over the 1-ring of the
  containing simplex, quadratic B-spline sample weights times the diminishing factor eta.
- :func:`linear_kernel` — the C0 barycentric hat (suffers the cell-crossing error).
- :func:`bspline_kernel` — quadratic B-spline MLS-MPM on a regular :class:`Grid` (the structured B-spline solver).

Mesh kernels take a :class:`~datagen.mesh.Mesh`, an :class:`~datagen.mesh.ExtendedMesh`, or
prebuilt :class:`MeshTables`; build the tables once (``MeshTables.build``) when calling
every step, since building them costs far more than a kernel evaluation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch

from ..layer import ExtendedMesh
from ..mesh import Mesh
from . import linalg, native
from .locate import CellLocator, LocateStatus, Location, locate

__all__ = [
    "KernelResult", "MeshTables", "Grid", "umls_kernel", "umls_kernel_p2g", "linear_kernel", "bspline_kernel",
    "quadratic_bspline", "mls_linear_weights", "nonnegative_mls",
]

_RING_CHUNK = 1 << 14  # cells per batch when tabulating ring adjacency


@dataclass(frozen=True)
class KernelResult:
    """Kernel of P particles over padded slots of K nodes each.

    index: (P, K) int64 node ids, -1 for empty slots (and for every slot of a lost particle).
    weight: (P, K) w_ip. grad_axes: (d, P, K) the components of grad w_ip (0 in empty slots),
    one contiguous block per axis. offsets: (d, P, K) the components of x_i - x_p likewise, or
    None to compute them on first use of :attr:`offset_axes` from ``positions`` = (nodes by axis
    (d, N), particles (P, d)) (only APIC reads them). status: (P,) int8 LocateStatus codes.
    cell: (P,) containing cell on a mesh (-1 if lost), None on a grid.
    """

    index: torch.Tensor
    weight: torch.Tensor
    grad_axes: torch.Tensor
    offsets: torch.Tensor | None
    status: torch.Tensor
    cell: torch.Tensor | None = None
    positions: tuple[torch.Tensor, torch.Tensor] | None = None

    @property
    def offset_axes(self) -> torch.Tensor:
        """(d, P, K) the components of x_i - x_p (0 in empty slots)."""
        if self.offsets is None:
            nodes, x = self.positions
            object.__setattr__(self, "offsets", _node_offsets(nodes, self.index, x).masked_fill_(self.index < 0, 0.0))
        return self.offsets

    @property
    def grad(self) -> torch.Tensor:
        """(P, K, d) grad w_ip (a view of grad_axes)."""
        return self.grad_axes.permute(1, 2, 0)

    @property
    def offset(self) -> torch.Tensor:
        """(P, K, d) x_i - x_p (a view of offset_axes)."""
        return self.offset_axes.permute(1, 2, 0)

    @property
    def n_lost(self) -> int:
        return int((self.status != LocateStatus.INSIDE).sum())

    def select(self, rows: torch.Tensor) -> KernelResult:
        """The kernel of the particles ``rows`` (an index tensor) only."""
        offsets = self.offsets[:, rows] if self.offsets is not None else None
        positions = (self.positions[0], self.positions[1][rows]) if self.positions is not None else None
        return KernelResult(index=self.index[rows], weight=self.weight[rows], grad_axes=self.grad_axes[:, rows],
                            offsets=offsets, status=self.status[rows],
                            cell=self.cell[rows] if self.cell is not None else None, positions=positions)


# ----------------------------------------------------------------------------- mesh tables
@dataclass(frozen=True, eq=False)
class MeshTables:
    """Everything the mesh kernels need, precomputed once per mesh, on one device.

    nodes: (N, d); cells: (C, d+1); ring: (C, K) the 1-ring N^1 of each cell's nodes N^0,
    -1 padded; ring_adjacency: (C, d+1, K) bool A(n, i) with self-loops for cell node n and
    ring node i; bary_grad: (C, d+1, d) gradients of the barycentric coordinates; h: the
    B-spline length (the physical mesh's longest edge); node_outside / cell_outside: (N,) /
    (C,) bool, True in the extra layer (all False for a plain mesh).
    """

    nodes: torch.Tensor
    cells: torch.Tensor
    ring: torch.Tensor
    ring_adjacency: torch.Tensor
    bary_grad: torch.Tensor
    h: float
    locator: CellLocator
    node_outside: torch.Tensor
    cell_outside: torch.Tensor
    mesh: Mesh

    def __post_init__(self):
        object.__setattr__(self, "_nodes_by_axis", self.nodes.T.contiguous())

    @classmethod
    def build(cls, mesh: Mesh | ExtendedMesh, *, h: float | None = None, device="cpu",
              dtype=torch.float64) -> MeshTables:
        """Tables for ``mesh``; h defaults to the longest edge of the physical mesh."""
        if isinstance(mesh, ExtendedMesh):
            whole, node_outside, cell_outside = mesh.mesh, mesh.node_outside, mesh.cell_outside
        else:
            whole = mesh
            node_outside = np.zeros(mesh.n_nodes, dtype=bool)
            cell_outside = np.zeros(mesh.n_cells, dtype=bool)
        if h is None:
            inner = ~node_outside[whole.edges].any(axis=1)
            h = float(whole.edge_lengths[inner].max())
        ring, ring_adj = _ring_tables(whole)
        as_t = lambda a, dt=dtype: torch.tensor(np.asarray(a), dtype=dt, device=device)  # noqa: E731
        return cls(
            nodes=as_t(whole.nodes), cells=as_t(whole.cells, torch.int64), ring=as_t(ring, torch.int64),
            ring_adjacency=as_t(ring_adj, torch.bool), bary_grad=as_t(_barycentric_gradients(whole)),
            h=float(h), locator=CellLocator.build(whole, device=device, dtype=dtype),
            node_outside=as_t(node_outside, torch.bool), cell_outside=as_t(cell_outside, torch.bool),
            mesh=whole,
        )

    @property
    def dim(self) -> int:
        return self.nodes.shape[1]

    @property
    def n_nodes(self) -> int:
        return self.nodes.shape[0]

    @property
    def nodes_by_axis(self) -> torch.Tensor:
        """(d, N) contiguous node coordinates, one row per axis."""
        return self._nodes_by_axis


def _ring_tables(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Padded 1-ring of every cell and the adjacency of ring nodes to the cell's nodes."""
    n, (c, k) = mesh.n_nodes, mesh.cells.shape
    adj = mesh.adjacency(self_loops=True)
    owner = np.repeat(np.arange(c), k)
    incidence = sp.csr_matrix((np.ones(c * k), (owner, mesh.cells.ravel())), shape=(c, n))
    reach = (incidence @ adj).tocsr()
    reach.sort_indices()
    counts = np.diff(reach.indptr)
    slot = np.arange(reach.nnz) - np.repeat(reach.indptr[:-1], counts)
    ring = np.full((c, counts.max()), -1, dtype=np.int64)
    ring[np.repeat(np.arange(c), counts), slot] = reach.indices
    coo = adj.tocoo()
    keys = np.sort(coo.row.astype(np.int64) * n + coo.col)
    ring_adj = np.zeros(ring.shape + (k,), dtype=bool)
    for start in range(0, c, _RING_CHUNK):
        part = slice(start, start + _RING_CHUNK)
        query = ring[part, :, None] * n + mesh.cells[part, None, :]
        pos = np.clip(np.searchsorted(keys, query), 0, keys.size - 1)
        ring_adj[part] = (keys[pos] == query) & (ring[part, :, None] >= 0)
    return ring, np.ascontiguousarray(ring_adj.transpose(0, 2, 1))


def _barycentric_gradients(mesh: Mesh) -> np.ndarray:
    """(C, d+1, d): row n is the (constant) gradient of barycentric coordinate n in each cell."""
    nodes, cells = mesh.nodes, mesh.cells
    spans = nodes[cells[:, 1:]] - nodes[cells[:, :1]]  # (C, d, d), rows are edges
    rest = np.linalg.inv(np.swapaxes(spans, 1, 2))  # row k: gradient of lambda_{k+1}
    return np.concatenate([-rest.sum(axis=1, keepdims=True), rest], axis=1)


def _as_tables(mesh) -> MeshTables:
    if isinstance(mesh, MeshTables):
        return mesh
    if isinstance(mesh, (Mesh, ExtendedMesh)):
        return MeshTables.build(mesh)
    raise TypeError(f"expected a Mesh, ExtendedMesh or MeshTables, got {type(mesh).__name__}")


def _as_positions(x, tables_nodes: torch.Tensor) -> torch.Tensor:
    x = torch.as_tensor(x, dtype=tables_nodes.dtype, device=tables_nodes.device)
    if x.ndim != 2 or x.shape[1] != tables_nodes.shape[1]:
        d = tables_nodes.shape[1]
        raise ValueError(f"particle positions must have shape (P, {d}), got {tuple(x.shape)}")
    return x


# ----------------------------------------------------------------------------- shared numerics
def quadratic_bspline(q: torch.Tensor) -> torch.Tensor:
    """Quadratic B-spline N(q) of a non-negative scaled distance q (support q < 1.5)."""
    outer = (1.5 - q).clamp_(min=0.0).square_().mul_(0.5)
    return outer.where(q >= 0.5, 0.75 - q * q)


def mls_linear_weights(d: torch.Tensor, r: torch.Tensor, *,
                       evaluate: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """MLS kernel with the linear basis p(z) = [1, z - x_p] (UMLS eqs. 22-29).

    d: (P, K) sample weights d_i (0 in empty slots); r: (dim, P, K) the components of the
    offsets x_i - x_p. Returns w (P, K) and grad w (dim, P, K): the rows of d_i M^-1 p(x_i - x_p).
    With S = sum d, mean offset m = sum d r / S and covariance Q = sum d (r-m)(r-m)^T / S,
    the block inverse of M gives w_i = d_i/S (1 - m^T Q^-1 (r_i - m)) and
    grad w_i = d_i/S Q^-1 (r_i - m): one dim x dim inverse instead of (dim+1) x (dim+1).
    Rows with S = 0 (lost particles) give zeros.

    evaluate: (P, K) weights e_i to evaluate the fit with: the moment matrix M is built from d
    but the results are e_i p_i^T M^-1 p(0) and its gradient part (default e = d).
    """
    total = d.sum(dim=1)
    alive = total > 0
    inv_total = 1.0 / torch.where(alive, total, torch.ones_like(total))[:, None]
    share = d * inv_total  # d_i / S
    r_p = r.permute(1, 0, 2)  # (P, dim, K) view
    m = torch.bmm(r_p, share[:, :, None])  # (P, dim, 1)
    rc = r_p - m
    src = rc * share[:, None, :]
    q = torch.bmm(src, rc.transpose(1, 2))
    q_inv = linalg.inv(torch.where(alive[:, None, None], q, linalg.identity_like(q)))
    if evaluate is not None:
        share = evaluate * inv_total
        src = rc * share[:, None, :]
    dim = r.shape[0]  # below, elementwise sums beat batched products of tiny matrices
    grad = torch.empty_like(r)
    weight = share.clone()
    for a in range(dim):  # UMLS eq. 29
        torch.mul(src[:, 0], q_inv[:, a, 0, None], out=grad[a])
        for b in range(1, dim):
            grad[a].addcmul_(src[:, b], q_inv[:, a, b, None])
        weight.addcmul_(grad[a], m[:, a], value=-1.0)
    return weight, grad


def nonnegative_mls(d: torch.Tensor, r: torch.Tensor, start: torch.Tensor, start_grad: torch.Tensor, *,
                    mls_weight: torch.Tensor | None = None, max_iter: int | None = None,
                    tol: float = 1e-13) -> tuple[torch.Tensor, torch.Tensor]:
    """The closest non-negative kernel to MLS that still reproduces linear functions.

    MLS weights (:func:`mls_linear_weights`) minimise sum w_i^2 / d_i subject to reproducing
    linear functions, sum w_i p(x_i - x_p) = p(0). With w >= 0 added this is a strictly convex
    QP; its solution is MLS on an active set A of nodes (w_i = d_i lambda^T p_i, M_A lambda =
    p(0)) with every other node at exactly 0 and lambda^T p_j <= 0 there. Solved per row by the
    primal active-set method, which keeps every iterate a non-negative, linearly exact kernel:
    it starts from ``start`` (such a kernel, e.g. the barycentric coordinates of the containing
    cell) with A = its support plus the nodes of positive MLS weight; a full step to MLS on A
    is taken when it is non-negative, and then the node whose fit is most positive enters A;
    otherwise the step stops where the first weight reaches 0, and that node leaves A.

    - where MLS is non-negative it is the solution (callers pass only rows that need this);
    - partition of unity, linear reproduction and sum grad w (x) x_i = I hold exactly, the
      gradient being the MLS fitted gradient on A;
    - the weights are continuous in the particle position: a node leaves A when its weight
      reaches 0, and (Sherman-Morrison) removing a zero-weight node changes no other weight.
      The fitted gradients of such a node jump by d_i/S Q^-1 (r_i - m), small for far nodes.

    d: (R, K) sample weights (0 in empty slots); r: (dim, R, K) offsets x_i - x_p;
    start: (R, K) / start_grad: (dim, R, K) a non-negative kernel with exact identities;
    mls_weight: (R, K) the plain MLS weights of these rows if already computed. Nodes
    enter A when their fit exceeds ``tol`` (so round-off cannot cycle). Rows that do not finish
    in ``max_iter`` iterations (default 4K; not seen in practice) keep ``start``.
    """
    candidate = d > 0
    if mls_weight is None:
        mls_weight, _ = mls_linear_weights(d, r)
    free = candidate & ((start > 0) | (mls_weight > 0))
    weight, grad = start.clone(), start_grad.clone()
    done = torch.zeros(d.shape[0], dtype=torch.bool, device=d.device)
    for _ in range(4 * d.shape[1] if max_iter is None else max_iter):
        fit, fit_grad = mls_linear_weights(d * free, r, evaluate=d)
        target = torch.where(free, fit, 0.0)
        blocked = free & (target < 0) & ~done[:, None]
        partial = blocked.any(dim=1)
        ratio = torch.where(blocked, weight / torch.where(blocked, weight - target, 1.0), torch.inf)
        alpha = ratio.amin(dim=1, keepdim=True).clamp(max=1.0)
        stepped = ((1 - alpha) * weight + alpha * target).clamp_(min=0.0)
        stepped.masked_fill_(blocked & (ratio <= alpha), 0.0)
        weight = torch.where(partial[:, None], stepped, weight)
        free &= ~(blocked & (ratio <= alpha))
        full = ~partial & ~done
        weight = torch.where(full[:, None], target, weight)
        grad = torch.where(full[None, :, None], fit_grad * free, grad)
        enter = ~free & candidate & (fit > tol) & full[:, None]
        entering = enter.any(dim=1)
        best = torch.where(enter, fit, -torch.inf).argmax(dim=1)
        free[entering.nonzero().squeeze(1), best[entering]] = True
        done |= full & ~entering
        if bool(done.all()):
            break
    weight = torch.where(done[:, None], weight, start)
    grad = torch.where(done[None, :, None], grad, start_grad)
    return weight, grad


def _barycentric_in_ring(tables: MeshTables, index: torch.Tensor, cell: torch.Tensor,
                         bary: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The linear hat of the containing cell written in the ring's slots: (R, K), (dim, R, K)."""
    corners = _gather_rows(tables.cells, cell)  # (R, d+1)
    match = (index[:, None, :] == corners[:, :, None]).to(bary.dtype)  # (R, d+1, K)
    weight = torch.einsum("rn,rnk->rk", bary, match)
    grad = torch.einsum("rna,rnk->ark", _gather_rows(tables.bary_grad, cell), match)
    return weight, grad


def _gather_rows(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """table[index] for an index tensor of any shape (index_select is faster than indexing)."""
    return table.index_select(0, index.reshape(-1)).reshape(index.shape + table.shape[1:])


# ----------------------------------------------------------------------------- mesh kernels
def umls_kernel(mesh, x, eta: bool = True, *, nonnegative: bool = True, location: Location | None = None,
                guess: torch.Tensor | None = None) -> KernelResult:
    """UMLS-MPM kernel (UMLS §2.3.4) of particles ``x: (P, d)``.

    Active nodes are the 1-ring N^1 of the containing cell; sample weights are
    d_i = N(|x_i - x_p| / h) * eta_i with N the quadratic B-spline, h the longest physical
    edge and eta_i = sum_{n in N^0} B_n A(i, n) (UMLS eq. 32, A with self-loops, B the
    barycentric coordinates, UMLS eq. 33). ``eta=False`` drops eta (the ablation of UMLS Fig. 7).

    nonnegative: where MLS gives a particle negative weights (boundary cells without the extra
    layer, UMLS Fig. 5; with it, a few particles near 3D creases), use the closest non-negative
    kernel that still reproduces linear functions (:func:`nonnegative_mls`); other particles
    are unaffected. ``False`` gives the plain MLS kernel of the paper.

    mesh: Mesh, ExtendedMesh or MeshTables. location: a precomputed :func:`locate` result
    for ``x``; guess: (P,) cells to try first when locating.
    """
    return _umls_kernel(mesh, x, eta, nonnegative, location, guess)[0]


def umls_kernel_p2g(mesh, x, mass: torch.Tensor, v: torch.Tensor, coef: torch.Tensor, n_nodes: int, *,
                    guess: torch.Tensor | None = None):
    """:func:`umls_kernel` (eta, non-negative) and, where the compiled loops run, the FLIP/PIC P2G
    sums [m, p, f_int] (1+2d, N) of particles with mass (P,), velocity (P, d) and
    coef = -V^0 times the force stress (P, d, d), summed in the same pass over the particles.
    Returns (kernel, sums, left_out): the particles whose MLS kernel was replaced by its
    non-negative one are left out of the sums (the caller adds them with the final kernel);
    sums and left_out are None where the loops are not compiled."""
    return _umls_kernel(mesh, x, True, True, None, guess, (mass, v, coef, n_nodes))


def _umls_kernel(mesh, x, eta: bool, nonnegative: bool, location: Location | None, guess: torch.Tensor | None,
                 p2g: tuple | None = None):
    tables = _as_tables(mesh)
    x = _as_positions(x, tables.nodes)
    if location is None:
        location = locate(tables.locator, x, guess)
    cell = location.cell.clamp(min=0)
    compiled = native.umls_weights(tables, x, location, eta, p2g)
    sums = left_out = None
    if compiled is not None:  # offsets are computed on first use (APIC)
        (index, weight, grad, negative), r = compiled[:4], None
        negative_rows = negative.nonzero().squeeze(1)
        if p2g is not None:
            sums, left_out = compiled[4], negative_rows
        rows = negative_rows if nonnegative else None
    else:
        index = _gather_rows(tables.ring, cell)
        index = index.masked_fill_((location.status != LocateStatus.INSIDE)[:, None], -1)
        r = _node_offsets(tables.nodes_by_axis, index, x)
        d = _sample_weights(tables, r, index, cell, location.bary, eta)
        weight, grad = mls_linear_weights(d, r)
        rows = (weight < 0).any(dim=1).nonzero().squeeze(1) if nonnegative else None
        r.masked_fill_(index < 0, 0.0)
    if rows is not None and rows.numel():
        rows_r = (r.index_select(1, rows) if r is not None
                  else _node_offsets(tables.nodes_by_axis, index[rows], x[rows]).masked_fill_(index[rows] < 0, 0.0))
        d_rows = _sample_weights(tables, rows_r, index[rows], cell[rows], location.bary[rows], eta)
        start = _barycentric_in_ring(tables, index[rows], cell[rows], location.bary[rows])
        weight[rows], grad[:, rows] = nonnegative_mls(d_rows, rows_r, *start, mls_weight=weight[rows])
    k = KernelResult(index=index, weight=weight, grad_axes=grad, offsets=r, status=location.status,
                     cell=location.cell, positions=(tables.nodes_by_axis, x))
    return k, sums, left_out


def _sample_weights(tables: MeshTables, r: torch.Tensor, index: torch.Tensor, cell: torch.Tensor,
                    bary: torch.Tensor, eta: bool) -> torch.Tensor:
    """(R, K) UMLS sample weights d_i = N(|x_i - x_p| / h) eta_i (0 in empty slots) from the offsets
    r: (d, R, K) of the slots ``index`` of particles in ``cell`` at barycentric coordinates ``bary``."""
    q = torch.mul(r[0], r[0])
    for a in range(1, tables.dim):
        q.addcmul_(r[a], r[a])
    d = quadratic_bspline(q.sqrt_().mul_(1.0 / tables.h))
    if eta:  # zero in empty slots, whose adjacency is False
        adjacency = _gather_rows(tables.ring_adjacency, cell)  # (R, d+1, K)
        d.mul_(sum(bary[:, n, None] * adjacency[:, n] for n in range(tables.dim + 1)))  # UMLS eq. 32
    else:
        d.masked_fill_(index < 0, 0.0)
    return d


def _node_offsets(nodes_by_axis: torch.Tensor, index: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(d, P, K) components of x_i - x_p for the nodes in ``index`` (-1 slots: node 0);
    nodes_by_axis: (d, N)."""
    flat = index.clamp(min=0).reshape(-1)
    dim = nodes_by_axis.shape[0]
    r = torch.empty((dim, flat.numel()), dtype=x.dtype, device=x.device)
    for a, row in enumerate(nodes_by_axis):
        torch.index_select(row, 0, flat, out=r[a])
    return r.view((dim,) + index.shape).sub_(x.T[:, :, None])


def linear_kernel(mesh, x, *, location: Location | None = None,
                  guess: torch.Tensor | None = None) -> KernelResult:
    """C0 linear hat: w = barycentric coordinates in the containing cell, grad w constant there."""
    tables = _as_tables(mesh)
    x = _as_positions(x, tables.nodes)
    if location is None:
        location = locate(tables.locator, x, guess)
    inside = (location.status == LocateStatus.INSIDE)[:, None]
    cell = location.cell.clamp(min=0)
    index = torch.where(inside, _gather_rows(tables.cells, cell), -1)
    weight = torch.where(inside, location.bary, 0.0)
    grad = _gather_rows(tables.bary_grad, cell).permute(2, 0, 1) * inside  # (d, P, d+1)
    corners = _gather_rows(tables.nodes, _gather_rows(tables.cells, cell))  # (P, d+1, d)
    offset = (corners - x[:, None, :]).permute(2, 0, 1) * inside
    return KernelResult(index=index, weight=weight, grad_axes=grad.contiguous(),
                        offsets=offset.contiguous(), status=location.status, cell=location.cell)


# ----------------------------------------------------------------------------- structured grid
@dataclass(frozen=True)
class Grid:
    """A regular grid of nodes: ``origin + spacing * (i_1, ..., i_d)`` for 0 <= i_k < shape[k].

    Nodes are numbered in C order (last axis fastest).
    """

    origin: tuple[float, ...]
    spacing: float
    shape: tuple[int, ...]

    @classmethod
    def covering(cls, lower, upper, spacing: float, pad: int = 2) -> Grid:
        """The grid of nodes at integer multiples of ``spacing`` (so walls and clamps at round
        coordinates fall on nodes) covering the box [lower, upper] with ``pad`` more nodes per side."""
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        first = np.floor(lower / spacing + 1e-9) - pad
        last = np.ceil(upper / spacing - 1e-9) + pad
        origin = first * spacing
        shape = (last - first).astype(int) + 1
        return cls(tuple(origin.tolist()), float(spacing), tuple(int(s) for s in shape))

    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def n_nodes(self) -> int:
        return int(np.prod(self.shape))

    def nodes(self) -> np.ndarray:
        """(N, d) node coordinates in numbering order."""
        axes = [self.origin[k] + self.spacing * np.arange(n) for k, n in enumerate(self.shape)]
        return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)


def bspline_kernel(grid: Grid, x: torch.Tensor) -> KernelResult:
    """Quadratic B-spline MLS-MPM kernel on a regular grid: 3^d nodes per particle.

    On a regular grid the MLS moment matrix is h^2/4 I, so w_ip = N(x) the tensor-product
    B-spline and grad w_ip = 4/h^2 w_ip (x_i - x_p) (the MLS-MPM gradient). Particles whose
    stencil leaves the grid are reported OUTSIDE with empty slots.
    """
    x = torch.as_tensor(x)
    h, d = grid.spacing, grid.dim
    origin = torch.tensor(grid.origin, dtype=x.dtype, device=x.device)
    shape = torch.tensor(grid.shape, device=x.device)
    scaled = (x - origin) / h
    base = torch.floor(scaled - 0.5)  # (P, d) lowest stencil node
    frac = scaled - base  # in [0.5, 1.5)
    per_axis = torch.stack([0.5 * (1.5 - frac) ** 2, 0.75 - (frac - 1.0) ** 2, 0.5 * (frac - 0.5) ** 2], -1)
    offsets = torch.cartesian_prod(*[torch.arange(3, device=x.device)] * d).reshape(-1, d)  # (3^d, d)
    node = base.long()[:, None, :] + offsets  # (P, 3^d, d)
    weight = torch.ones(node.shape[:2], dtype=x.dtype, device=x.device)
    for axis in range(d):
        weight = weight * per_axis[:, axis, :][:, offsets[:, axis]]
    r = (node.to(x.dtype) - scaled[:, None, :]) * h  # x_i - x_p
    strides = torch.tensor([math.prod(grid.shape[k + 1:]) for k in range(d)], device=x.device)
    finite = torch.isfinite(x).all(dim=1)
    inside = ((node >= 0) & (node < shape)).all(dim=-1).all(dim=-1) & finite
    index = torch.where(inside[:, None], (node * strides).sum(-1), -1)
    weight = torch.where(inside[:, None], weight, 0.0)
    offset = (r * inside[:, None, None]).permute(2, 0, 1).contiguous()
    grad = (4.0 / h**2) * weight * offset
    status = torch.full_like(index[:, 0], int(LocateStatus.INSIDE), dtype=torch.int8)
    status[~inside] = int(LocateStatus.OUTSIDE)
    status[~finite] = int(LocateStatus.NONFINITE)
    return KernelResult(index=index, weight=weight, grad_axes=grad, offsets=offset, status=status)
