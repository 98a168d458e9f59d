"""The `slope` scene (thesis §2.3.4): sensitive clay (Hencky-J2 with softening) failing under gravity.

The default-resolution comparison with the B-spline grid solver (run-out over 4 s, ~10 minutes each) is
too long for the test suite; its numbers are in the module docstring of datagen.scenes.slope.
"""

from __future__ import annotations

import numpy as np
import pytest

import datagen

pytestmark = pytest.mark.usefixtures("one_thread")

COARSE = {"mesh_size": 1.0, "particle_spacing": 0.5}
RHO_G_H = 2150.0 * 9.81 * 7.0


def test_slope_starts_to_fail_and_reports_its_diagnostics():
    traj = datagen.simulate({"scene": "slope", "params": COARSE, "output": {"frames": 5, "frame_interval": 0.1}})
    d = traj.diagnostics
    n = traj.positions.shape[1]
    assert d["runout"].shape == (6,) and d["plastic_strain"].shape == (6, n) and d["mean_stress"].shape == (6, n)
    assert d["runout"][0] == 0.0 and d["plastic_strain_max"][0] == 0.0
    assert np.all(np.diff(d["plastic_strain_max"]) >= 0)  # eps_q^p only grows
    assert d["plastic_strain_max"][-1] > 0.01  # measured 0.020 at 0.5 s
    assert d["runout"][-1] > 0.005  # measured 0.0098 m: the toe has begun to move
    # Mean normal stress: compression at the foot of the back wall, a little over the overburden rho g H there
    # (the face's thrust; measured -1.53 rho g H at 0.1 s after the sudden gravity load, -1.42 at 0.5 s).
    foot = int(np.argmin(np.linalg.norm(traj.positions[0], axis=1)))
    assert -2.0 * RHO_G_H < d["mean_stress"][-1, foot] < -1.0 * RHO_G_H
    assert np.all(d["mean_stress"][0] == 0.0)


def test_slope_in_3d_runs():
    traj = datagen.simulate({"scene": "slope", "params": {**COARSE, "dim": 3, "width": 1.0},
                             "output": {"frames": 1, "frame_interval": 0.01}})
    assert traj.positions.shape[-1] == 3 and np.isfinite(traj.positions).all()
    assert traj.diagnostics["plastic_strain"].shape[1] == traj.positions.shape[1]
