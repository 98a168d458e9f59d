"""How the whole body answers a push, to first order: the node input of ``graph.elastic``.

An indenter pressing on a thin arm moves the arm's far end; a graph network that sees only the
rest shape and where the obstacle reaches into it has to work out from the mesh alone how
stiff each part of the body is and how it is held. This module computes the first-order answer
outright, on the body's rest mesh, with linear elasticity (P1 triangles in 2D, plane strain; P1
tetrahedra in 3D), E = 1 and the scene's Poisson ratio:

- the body is *held* where it touches the container (the walls around it, as
  :func:`bsms.physics.penetration.outlines` tells them): nodes within ``HOLD`` median rest edges of
  a wall are fixed -- a base bonded to the floor, a clamp;
- the load is the penetration input (:class:`bsms.physics.penetration.Penetration`), as a
  frictionless contact: each free node inside an obstacle is moved along the vector that would put
  it back on the obstacle's surface by at least its length and is free to slide across it, a node
  the contact would pull is released, and the rest of the body follows elastically
  (:meth:`ElasticResponse.constrained`). The answer is not scaled: Young's modulus drops out, and
  the input is a displacement field in world units.

Prescribing every penetrating node onto the obstacle's surface (a bilateral displacement
condition) over-constrains the body -- a solver's contact lets it sink in by part of a cell and
slide -- and matched the press family's test split worse in a first comparison; forces along the
pushes with the answer scaled to them where they act concentrate the strain under the loaded
nodes and give the far field too little (the press family's training bodies move 0.85-11 times as
far as that answer, 0.23-1.28 times as far as the contact's; ``graph.elastic_load: force``,
retired: docs/experiments.md). A tiny multiple of the stiffness' diagonal keeps a body that
nothing holds solvable (it then follows the push rigidly). The stiffness is factorised once per
scenario, when it is built (with its hierarchy: mesh preprocessing, outside a learned frame's time;
a process that unpickles a scenario makes its own on first use); a frame costs a solve pair per
pushed node not seen before.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import linalg, sparse
from scipy.optimize import nnls
from scipy.sparse.linalg import splu

from bsms.physics.penetration import closest_on_facets, outlines

__all__ = ["HOLD", "REGULARISATION", "CONTACT_ITERATIONS", "CACHED_NODES", "stiffness",
           "held_nodes", "ElasticResponse"]

# nodes within this many median rest edges of the container are held: the row on a bonded floor
# and the nodes just above it, which a solver's sticky grid holds too (on press_stiff's test split
# 0.05 edges left a J's answer at 0.79 of its at-rest error, 1 edge at 0.22:
# benchmarks/elastic_answer.py --hold, docs/press.md)
HOLD = 1.0
# K + REGULARISATION * mean(diag K) * I: solvable when nothing holds the body, negligible otherwise
REGULARISATION = 1e-9
# nodes whose unit responses an ElasticResponse keeps for constrained (dofs x dim floats each; training's
# datasets, which draw frames of many scenes, keep none)
CACHED_NODES = 1024
# active-set guesses ElasticResponse.constrained corrects before it solves as non-negative least squares
ACTIVE_SET_TRIES = 4
# ElasticResponse.constrained gives up after this many iterations per pushed node of its non-negative least squares
CONTACT_ITERATIONS = 10


def _gradients(rest: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, d+1, d) gradients of each cell's barycentric coordinates and (T,) cell measures."""
    corners = rest[cells]  # (T, d+1, d)
    edges = corners[:, 1:] - corners[:, :1]  # (T, d, d): rows are edge vectors
    det = np.linalg.det(edges)
    if np.any(np.abs(det) <= np.finfo(float).tiny):
        raise ValueError("graph.elastic: the body mesh has a degenerate cell (zero area or volume)")
    inner = np.linalg.inv(edges).transpose(0, 2, 1)  # (T, d, d): row k is the gradient of coordinate k+1
    grads = np.concatenate([-inner.sum(1, keepdims=True), inner], axis=1)
    return grads, np.abs(det) / math.factorial(rest.shape[1])


