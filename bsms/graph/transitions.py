"""Non-parametric transitions between adjacent bi-stride levels (thesis §4.3.2).

Between a fine level (N nodes, adjacency A, nodal weights w; w = 1 on the mesh) and the
coarse level of its kept nodes K:

1. T = A + I when ``self_loops`` (a kept node contributes its own value), else T = A; a node
   without neighbours always keeps its self-loop, or it would have nowhere to go.
2. Row-normalise, Â_ij = T_ij / sum_j T_ij: each sender spreads its weight evenly over
   the nodes it touches, ŵ_ij = w_i Â_ij.
3. A kept receiver j collects W_j = sum_i ŵ_ij, its nodal weight on the coarse level (the
   weights accumulate from level to level).
4. Contribution table C_ij = ŵ_ij / W_j. **Down**: v_j = sum_i C_ij v_i, a weighted average
   (rows of the down operator sum to 1).
5. **Up** uses the same table transposed, v_i = sum_j U_ij v_j with U_ij = C_ij / sum_j C_ij:
   renormalised per fine node so that a constant field survives down-then-up (the thesis'
   plain transpose scales a node's value by how much it contributed). Every dropped node has
   a kept neighbour (bi-stride is 2-CC); a kept node that has neither its self-loop nor a
   kept neighbour takes its own coarse value.

Operators are stored as COO triplets (:class:`Transition`): ``out[rows] += weights *
x[cols]``, i.e. ``index_add`` / ``scatter_add`` in torch on any device.

Self-loop default: on. Measured with ``benchmarks/transition_self_loops.py``: relative L2
error of a down-then-up round trip of the smooth field sin 2x cos 3y + xy (+ sin 2.5z in 3D),
MinAve seeding:

=======================  =====  ==========  =========  ============
mesh                     nodes  round trip  self-loop  no self-loop
=======================  =====  ==========  =========  ============
disk r=1, h=0.03          4177  level 1       0.0139      0.0177
disk r=1, h=0.03          4177  level 2       0.0418      0.0451
glyph 'BSMS', h=0.02      2818  level 1       0.0152      0.0208
glyph 'BSMS', h=0.02      2818  level 2       0.0389      0.0447
annulus 0.4-1, h=0.03     3599  level 1       0.0187      0.0243
box 1^3, h=0.06           9028  level 1       0.0285      0.0300
sphere r=1, h=0.12        4719  level 1       0.0873      0.0913
=======================  =====  ==========  =========  ============

With its own value a kept node's coarse value stays centred on it; without, it averages the
ring around it and the round trip blurs more (4-37% larger error through one level).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["Transition", "transition_operators"]


@dataclass(frozen=True, eq=False)
class Transition:
    """A sparse linear map between levels as COO triplets: ``out[rows] += weights * x[cols]``.

    rows: (nnz,) int64 output nodes, sorted; cols: (nnz,) int64 input nodes;
    weights: (nnz,) float64, non-negative, each output's weights summing to 1;
    shape: (n_out, n_in). The hierarchy builds and caches numpy arrays; the learned models
    read the same triplets as torch tensors (:func:`bsms.level_graph.level_graph`, batched by
    :meth:`bsms.level_graph.LevelGraph.transition`, applied by :func:`bsms.models.apply_transition`).
    :meth:`matrix` and :meth:`apply` are for the numpy form.
    """

    rows: np.ndarray
    cols: np.ndarray
    weights: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def from_csr(cls, matrix: sp.csr_matrix) -> Transition:
        matrix = matrix.tocsr()
        matrix.sort_indices()
        rows = np.repeat(np.arange(matrix.shape[0], dtype=np.int64), np.diff(matrix.indptr))
        return cls(rows, matrix.indices.astype(np.int64), matrix.data.astype(np.float64),
                   (int(matrix.shape[0]), int(matrix.shape[1])))

    def matrix(self) -> sp.csr_matrix:
        """The operator as a (n_out, n_in) scipy CSR matrix."""
        return sp.csr_matrix((self.weights, (self.rows, self.cols)), shape=self.shape)

    def apply(self, values: np.ndarray) -> np.ndarray:
        """values: (n_in, ...) -> (n_out, ...)."""
        values = np.asarray(values)
        if values.shape[:1] != (self.shape[1],):
            raise ValueError(f"values must have {self.shape[1]} rows (one per input node), "
                             f"got shape {values.shape}")
        out = np.zeros((self.shape[0], *values.shape[1:]), dtype=np.result_type(values, np.float64))
        np.add.at(out, self.rows, self.weights.reshape(-1, *[1] * (values.ndim - 1)) * values[self.cols])
        return out


def _up_from_down(down: sp.csr_matrix, kept: np.ndarray) -> sp.csr_matrix:
    """U = C^T renormalised per fine node; a kept node with an empty row takes its own value."""
    by_sender = down.tocsc()  # column i of C = row i of C^T
    up = sp.csr_matrix((by_sender.data, by_sender.indices, by_sender.indptr),
                       shape=(down.shape[1], down.shape[0]))
    orphans = np.flatnonzero(np.diff(up.indptr)[kept] == 0)  # kept, no loop, no kept neighbour
    if orphans.size:
        loops = sp.csr_matrix((np.ones(orphans.size), (kept[orphans], orphans)), shape=up.shape)
        up = (up + loops).tocsr()
    totals = np.add.reduceat(up.data, up.indptr[:-1])  # every row is non-empty now
    up.data = up.data / np.repeat(totals, np.diff(up.indptr))
    return up


def transition_operators(closed: sp.csr_matrix, kept: np.ndarray, degree: np.ndarray,
                         node_weights: np.ndarray, self_loops: bool = True
                         ) -> tuple[Transition, Transition, np.ndarray]:
    """Down and up operators between a level and its pooled level, and the coarse weights.

    closed: (K, N) 0/1 CSR rows of A + I at the kept nodes, sorted indices
    (:func:`bsms.graph.pooling.closed_rows`); kept: (K,) sorted fine indices of the coarse
    nodes; degree: (N,) neighbour count of each fine node; node_weights: (N,) accumulated
    weights w. -> (down (K, N), up (N, K), coarse node weights (K,)).
    """
    n, k = degree.size, kept.size
    receiver = np.repeat(np.arange(k), np.diff(closed.indptr))  # rows of T[kept, :] (T symmetric)
    sender = closed.indices
    lonely = degree == 0
    if not self_loops:
        keep = (sender != kept[receiver]) | lonely[sender]
        receiver, sender = receiver[keep], sender[keep]
    share = node_weights / (degree + (1 if self_loops else lonely))  # w_i / sum_j T_ij
    received = share[sender]  # ŵ_ij
    coarse_weights = np.bincount(receiver, weights=received, minlength=k)  # W_j
    contribution = received / coarse_weights[receiver]  # C_ij
    indptr = np.concatenate([[0], np.cumsum(np.bincount(receiver, minlength=k))])
    down = sp.csr_matrix((contribution, sender, indptr), shape=(k, n))
    return Transition.from_csr(down), Transition.from_csr(_up_from_down(down, kept)), coarse_weights
