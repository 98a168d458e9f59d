"""Which simplex contains each particle: a spatial hash of cell bounding boxes (UMLS App. A).

Build once per mesh (:class:`CellLocator`), then :func:`locate` answers for all particles
at once: the hash bucket of each particle gives a short, padded list of candidate cells,
the barycentric coordinates in every candidate are computed in one batched product, and
the candidate where the particle is deepest inside wins. A particle inside no cell is
reported with a status (:class:`LocateStatus`), never dropped or moved.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import torch

from ..mesh import Mesh
from . import native

__all__ = ["CellLocator", "Location", "LocateStatus", "locate", "barycentric"]

BARYCENTRIC_TOL = 1e-10
"""A particle is inside a cell when all its barycentric coordinates are >= -tol."""

_CHUNK_ENTRIES = 1 << 22  # particle-candidate pairs handled per batch (bounds memory)


class LocateStatus(enum.IntEnum):
    INSIDE = 0
    OUTSIDE = 1  # finite position inside no cell
    NONFINITE = 2  # NaN or inf position


@dataclass(frozen=True)
class Location:
    """Where particles are.

    cell: (P,) int64 containing cell, -1 where the status is not INSIDE.
    bary: (P, d+1) barycentric coordinates in ``cell`` (zeros where not INSIDE).
    status: (P,) int8 :class:`LocateStatus` codes.
    """

    cell: torch.Tensor
    bary: torch.Tensor
    status: torch.Tensor

    @property
    def n_lost(self) -> int:
        """Number of particles not inside any cell."""
        return int((self.status != LocateStatus.INSIDE).sum())


@dataclass(frozen=True, eq=False)
class CellLocator:
    """Per-mesh tables for :func:`locate` (torch tensors on one device).

    origin: (d,) corner of the hash grid; spacing: bucket edge length; shape: (d,) buckets
    per axis; buckets: (B, K) candidate cells per bucket, -1 padded; corner: (C, d) node 0 of
    each cell; to_bary: (C, d, d) maps ``x - corner`` to barycentric coordinates 1..d.
    """

    origin: torch.Tensor
    spacing: float
    shape: torch.Tensor
    strides: torch.Tensor
    buckets: torch.Tensor
    corner: torch.Tensor
    to_bary: torch.Tensor

    @classmethod
    def build(cls, mesh: Mesh, *, device="cpu", dtype=torch.float64) -> CellLocator:
        nodes, cells = mesh.nodes, mesh.cells
        lo_box = nodes[cells].min(axis=1)  # (C, d) cell bounding boxes
        hi_box = nodes[cells].max(axis=1)
        spacing = float((hi_box - lo_box).max(axis=1).mean())
        origin = nodes.min(axis=0) - 1e-9 * max(spacing, 1.0)
        shape = np.floor((nodes.max(axis=0) - origin) / spacing).astype(np.int64) + 1
        lo = np.clip(np.floor((lo_box - origin) / spacing).astype(np.int64), 0, shape - 1)
        hi = np.clip(np.floor((hi_box - origin) / spacing).astype(np.int64), 0, shape - 1)
        strides = np.cumprod(np.concatenate([[1], shape[::-1][:-1]]))[::-1].copy()
        table = _bucket_table(lo, hi, strides, int(np.prod(shape)))
        spans = nodes[cells[:, 1:]] - nodes[cells[:, :1]]  # (C, d, d), rows are edges
        to_bary = np.linalg.inv(np.swapaxes(spans, 1, 2))
        as_t = lambda a, dt=dtype: torch.tensor(np.asarray(a), dtype=dt, device=device)  # noqa: E731
        return cls(
            origin=as_t(origin), spacing=spacing, shape=as_t(shape, torch.int64),
            strides=as_t(strides, torch.int64), buckets=as_t(table, torch.int64),
            corner=as_t(nodes[cells[:, 0]]), to_bary=as_t(to_bary),
        )

    @property
    def dim(self) -> int:
        return self.corner.shape[1]


def _bucket_table(lo: np.ndarray, hi: np.ndarray, strides: np.ndarray, n_buckets: int) -> np.ndarray:
    """(n_buckets, K) padded lists of the cells whose bounding box touches each bucket."""
    span = hi - lo + 1  # (C, d) buckets per axis touched by each cell
    count = span.prod(axis=1)
    cell = np.repeat(np.arange(len(lo)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    key = np.zeros_like(local)
    for axis in reversed(range(lo.shape[1])):  # mixed-radix digits of `local`
        key += (lo[cell, axis] + local % span[cell, axis]) * strides[axis]
        local //= span[cell, axis]
    order = np.argsort(key, kind="stable")
    key, cell = key[order], cell[order]
    per_bucket = np.bincount(key, minlength=n_buckets)
    slot = np.arange(key.size) - np.repeat(np.cumsum(per_bucket) - per_bucket, per_bucket)
    table = np.full((n_buckets, max(int(per_bucket.max()), 1)), -1, dtype=np.int64)
    table[key, slot] = cell
    return table


def barycentric(locator: CellLocator, cell: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Barycentric coordinates of ``x: (..., d)`` in ``cell: (...)`` -> (..., d+1). UMLS eq. 33."""
    flat = cell.reshape(-1)
    to_bary = locator.to_bary.index_select(0, flat).reshape(cell.shape + locator.to_bary.shape[1:])
    corner = locator.corner.index_select(0, flat).reshape(cell.shape + locator.corner.shape[1:])
    rest = (to_bary * (x - corner)[..., None, :]).sum(-1)  # elementwise: batched tiny matmuls are slow
    return torch.cat([1.0 - rest.sum(-1, keepdim=True), rest], dim=-1)


