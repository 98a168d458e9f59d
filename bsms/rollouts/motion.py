"""What moves, and what a prediction gets wrong: rigid-body and deformation parts.

An error relative to the body size can look small where little moves, and a body that slides
and tips shows mostly rigid motion, which tests friction more than elasticity. Every frame is
therefore split by its best rigid fit (Kabsch: the rotation and translation that minimise the
summed squared distance over the nodes that count):

* the **true motion** (frame t against frame 0) into the rigid motion of frame 0's best fit onto
  frame t and the deformation left over;
* a **prediction's error** (prediction against truth at frame t) into the rigid motion of the
  truth's best fit onto the prediction and the deformation error left over.

Both parts are RMS over every step and node that counts, relative to the body size, like
``rel_all`` (:func:`bsms.rollouts.rollout.rollout_metrics`). ``vs_rest`` is a model's RMSE over all
steps divided by that of predicting no motion at all (``rest_rel_all``): above 1 the model has
learned nothing.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SKILL_KEYS", "rigid_fit", "motion_parts", "error_parts", "skill"]

# the per-rollout measures of :func:`skill` (each averaged over trajectories in summaries)
SKILL_KEYS = ("rest_rel_all", "vs_rest", "rigid_rel_all", "deform_rel_all", "rest_rigid_rel_all",
              "rest_deform_rel_all")


def rigid_fit(source: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(T, N, d) ``source`` moved rigidly, frame by frame, onto ``target`` (both (T, N, d); a
    (N, d) source stands for every frame): per frame the proper rotation R and translation c
    minimising sum |R s_i + c - t_i|^2 over the nodes of ``mask`` (default all), applied to every
    node. Frames with a non-finite target are non-finite."""
    target = np.asarray(target, float)
    source = np.broadcast_to(np.asarray(source, float), target.shape)
    mask = np.ones(target.shape[1], bool) if mask is None else np.asarray(mask, bool)
    out = np.full(target.shape, np.nan)
    finite = np.isfinite(target[:, mask]).all(axis=(1, 2)) & np.isfinite(source[:, mask]).all(axis=(1, 2))
    if not mask.any() or not finite.any():
        return out
    s, t = source[finite], target[finite]
    s_mean, t_mean = s[:, mask].mean(axis=1, keepdims=True), t[:, mask].mean(axis=1, keepdims=True)
    cross = np.einsum("fni,fnj->fij", s[:, mask] - s_mean, t[:, mask] - t_mean)  # (F, d, d)
    u, _, vt = np.linalg.svd(cross)
    flip = np.sign(np.linalg.det(np.einsum("fij,fjk->fik", u, vt)))
    u[:, :, -1] *= np.where(flip == 0, 1.0, flip)[:, None]  # a proper rotation (no reflection)
    rotation = np.einsum("fij,fjk->fki", u, vt)  # R = V U^T
    out[finite] = np.einsum("fij,fnj->fni", rotation, s - s_mean) + t_mean
    return out


def _rel(difference: np.ndarray, mask: np.ndarray, size: float) -> float:
    """RMS over steps 1.. and the nodes of ``mask`` of (T, N, d) ``difference``, over ``size``
    (inf when a step is not finite)."""
    with np.errstate(invalid="ignore", over="ignore"):
        per_step = np.mean(np.sum(difference[1:, mask] ** 2, axis=-1), axis=-1)
    if not len(per_step):
        return float("nan")
    if not np.isfinite(per_step).all():
        return float("inf")
    return float(np.sqrt(np.mean(per_step))) / size


def motion_parts(truth: np.ndarray, mask: np.ndarray, size: float) -> dict:
    """The true motion from frame 0, relative to ``size``, over all steps: ``rest_rel_all`` (all
    of it: the error of predicting no motion), ``rest_rigid_rel_all`` (frame 0's best rigid fit
    onto each frame) and ``rest_deform_rel_all`` (what the fit leaves: the deformation)."""
    truth = np.asarray(truth, float)
    fitted = rigid_fit(truth[0], truth, mask)
    return {"rest_rel_all": _rel(truth - truth[:1], mask, size),
            "rest_rigid_rel_all": _rel(fitted - truth[:1], mask, size),
            "rest_deform_rel_all": _rel(truth - fitted, mask, size)}


def error_parts(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray, size: float) -> dict:
    """A rollout's error split per frame by the truth's best rigid fit onto the prediction:
    ``rigid_rel_all`` (the fit's motion of the truth) and ``deform_rel_all`` (the prediction's
    distance from the fit), each RMS over all steps relative to ``size``. predicted may be shorter
    than truth (a rollout that stopped): the missing steps count as infinite."""
    truth = np.asarray(truth, float)
    reached = np.full(truth.shape, np.nan)
    n = min(len(predicted), len(truth))
    reached[:n] = predicted[:n]
    fitted = rigid_fit(truth, reached, mask)
    return {"rigid_rel_all": _rel(fitted - truth, mask, size), "deform_rel_all": _rel(reached - fitted, mask, size)}


def skill(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray, size: float, rel_all: float) -> dict:
    """Everything above for one rollout whose RMSE over all steps relative to ``size`` is
    ``rel_all``: :func:`motion_parts`, :func:`error_parts` and ``vs_rest`` = rel_all /
    rest_rel_all (inf where nothing moves)."""
    out = {**motion_parts(truth, mask, size), **error_parts(predicted, truth, mask, size)}
    rest = out["rest_rel_all"]
    out["vs_rest"] = rel_all / rest if rest > 0 else float("inf")
    return out
