"""A body's velocity change split into its rigid-motion part and the rest (``model.rigid_part``).

Rigid motion over a step gives a Lagrangian velocity change that is a linear field of position:
with secant velocities (x_{t+1} - x_t) / dt, a body turning by theta about an axis n through p
has Delta v = (R(theta) + R(-theta) - 2 I)(x - p) / dt = 2 (cos theta - 1)(I - n n^T)(x - p) / dt,
plus (R(theta) - I)(x - p) / dt times the change of its turn rate, plus a translation. The
smallest space of fields holding all of these, at any step length:

- 2D: the similarity fields f_s(x) = a + s (x - c) + w J (x - c) (translation, isotropic scale
  rate, turn rate; 4 parameters), I - n n^T being the identity in the plane;
- 3D: the affine fields f_s(x) = a + A (x - c) (12 parameters), the matrices I - n n^T of all
  axes spanning the symmetric ones.

:func:`rigid_part` gives the field of that space closest to a node field (least squares over the
body's free nodes, every node weighted alike; c their centroid); the rest is the deformation. A
stiff body's velocity change is almost all rigid part, and a model that predicts the two with
their own normalisers (:class:`~bsms.models.simulator.LearnedSimulator`) errs on the rest only in
proportion to the deformation, while its rigid part is fitted over all the body's nodes, so
node-by-node errors average out instead of tearing the body apart.

Bodies are the graphs of a batch (one body per scene; where a scene holds several, they share one
field and the rest carries their differences: still exact, with less to gain).
"""

from __future__ import annotations

import torch
from torch import Tensor


def space_dimension(dim: int) -> int:
    """The dimension of the rigid-motion space of :func:`rigid_part`: 4 in 2D (similarity), 12 in 3D (affine)."""
    return 4 if dim == 2 else dim * (dim + 1)


def _sums(values: Tensor, ids: Tensor, n: int) -> Tensor:
    """Sum of ``values`` (N, ...) per id (N,) in [0, n) -> (n, ...)."""
    return values.new_zeros((n, *values.shape[1:])).index_add_(0, ids, values)


def _fit(field: Tensor, pos: Tensor, ids: Tensor, n_bodies: int, mask: Tensor,
         affine: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """The fit of :func:`rigid_part` (``affine``: the best affine field in 2D as well): ((N, d) each
    node's offset from its body's centroid, (B, d) the translation, (B, d, d) the linear map: 2D
    s I + w J, 3D or affine A)."""
    dim = pos.shape[1]
    if dim not in (2, 3):
        raise ValueError(f"rigid parts are built for 2D and 3D positions, got {dim}D")
    weight = mask.to(field.dtype)[:, None]
    count = _sums(weight, ids, n_bodies).clamp(min=1.0)
    p = pos - (_sums(weight * pos, ids, n_bodies) / count).index_select(0, ids)
    mean = _sums(weight * field, ids, n_bodies) / count
    if dim == 3 or affine:  # A = (sum f p^T)(sum p p^T)^+
        moments = _sums(weight[:, :, None] * field[:, :, None] * p[:, None, :], ids, n_bodies)
        spread = _sums(weight[:, :, None] * p[:, :, None] * p[:, None, :], ids, n_bodies)
        return p, mean, moments @ torch.linalg.pinv(spread, hermitian=True)
    # 2D: p and J p are orthogonal at every node and of one length, and both sum to zero
    squares = _sums(weight * p.square().sum(1, keepdim=True), ids, n_bodies)  # (B, 1)
    safe = squares.clamp(min=torch.finfo(field.dtype).tiny)
    turned = torch.stack([-p[:, 1], p[:, 0]], 1)
    scale, turn = (torch.where(squares > 0, _sums(weight * (basis * field).sum(1, keepdim=True), ids, n_bodies) / safe,
                               0.0)[:, 0] for basis in (p, turned))
    linear = torch.stack([torch.stack([scale, -turn], -1), torch.stack([turn, scale], -1)], -2)
    return p, mean, linear


def _apply(linear: Tensor, p: Tensor, ids: Tensor) -> Tensor:
    """Each node's body's (B, d, d) ``linear`` map of its offset ``p`` (N, d)."""
    return (linear.index_select(0, ids) @ p[:, :, None])[:, :, 0]


def rigid_part(field: Tensor, pos: Tensor, ids: Tensor, n_bodies: int, mask: Tensor) -> Tensor:
    """(N, d) the field of the module's space (2D similarity, 3D affine) closest to ``field`` (N, d)
    over the ``mask`` nodes (N,) bool of each body (``ids`` (N,) in [0, ``n_bodies``)), at positions
    ``pos`` (N, d), evaluated at every node (masked or not). A body with no masked node gets zeros;
    one whose masked nodes leave part of the space unresolved (all at one point, in 3D on one
    plane) gets the least-norm fit of the rest of it."""
    p, mean, linear = _fit(field, pos, ids, n_bodies, mask)
    return mean.index_select(0, ids) + _apply(linear, p, ids)


def rigid_step(velocity: Tensor, pos: Tensor, ids: Tensor, n_bodies: int, mask: Tensor, dt: Tensor) -> Tensor:
    """(N, d) ``velocity`` (a step's secant velocity, (x_{t+1} - x_t) / dt) with its affine part (the
    best affine field over each body's ``mask`` nodes, in 2D as in 3D) made a rigid motion: the
    body's map x -> x + dt (a + A (x - c)) replaced by x -> x + dt a + R (x - c), R the rotation
    nearest I + dt A (its polar factor), the rest (the non-affine deformation) kept.
    A stiff body then keeps its size and shape to within the rest however its affine part errs.
    ``dt`` (N,) each node's step (a body's: the mean over its ``mask`` nodes; a body without one
    keeps its velocity)."""
    p, mean, linear = _fit(velocity, pos, ids, n_bodies, mask, affine=True)
    weight = mask.to(velocity.dtype)
    dt = _sums(weight * dt.to(velocity.dtype), ids, n_bodies) / _sums(weight, ids, n_bodies).clamp(min=1.0)
    dt = torch.where(dt > 0, dt, 1.0)  # (B,); a body without masked nodes: linear 0, nothing changes
    eye = torch.eye(pos.shape[1], dtype=velocity.dtype, device=velocity.device)
    u, _, vh = torch.linalg.svd(eye + dt[:, None, None] * linear)
    flip = torch.ones_like(u[:, 0])
    flip[:, -1] = torch.sign(torch.linalg.det(u @ vh))  # a proper rotation
    rotation = (u * flip[:, None, :]) @ vh
    rigid = (rotation - eye) / dt[:, None, None]
    return velocity + _apply(rigid - linear, p, ids)
