"""The frame loop every CSMPM scene runs: steps of the caller's solver up to each frame's time."""

from __future__ import annotations

import time

from ..config import ConfigError
from . import b2b1, euler, gas

__all__ = ["frames", "gas_frames"]


def frames(output: dict, max_substeps: int, step):
    """Advance to each of ``output['frames']`` frames ``output['frame_interval']`` apart by calling
    ``step(t, remaining) -> (dt, cg_iterations)``, which advances the caller's state by dt <=
    remaining from time t; yields (frame, t, steps, the most CG iterations of a step, wall
    seconds) after each frame. ConfigError when a frame would take more than ``max_substeps``."""
    t = 0.0
    for k in range(1, output["frames"] + 1):
        end, start, most, steps = k * output["frame_interval"], time.perf_counter(), 0, 0
        while t < end - 1e-12 * end:
            remaining = end - t
            dt, iterations = step(t, remaining)
            t, steps, most = (end if dt == remaining else t + dt), steps + 1, max(most, iterations)
            if steps > max_substeps:
                raise ConfigError(f"frame {k} took more than solver.max_substeps ({max_substeps:,}) steps; "
                                  "raise it, or coarsen the grid (params.cells)")
        yield k, t, steps, most, time.perf_counter() - start


def gas_frames(scene: str, grid, state, gamma: float, solver: dict, output: dict):
    """A gas scene's run (:mod:`datagen.csmpm.euler`, or :mod:`~datagen.csmpm.b2b1` where
    ``solver['scheme']`` says so, on ``grid`` from ``state``): (states per frame,
    their times, wall seconds per frame, the most CG iterations per frame, total steps); frame 0
    is the start. RuntimeError naming ``scene`` if the gas leaves the physical states."""
    states, times, wall, iterations, substeps = [state], [0.0], [0.0], [0], 0
    run = {"state": state}
    advance_one = b2b1.step if solver["scheme"] == "B2B1" else euler.step

    def advance(t: float, remaining: float):
        dt = min(euler.time_step(run["state"], grid, solver["cfl"], solver["acoustic"], gamma), remaining)
        run["state"], info = advance_one(run["state"], grid, dt, gamma)
        if not gas.physical(run["state"], gamma):
            raise RuntimeError(f"{scene}: the gas state became non-physical (density or pressure <= 0) at "
                               f"t = {t + dt:.6g} s; lower solver.cfl")
        return dt, info.cg_iterations

    for _, t, steps, most, seconds in frames(output, solver["max_substeps"], advance):
        states.append(run["state"])
        times.append(t)
        wall.append(seconds)
        iterations.append(most)
        substeps += steps
    return states, times, wall, iterations, substeps
