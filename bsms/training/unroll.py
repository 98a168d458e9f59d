"""Multi-step (pushforward) training: each sample is unrolled over K model steps.

A sample is frame t of a trajectory with t + K <= T - 1 (frames t..t+K exist). Step k starts
from a state (x_k, v_k) of every scenario node: step 0 from the data's frame t (with the
training noise, :meth:`~bsms.data.FrameDataset.sample_state`), step k >= 1 from the model's
prediction of step k-1 integrated as a rollout integrates (:func:`bsms.rollouts.rollout.integrate`):
free nodes v' = v + dv, x' = x + dt v'; kinematic nodes (clamped, obstacle) take the data's
state of frame t+k (positions, and the input velocities the data gives them). Each step's
graph is rebuilt from its state by the scenario (contacts and the obstacle nodes in reach
follow the predicted positions), and its target is the velocity change that brings that state
to the data's frame t+k+1: dv = (x_{t+k+1} - x_k) / dt - v_k on free nodes (step 0 keeps the
one-step target with its noise correction, ``noise.gamma`` included).

What is trained (``train.unroll_gradient``):
- ``last`` (pushforward, Brandstetter et al. 2022): steps 0..K-2 run without gradient; the
  loss is the last step's one-step loss.
- ``all``: the mean of every step's loss, each with its gradient; the state passed on is
  detached (truncated: no gradient reaches an earlier step through a later one).
- ``through``: the mean of every step's loss, with gradients flowing through the predicted
  positions and velocities into the later steps' edge and node inputs and their targets
  (step k's loss is then that of the predicted positions of frame t+k+1); the graph's
  connectivity (contacts, obstacle nodes in reach, levels) is rebuilt without gradient.

Normalisers learn from step 0's inputs and targets only (as one-step training does). With
K = 1 the loss is that of :meth:`~bsms.models.simulator.LearnedSimulator.loss`, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Batch

from bsms.config import ConfigError
from bsms.data import FrameDataset, LevelGraph, NumberedSamples
from bsms.level_graph import level_graph
from bsms.rollouts.rollout import integrate

__all__ = ["GRADIENTS", "Start", "UnrollBatch", "UnrollSamples", "collate", "unrolled_loss"]

GRADIENTS = ("last", "all", "through")


@dataclass(frozen=True, eq=False)
class Start:
    """Where a sample's unroll begins: its trajectory, frame t, and step 0's input state (N, d)
    float64 of every scenario node (training noise included)."""

    trajectory: int
    t: int
    pos: np.ndarray
    velocity: np.ndarray


@dataclass
class UnrollBatch:
    """graph: step 0's graphs as one batch (the one-step batch); starts: one :class:`Start` per
    graph, or None (one-step samples only)."""

    graph: LevelGraph
    starts: list[Start] | None = None

    def to(self, device) -> UnrollBatch:
        return UnrollBatch(self.graph.to(device), self.starts)


def collate(items) -> UnrollBatch:
    """The batch of a list of :class:`UnrollSamples` items."""
    graphs, starts = zip(*items, strict=True)
    return UnrollBatch(Batch.from_data_list(list(graphs)), None if starts[0] is None else list(starts))


class UnrollSamples(NumberedSamples):
    """The samples (trajectory, frame t) of ``frames`` with t + ``unroll`` <= T - 1, each item
    (step 0's graph, its :class:`Start`). Keys are those of :class:`~bsms.data.FrameDataset`:
    an index, or ``(index, noise_seed)``. With ``unroll`` 1 the samples, their order and their
    graphs are those of ``frames`` (and the start is None)."""

    def __init__(self, frames: FrameDataset, unroll: int = 1, key: str = "train.unroll"):
        self.frames, self.unroll = frames, int(unroll)
        if self.unroll < 1:
            raise ConfigError(f"config key '{key}' must be >= 1, got {unroll}")
        if self.unroll > 1 and frames.states:
            raise ConfigError(f"config key '{key}' must be 1 for Eulerian data (fields on a fixed mesh, "
                              f"{frames.files[0]}); multi-step training integrates Lagrangian positions")
        lengths = [len(p) for p in (frames.positions or frames.states)]
        counts = [max(0, length - self.unroll) for length in lengths]
        if sum(counts) == 0:
            raise ConfigError(f"config key '{key}' ({self.unroll}) needs trajectories of more than {self.unroll} "
                              f"frames; the longest of the {len(lengths)} training trajectories has {max(lengths)}")
        self._starts = np.concatenate([[0], np.cumsum(counts)])

    def __getitem__(self, key) -> tuple[LevelGraph, Start | None]:
        if self.unroll == 1:
            return self.frames[key], None
        index, noise_seed = key if isinstance(key, tuple) else (key, None)
        k, t = self.locate(int(index))
        pos, velocity, target = self.frames.sample_state(k, t, noise_seed)
        return self.frames.scenarios[k].graph(pos, velocity, target), Start(k, t, pos, velocity)


@dataclass
class _State:
    """One sample's state at a step: the data frame it stands for, and (N, d) float64 tensors
    of every scenario node (names as the graph fields they fill)."""

    trajectory: int
    frame: int
    pos: Tensor
    velocity: Tensor
    target: Tensor | None = None


def _node_counts(graph: LevelGraph) -> list[int]:
    counts = graph["n_nodes_0"]
    return counts.tolist() if torch.is_tensor(counts) else [int(counts)]


def _tensor(array: np.ndarray, device) -> Tensor:
    return torch.from_numpy(np.asarray(array, np.float64)).to(device)


def _advance(model, samples: UnrollSamples, states: list[_State], graph: LevelGraph, prediction: Tensor,
             through: bool) -> list[_State] | None:
    """The states of the next step from the model's ``prediction`` on ``graph`` (None where a
    state went non-finite): free nodes integrated, kinematic nodes the data's next frame."""
    change = model.physical(prediction if through else prediction.detach(), graph)
    counts = _node_counts(graph)
    out = []
    for state, rows, nodes in zip(states, torch.split(change, counts), torch.split(graph.scenario_nodes, counts),
                                  strict=True):
        frames, frame = samples.frames, state.frame + 1
        scenario, device = frames.scenarios[state.trajectory], state.pos.device
        dv = state.pos.new_zeros(state.pos.shape).index_copy(0, nodes, rows.to(state.pos.dtype))
        kinematic = torch.from_numpy(scenario.kinematic).to(device)[:, None]
        pos, velocity = integrate(state.pos, state.velocity, dv, scenario.frame_dt)
        if not bool(torch.isfinite(pos).all() & torch.isfinite(velocity).all()):
            return None
        data_pos, data_velocity, data_target = (_tensor(a, device) for a in frames.sample_state(state.trajectory,
                                                                                                frame))
        if scenario.options.quasi_static:
            velocity = torch.zeros_like(velocity)
        pos, velocity = torch.where(kinematic, data_pos, pos), torch.where(kinematic, data_velocity, velocity)
        truth = _tensor(frames.positions[state.trajectory][frame + 1], device)
        target = torch.where(kinematic, data_target, (truth - pos) / scenario.frame_dt - velocity)
        out.append(_State(state.trajectory, frame, pos, velocity, target))
    return out


