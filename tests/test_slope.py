"""The `slope` scene (thesis §2.3.4): sensitive clay (Hencky-J2 with softening) failing under gravity.

The comparisons with the B-spline grid solver (run-out over 4 s at the defaults and at the papers'
resolution, 2.5 and ~23 minutes) are too long for the test suite: `benchmarks/umls_cases.py` runs them
and the module docstring of datagen.scenes.slope has their numbers.
"""

from __future__ import annotations

import numpy as np
import pytest

import datagen

pytestmark = pytest.mark.usefixtures("one_thread")

COARSE = {"mesh_size": 1.0, "particle_spacing": 0.5}


def test_slope_starts_to_fail_and_reports_its_diagnostics():
    traj = datagen.simulate({"scene": "slope", "params": COARSE, "output": {"frames": 5, "frame_interval": 0.1}})
    d = traj.diagnostics
    n = traj.positions.shape[1]
    assert d["runout"].shape == (6,) and d["plastic_strain"].shape == (6, n) and d["mean_stress"].shape == (6, n)
    assert d["runout"][0] == 0.0 and d["plastic_strain_max"][0] == 0.0
    assert np.all(np.diff(d["plastic_strain_max"]) >= 0)  # eps_q^p only grows
    assert d["plastic_strain_max"][-1] > 0.01  # measured 0.044 at 0.5 s
    assert d["runout"][-1] > 0.005  # measured 0.020 m: the toe has begun to move
    # Mean normal stress at the foot of the back wall: nearly incompressible clay under gravity is close to
    # isotropic (K0 = nu / (1 - nu) ~ 1), so about the overburden rho g depth there (measured 1.07 of it at
    # 0.1 s after the sudden gravity load, 1.01-1.06 at 0.2-0.5 s; with the floor's ghosts folded 0.97 and
    # 0.84-0.88, and with the earlier F-bar of increments dJ 1.5 and 1.4).
    foot = int(np.argmin(np.linalg.norm(traj.positions[0], axis=1)))
    overburden = 2150.0 * 9.81 * (7.0 - traj.positions[0, foot, 1])
    assert -1.15 * overburden < d["mean_stress"][-1, foot] < -0.95 * overburden
    assert np.all(d["mean_stress"][0] == 0.0)


def test_slope_in_3d_runs():
    traj = datagen.simulate({"scene": "slope", "params": {**COARSE, "dim": 3, "width": 1.0},
                             "output": {"frames": 1, "frame_interval": 0.01}})
    assert traj.positions.shape[-1] == 3 and np.isfinite(traj.positions).all()
    assert traj.diagnostics["plastic_strain"].shape[1] == traj.positions.shape[1]
