"""A learned step that spans k data frames (``train.frame_stride``).

A model trained with stride k learns the step from frame t to frame t + k: its inputs are the
state at frame t with the velocity (x_t - x_{t-k}) / (k dt), its target the velocity change to
(x_{t+k} - x_t) / (k dt). :func:`bsms.augment.strided` makes that data from a stored trajectory (every k-th
frame from an offset; training uses every offset, so no frame is wasted), and a rollout of such
a model (:func:`bsms.rollouts.rollout.rollouts`) runs one model step per k frames and gives
back every data frame: :func:`upsampled` fills the k - 1 frames between two model states with
the cubic Hermite curve through them, its tangents the centred differences of the model's
states (the initial velocity at frame 0, a second-order one-sided difference at the last
state), so that a rollout is compared, drawn and written frame for frame as any other.
"""

from __future__ import annotations

import copy
import dataclasses
import time

import numpy as np

from bsms.data import frame_velocities

__all__ = ["model_steps", "strided_known", "upsampled", "strided_rollouts"]


def model_steps(frames: int, stride: int) -> int:
    """Model steps that cover ``frames`` data frames at ``stride`` frames per step."""
    return -(-int(frames) // int(stride))


def strided_known(known: np.ndarray | None, frames: int, stride: int) -> np.ndarray | None:
    """Known positions (>= frames + 1, N, d) at the model's steps: every ``stride``-th row, the
    last row held past the data's end (a drive known only to frame ``frames`` stays there)."""
    if known is None:
        return None
    rows = np.minimum(np.arange(model_steps(frames, stride) + 1) * stride, len(known) - 1)
    return known[rows]


def upsampled(states: np.ndarray, initial_velocity: np.ndarray, stride: int, frame_dt: float,
              frames: int) -> np.ndarray:
    """(F + 1, N, d) positions at every data frame from the model's states (M + 1, N, d), one
    every ``stride`` frames of ``frame_dt`` (F = min(frames, M stride)): cubic Hermite between
    consecutive states, tangents the centred differences of the states, the initial velocity at
    the first state and a second-order one-sided difference at the last."""
    states = np.asarray(states, dtype=np.float64)
    if stride == 1:
        return states[: frames + 1]
    m = len(states) - 1
    frames = min(int(frames), m * stride)
    if m == 0:
        return states[:1]
    tangents = np.empty_like(states)  # d x / d u, u the step's fraction
    tangents[0] = np.asarray(initial_velocity) * stride * frame_dt
    tangents[1:-1] = 0.5 * (states[2:] - states[:-2])
    tangents[-1] = states[-1] - states[-2] if m == 1 else 0.5 * (3 * states[-1] - 4 * states[-2] + states[-3])
    t = np.arange(frames + 1)
    j = np.minimum(t // stride, m - 1)
    u = ((t - j * stride) / stride)[:, None, None]
    h00, h10 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u
    h01, h11 = -2 * u**3 + 3 * u**2, u**3 - u**2
    out = h00 * states[j] + h10 * tangents[j] + h01 * states[j + 1] + h11 * tangents[j + 1]
    out[::stride] = states[: len(out[::stride])]  # the model's own states exactly
    return out


def _with_frame_dt(scenario, frame_dt: float):
    """A shallow copy of ``scenario`` (a :class:`~bsms.data.Scenario`, or an object standing in for
    one) whose frames are ``frame_dt`` apart; its graphs, hierarchy and caches shared."""
    twin = copy.copy(scenario)
    twin.frame_dt = frame_dt
    return twin


def strided_rollouts(run, model, scenarios, initial_positions, initial_velocities, steps, known_positions,
                     stride: int, **options) -> list:
    """The rollouts ``run`` (:func:`bsms.rollouts.rollout.rollouts`' own loop, with its arguments)
    makes of a model of ``stride`` frames per step, on scenarios of one data frame per row: run
    with the frame time k dt, then given back at every data frame (:func:`upsampled`; kinematic
    nodes exactly where ``known_positions`` puts them); each frame's time the model step's over
    k, the upsampling's included."""
    if options.get("initial_states") is not None:
        raise ValueError(f"a frame stride ({stride}) applies to Lagrangian models; this one learned Eulerian fields")
    for k, n in zip(known_positions, steps, strict=True):
        if k is not None and len(k) < n + 1:
            raise ValueError(f"known_positions has {len(k)} frames; a rollout of {n} steps needs {n + 1}")
    coarse = [_with_frame_dt(s, s.frame_dt * stride) for s in scenarios]
    counts = [model_steps(n, stride) for n in steps]
    known = [strided_known(k, n, stride) for k, n in zip(known_positions, steps, strict=True)]
    results = run(model, coarse, initial_positions, initial_velocities, counts, known, **options)
    out = []
    for result, scenario, v0, n, k in zip(results, scenarios, initial_velocities, steps, known_positions,
                                          strict=True):
        start = time.perf_counter()
        positions = upsampled(result.positions, v0, stride, scenario.frame_dt, n)
        frames = len(positions) - 1
        if k is not None:
            kinematic = scenario.kinematic
            positions[:, kinematic] = k[: frames + 1][:, kinematic]
        velocities = frame_velocities(positions, np.asarray(v0, np.float64), scenario.frame_dt)
        spent = time.perf_counter() - start
        seconds = np.repeat(result.step_seconds / stride, stride)[:frames] + spent / max(frames, 1)
        nodes = np.repeat(result.graph_nodes, stride, axis=0)[:frames]
        out.append(dataclasses.replace(result, positions=positions, velocities=velocities, step_seconds=seconds,
                                       graph_nodes=nodes))
    return out