def _graph(samples: UnrollSamples, states: list[_State], device, through: bool) -> LevelGraph:
    """The batch of the states' graphs, rebuilt by their scenarios; ``through``: its positions,
    velocities and targets are the states' own tensors (with their gradients)."""
    frames = [samples.frames.scenarios[s.trajectory].frame(*(a.detach().cpu().numpy()
                                                             for a in (s.pos, s.velocity, s.target)))
              for s in states]
    graph = level_graph(frames).to(device)
    if through:
        nodes = [torch.from_numpy(f.nodes["scenario_nodes"]).to(device) for f in frames]
        for name in ("pos", "velocity", "target"):
            graph[name] = torch.cat([getattr(s, name).index_select(0, n) for s, n in zip(states, nodes,
                                                                                         strict=True)]).float()
    return graph


def _non_finite(model) -> Tensor:
    """A NaN loss whose gradient is NaN too (the trainer stops at it as at any non-finite loss)."""
    return next(model.parameters()).sum() * float("nan")


def unrolled_loss(model, batch: UnrollBatch | LevelGraph, samples: UnrollSamples | None, steps: int = 1,
                  gradient: str = "last", accumulate: bool = False, precision: str = "f32",
                  record: list | None = None) -> Tensor:
    """The loss of ``batch`` unrolled over ``steps`` model steps (module docstring): squared
    error on the normalised targets summed over free nodes and dimensions (as
    ``model.loss(..., reduction="sum")``), of the last step (``gradient`` ``last``) or the mean
    over steps (``all``, ``through``). ``accumulate`` feeds the normalisers step 0's inputs and
    targets; ``record``: a list that receives (graph, prediction) of every step."""
    if gradient not in GRADIENTS:
        raise ValueError(f"unknown unroll gradient {gradient!r}; choose one of {', '.join(GRADIENTS)}")
    batch = batch if isinstance(batch, UnrollBatch) else UnrollBatch(batch)
    if steps > 1 and (batch.starts is None or samples is None):
        raise ValueError("an unrolled step needs the samples and their starts (an UnrollBatch of UnrollSamples)")
    graph, states, losses = batch.graph, None, []
    device = graph.pos.device
    for k in range(steps):
        last, through = k + 1 == steps, gradient == "through"
        trained = last or gradient != "last"
        with torch.set_grad_enabled(torch.is_grad_enabled() and trained):
            if accumulate and k == 0:
                model.accumulate_outputs(graph)
            prediction = model(graph, accumulate and k == 0, precision)
            if trained:
                losses.append(model.prediction_loss(prediction, graph, reduction="sum"))
        if record is not None:
            record.append((graph, prediction))
        if last:
            break
        if states is None:
            states = [_State(s.trajectory, s.t, _tensor(s.pos, device), _tensor(s.velocity, device))
                      for s in batch.starts]
        states = _advance(model, samples, states, graph, prediction, through)
        if states is None:
            return _non_finite(model)
        graph = _graph(samples, states, device, through)
    return losses[0] if len(losses) == 1 else torch.stack(losses).mean()