def stiffness(rest: np.ndarray, cells: np.ndarray, nu: float) -> sparse.csc_matrix:
    """(dN, dN) stiffness of linear elasticity with E = 1 and Poisson ratio ``nu`` on the simplex
    mesh ``rest`` (N, d), ``cells`` (T, d+1) (plane strain in 2D). Dof ``d i + k`` is node i's
    displacement along axis k. K[a i, b j] = sum over cells of measure (lam g_ai g_bj +
    mu (g_aj g_bi + delta_ij g_a . g_b)), g the barycentric gradients."""
    if not 0.0 <= nu < 0.5:
        raise ValueError(f"graph.elastic needs a Poisson ratio in [0, 0.5), got nu = {nu}; give the scene a "
                         "compressible material")
    rest, cells = np.asarray(rest, np.float64), np.asarray(cells, np.int64)
    n, dim = rest.shape
    lam, mu = nu / ((1 + nu) * (1 - 2 * nu)), 1.0 / (2 * (1 + nu))
    g, measure = _gradients(rest, cells)
    eye = np.eye(dim)
    block = (lam * np.einsum("tai,tbj->tabij", g, g) + mu * np.einsum("taj,tbi->tabij", g, g)
             + mu * np.einsum("tak,tbk,ij->tabij", g, g, eye)) * measure[:, None, None, None, None]
    dofs = (dim * cells[:, :, None] + np.arange(dim)).reshape(len(cells), -1)  # (T, (d+1) d), node-major
    local = block.transpose(0, 1, 3, 2, 4).reshape(len(cells), dofs.shape[1], dofs.shape[1])
    rows = np.repeat(dofs, dofs.shape[1], axis=1).ravel()
    cols = np.tile(dofs, (1, dofs.shape[1])).ravel()
    return sparse.csc_matrix((local.ravel(), (rows, cols)), shape=(dim * n, dim * n))


def held_nodes(rest: np.ndarray, facets: np.ndarray, n_body: int, tolerance: float) -> np.ndarray:
    """(H,) the body nodes (of the first ``n_body`` of ``rest``) within ``tolerance`` of the container's
    facets (scenario node indices; :func:`bsms.physics.penetration.outlines`)."""
    _, containers = outlines(rest, facets, n_body, "graph.elastic")
    if not containers:
        return np.zeros(0, np.int64)
    walls = np.concatenate(containers)
    corners = [rest[walls[:, i]] for i in range(walls.shape[1])]
    body = rest[:n_body]
    distance = np.linalg.norm(closest_on_facets(body, corners) - body, axis=1)
    return np.flatnonzero(distance <= tolerance)


def _contact_multipliers(coupling: np.ndarray, depth: np.ndarray, released: np.ndarray) -> np.ndarray:
    """(m,) the pushes lam >= 0 minimising 1/2 lam S lam - depth . lam for ``coupling`` S (m, m),
    symmetric positive definite: the dual of frictionless contact, whose answer is unique. Every
    node it pushes meets its depth (S lam = depth where lam > 0), every other clears it (S lam >=
    depth). Guessed from ``released`` (m,), the nodes thought clear (a rollout's last frame), and
    corrected a few times by the primal-dual active set rule; if that does not settle it,
    non-negative least squares in S's Cholesky factor."""
    active, scale = ~released, float(np.mean(np.diag(coupling)))
    for _ in range(ACTIVE_SET_TRIES):
        chosen = np.flatnonzero(active)
        multipliers = np.zeros(len(depth))
        if len(chosen):
            multipliers[chosen] = linalg.cho_solve(linalg.cho_factor(coupling[np.ix_(chosen, chosen)], lower=True),
                                                   depth[chosen])
        reach = coupling[:, chosen] @ multipliers[chosen]
        if np.all(multipliers >= 0) and np.all(reach[~active] >= depth[~active] * (1 - 1e-9)):
            return multipliers
        # push where the multiplier stays positive; hold again a released node left inside its push
        guess = multipliers + (depth - reach) / scale > 0
        if np.array_equal(guess, active):
            break
        active = guess
    lower = linalg.cholesky(coupling, lower=True)
    iterations = max(1, round(CONTACT_ITERATIONS * len(depth)))
    try:
        multipliers, _ = nnls(lower.T, linalg.solve_triangular(lower, depth, lower=True), maxiter=iterations)
    except RuntimeError:
        raise RuntimeError(f"graph.elastic: the contact answer did not settle which of {len(depth)} pushed nodes "
                           f"push in {iterations} iterations") from None
    return multipliers