def _search(locator: CellLocator, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Hash search for finite ``x: (P, d)`` -> (cell (P,), bary (P, d+1), found (P,) bool)."""
    idx = torch.floor((x - locator.origin) / locator.spacing).long()
    in_grid = ((idx >= 0) & (idx < locator.shape)).all(dim=1)
    key = (idx.clamp(min=0) * locator.strides).sum(dim=1).clamp(max=locator.buckets.shape[0] - 1)
    candidates = torch.where(in_grid[:, None], locator.buckets[key], -1)  # (P, K)
    valid = candidates >= 0
    bary = barycentric(locator, candidates.clamp(min=0), x[:, None, :])  # (P, K, d+1)
    depth = torch.where(valid, bary.min(dim=-1).values, -math.inf)
    best = depth.argmax(dim=1)
    rows = torch.arange(len(x), device=x.device)
    found = depth[rows, best] >= -BARYCENTRIC_TOL
    return candidates[rows, best], bary[rows, best], found


def locate(locator: CellLocator, x: torch.Tensor, guess: torch.Tensor | None = None) -> Location:
    """Containing cell and barycentric coordinates of every particle.

    x: (P, d) positions. guess: optional (P,) cells to try first (e.g. last step's cells;
    -1 = no guess); particles not inside their guess are searched through the hash.
    A particle on a shared face may belong to either cell; the search prefers the cell
    where its smallest barycentric coordinate is largest.
    """
    x = torch.as_tensor(x, dtype=locator.corner.dtype, device=locator.corner.device)
    n, d = x.shape
    cell = torch.full((n,), -1, dtype=torch.int64, device=x.device)
    bary = torch.zeros((n, d + 1), dtype=x.dtype, device=x.device)
    finite = torch.isfinite(x).all(dim=1)
    todo = finite
    if guess is not None:
        guess = guess.to(x.device)
        compiled = native.locate_guess(locator, x, guess, BARYCENTRIC_TOL)
        if compiled is not None:
            cell, bary = compiled
            hit = cell >= 0
        else:
            trial = barycentric(locator, guess.clamp(min=0), x)
            hit = finite & (guess >= 0) & (trial.min(dim=1).values >= -BARYCENTRIC_TOL)
            cell = torch.where(hit, guess, cell)
            bary = torch.where(hit[:, None], trial, bary)
        todo = finite & ~hit
    pending = torch.nonzero(todo).flatten()
    chunk = max(1, _CHUNK_ENTRIES // max(1, locator.buckets.shape[1] * (d + 1)))
    for start in range(0, pending.numel(), chunk):
        rows = pending[start:start + chunk]
        found_cell, found_bary, found = _search(locator, x[rows])
        cell[rows] = torch.where(found, found_cell, -1)
        bary[rows] = torch.where(found[:, None], found_bary, 0.0)
    status = torch.full((n,), int(LocateStatus.INSIDE), dtype=torch.int8, device=x.device)
    status[cell < 0] = int(LocateStatus.OUTSIDE)
    status[~finite] = int(LocateStatus.NONFINITE)
    return Location(cell=cell, bary=bary, status=status)
