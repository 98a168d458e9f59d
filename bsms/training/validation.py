"""What training validates on: the one-step RMSE of sampled frames, or whole rollouts of the
validation trajectories with their skill against predicting no motion (``train.validation``)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch_geometric.data import Batch

from bsms.rollouts.learned_rollouts import learned_rollouts

__all__ = ["one_step_rmse", "rollout_scores"]


@torch.no_grad()
def one_step_rmse(model, valid_set, samples: int, batch_size: int, device, precision: str) -> float:
    """RMSE over ``samples`` frames of ``valid_set`` (evenly spread) of the free nodes' next
    position (m; Lagrangian data) or of the first output field (the data's units; Eulerian data)."""
    n = len(valid_set)
    picks = np.unique(np.linspace(0, n - 1, min(n, samples)).round().astype(int))
    squared, count = 0.0, 0
    spec = model.spec
    for start in range(0, len(picks), batch_size):
        batch = Batch.from_data_list([valid_set[int(i)] for i in picks[start:start + batch_size]]).to(device)
        change = model.physical(model(batch, precision=precision), batch)
        error = change - batch.target
        if spec.is_lagrangian:
            error = error * batch.frame_dt[:, None]
        else:
            error = error[:, spec.output_columns(spec.outputs[0].name)]
        squared += float(error[batch.loss_mask].square().sum())
        count += int(batch.loss_mask.sum())
    return math.sqrt(squared / max(count, 1))


@torch.no_grad()
def rollout_scores(model, graph, trajectories, cache_dir, device, scenarios=None) -> tuple[float, float]:
    """(RMSE (m) over every step of every trajectory, each rolled out from frame 0 as one batch;
    the mean over trajectories of ``vs_rest``, that RMSE over the one of predicting no motion,
    :mod:`bsms.rollouts.motion`). Both are inf when a rollout goes non-finite."""
    frames = [len(t.times) - 1 for t in trajectories]
    scored = learned_rollouts(model, graph, trajectories, cache_dir, frames, device=device, scenarios=scenarios)
    squares = [metrics["rmse_all"] ** 2 for metrics, _ in scored]
    if not np.isfinite(squares).all():
        return math.inf, math.inf
    return float(math.sqrt(np.mean(squares))), float(np.mean([metrics["vs_rest"] for metrics, _ in scored]))