class ElasticResponse:
    """The elastic input of one scenario.

    rest: (N, d) rest positions of all scenario nodes, the first ``n_body`` the body's; facets:
    (F, d) obstacle facets in scenario node indices (the container among them holds the body);
    cells: (T, d+1) the body's simplices; nu: the scene's Poisson ratio (a number; ValueError
    otherwise); edge_length: the body's median rest edge; hold: nodes within this many of it from
    the container are held."""

    def __init__(self, rest: np.ndarray, facets: np.ndarray, n_body: int, cells: np.ndarray, nu, edge_length: float,
                 hold: float = HOLD):
        if not isinstance(nu, (int, float)) or isinstance(nu, bool):
            raise ValueError(f"graph.elastic needs the material's Poisson ratio: the scene has no numeric parameter "
                             f"'nu' (got {nu!r}); give the scene params a 'nu', or set graph.elastic: false")
        rest = np.asarray(rest, np.float64)
        self.n_body, self.dim = int(n_body), rest.shape[1]
        if np.asarray(cells).shape[1] != self.dim + 1:
            raise ValueError(f"graph.elastic needs a simplex body mesh ({self.dim + 1}-node cells in "
                             f"{self.dim}D), got cells of {np.asarray(cells).shape[1]} nodes")
        self.stiffness = stiffness(rest[:n_body], cells, nu)
        self.held = held_nodes(rest, facets, n_body, hold * edge_length)
        keep = np.ones(self.dim * self.n_body, bool)
        keep[(self.dim * self.held[:, None] + np.arange(self.dim)).ravel()] = False
        self.free_dofs = np.flatnonzero(keep)
        self._dofs = -np.ones(self.dim * self.n_body, np.int64)  # each body dof's free index, -1 where held
        self._dofs[self.free_dofs] = np.arange(len(self.free_dofs))
        self._factor = None
        self._solver()  # with the hierarchy, once per mesh: a frame only solves
        self.cache_limit = CACHED_NODES
        self._forget()

    def _forget(self) -> None:
        """Drop the unit responses kept for :meth:`constrained` and its guess of released nodes."""
        self.__dict__.update(self._empty_memory())

    def _empty_memory(self) -> dict:
        return {"_bank": np.zeros((len(self.free_dofs), 0, self.dim)), "_count": 0,
                "_slot": np.full(self.n_body, -1, np.int64),
                "_released": np.zeros(self.n_body, bool)}  # the last answer's released nodes: the next one's guess

    def __getstate__(self):  # a factorisation does not pickle, nor a rollout's memory: each process makes its own
        return {**self.__dict__, "_factor": None, **self._empty_memory()}

    def _unit_bank(self, nodes: np.ndarray, rows: np.ndarray) -> np.ndarray | None:
        """The slots of ``nodes`` in ``self._bank`` (F, slots, d): K^-1 at the free dofs for a unit
        force on a node along each axis, solved for once per node (``rows``: (m, d) the nodes'
        free dofs) -- a rollout's indenter reaches much the same nodes frame after frame. None
        when they would not fit ``cache_limit`` nodes."""
        missing = np.flatnonzero(self._slot[nodes] < 0)
        count = self._count + len(missing)
        if count > self.cache_limit:
            return None
        if count > self._bank.shape[1]:
            grown = np.zeros((len(self.free_dofs), min(max(2 * self._bank.shape[1], count, 64), self.cache_limit),
                              self.dim))
            grown[:, : self._count] = self._bank[:, : self._count]
            self._bank = grown
        if len(missing):
            rhs = np.zeros((len(self.free_dofs), len(missing) * self.dim))
            rhs[rows[missing].ravel(), np.arange(len(missing) * self.dim)] = 1.0
            self._bank[:, self._count:count] = self._solver().solve(rhs).reshape(-1, len(missing), self.dim)
            self._slot[nodes[missing]] = np.arange(self._count, count)
            self._count = count
        return self._slot[nodes]

    def _solver(self):
        if self._factor is None:
            k = self.stiffness[self.free_dofs][:, self.free_dofs]
            shift = REGULARISATION * float(k.diagonal().mean()) if k.shape[0] else 0.0
            # symmetric positive definite: an ordering of K + K^T and no pivoting off the diagonal
            self._factor = splu((k + shift * sparse.identity(k.shape[0], format="csc")).tocsc(),
                                permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        return self._factor

    def __call__(self, penetration: np.ndarray) -> np.ndarray:
        """(N, d) the body's answer to ``penetration`` (N, d) of all scenario nodes (0 outside the
        obstacles): :meth:`constrained`."""
        return self.constrained(penetration)

    def many(self, penetrations: list[np.ndarray]) -> list[np.ndarray]:
        """:meth:`__call__` of each of ``penetrations``: :meth:`constrained_many`."""
        return self.constrained_many(penetrations)

    def constrained_many(self, penetrations: list[np.ndarray]) -> list[np.ndarray]:
        """:meth:`constrained` of each of ``penetrations`` (a rollout's frames), the unit
        responses of every node any of them pushes solved for together first (one solve of many
        right-hand sides), where they fit the cache."""
        pushed = np.zeros(self.n_body, bool)
        for p in penetrations:
            pushed |= np.any(np.asarray(p)[: self.n_body] != 0, axis=1)
        nodes, rows = self._free_nodes(np.flatnonzero(pushed))
        if self.cache_limit and len(nodes):
            self._unit_bank(nodes, rows)
        return [self.constrained(p) for p in penetrations]

    def _free_nodes(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Those of body ``nodes`` that are not held, and (m, d) their free dof indices."""
        rows = self._dofs[self.dim * nodes[:, None] + np.arange(self.dim)]
        free = np.all(rows >= 0, axis=1)
        return nodes[free], rows[free]

    def constrained(self, penetration: np.ndarray) -> np.ndarray:
        """(N, d): the body's answer to ``penetration`` (N, d) as a contact makes it, unscaled: each
        loaded free node is moved along its push by at least the push's length and may slide across
        it, the rest of the body follows elastically; 0 on the other nodes.

        The displacement of least elastic energy with ``n_i . u_i = |p_i|`` on the loaded nodes
        (Lagrange multipliers: ``K u = C^T lam``), where a node the contact would pull (a negative
        multiplier) is released instead: the conditions of frictionless contact with the
        obstacle's surface where the push puts it (every pushed node on it or clear of it, every
        multiplier a push, none where a node is clear), solved exactly as non-negative least
        squares of the multipliers. The answer is not scaled to the pushes -- the loaded nodes meet
        them. Costs d solves per loaded node not seen before (of one
        factorisation, with many right-hand sides) and dense algebra of the loaded nodes' count."""
        out = np.zeros(np.shape(penetration), np.float64)
        push = np.asarray(penetration, np.float64)[: self.n_body]
        depth = np.linalg.norm(push, axis=1)
        loaded, rows = self._free_nodes(np.flatnonzero(depth > 0))
        if not len(loaded):
            return out
        normals = push[loaded] / depth[loaded, None]
        slots = self._unit_bank(loaded, rows) if self.cache_limit else None
        if slots is None:  # K^-1 C^T: what a unit push of each node along its normal does
            rhs = np.zeros((len(self.free_dofs), len(loaded)))
            rhs[rows, np.arange(len(loaded))[:, None]] = normals
            response = self._solver().solve(rhs)
            near = response[rows]  # (m, d, m)
        else:
            near = np.einsum("idjb,jb->idj", self._bank[rows][:, :, slots], normals)
        # S = C K^-1 C^T: how far the push of node j carries node i along node i's own
        coupling = np.einsum("idj,id->ij", near, normals)
        multipliers = _contact_multipliers(0.5 * (coupling + coupling.T), depth[loaded], self._released[loaded])
        self._released[loaded] = multipliers <= 0
        u = np.zeros(self.dim * self.n_body)
        if slots is None:
            u[self.free_dofs] = response @ multipliers
        else:
            weights = np.zeros((self._bank.shape[1], self.dim))
            weights[slots] = multipliers[:, None] * normals
            u[self.free_dofs] = self._bank.reshape(len(self.free_dofs), -1) @ weights.ravel()
        out[: self.n_body] = u.reshape(self.n_body, self.dim)
        return out
