"""UMLS-MPM against the structured quadratic B-spline grid solver (item 6): disks and cantilever.

Small versions of UMLS §3.2-3.3; benchmarks/mpm_verification.py runs the larger ones.
"""

import numpy as np
import pytest

import datagen

pytestmark = pytest.mark.usefixtures("one_thread")


CFL = 0.6  # larger steps than the default 0.3 keep these runs short; both are stable at 0.6


def _disks(solver: dict, params: dict | None = None):
    return datagen.simulate({"scene": "colliding_disks", "params": params or {}, "solver": {**solver, "cfl": CFL},
                             "output": {"frames": 30, "frame_interval": 0.1}})


def test_colliding_disks_keep_momentum_and_recover_energy_like_the_bspline_solver():
    umls = _disks({"kernel": "umls"})
    bspline = _disks({"kernel": "bspline", "grid_spacing": 0.0125}, {"body_size": 0.009})  # 2x finer, 4x particles
    for traj in (umls, bspline):
        scale = float(traj.diagnostics["mass"][0]) * np.linalg.norm(traj.velocities[0], axis=1).max()
        assert np.abs(traj.diagnostics["momentum"]).max() < 1e-10 * scale
    recovered = {name: t.diagnostics["kinetic_energy"][-1] / t.diagnostics["kinetic_energy"][0]
                 for name, t in (("umls", umls), ("bspline", bspline))}
    during = umls.diagnostics["kinetic_energy"] / umls.diagnostics["kinetic_energy"][0]
    assert during.min() < 0.3  # the disks really collided and stopped
    assert recovered["bspline"] > 0.5  # and the B-spline solver bounced back
    assert abs(recovered["umls"] - recovered["bspline"]) < 0.1 * recovered["bspline"]


def _tip_deflection(kernel: str, params: dict, solver: dict | None = None) -> float:
    """Largest downward tip displacement over the first swing (t <= 0.8 s), at the scene's default CFL (0.3)."""
    solver = {"kernel": kernel, **(solver or {})}
    traj = datagen.simulate({"scene": "cantilever", "params": params, "solver": solver,
                             "output": {"frames": 80, "frame_interval": 0.01}})
    tip = int(np.argmin(np.linalg.norm(traj.positions[0] - [10.0, 1.0], axis=1)))
    return float(-(traj.positions[:, tip, 1] - traj.positions[0, tip, 1]).min())


def test_cantilever_matches_the_bspline_solver_at_every_mesh_rotation():
    # The paper's 0.5 m mesh. The sticky wall at x = 0 mirrors its extra-layer nodes (v_ghost = -v at their
    # reflection) and folds their P2G sums back (the beam sees its mirror image), and so does the B-spline solver's
    # grid: upright 1.3875 m against the B-spline solver's 1.394 m (-0.5%; with the grid's clamp nodes held at rest
    # the B-spline solver gave 1.418 m, softer). Measured changes with rotation: 15 deg +4.6%, 30 deg +0.2%, 45 deg -0.1%.
    # At 15 deg the triangulation is irregular next to the wall and the beam turns ~0.009 rad more at the root
    # (a rigid rotation added to the upright profile); it shrinks with dt (+5.6% at CFL 0.6, +4.6% at the
    # default 0.3, +4.0% at 0.15) and is there whatever the wall treatment, so it is not the wall condition.
    bspline = _tip_deflection("bspline", {"particle_spacing": 0.125}, {"grid_spacing": 0.25})
    assert 1.2 < bspline < 1.6  # about twice the static Euler-Bernoulli deflection, 0.74 m
    upright = _tip_deflection("umls", {"mesh_size": 0.5})
    assert abs(upright - bspline) < 0.05 * bspline
    for angle in (15.0, 30.0, 45.0):
        rotated = _tip_deflection("umls", {"mesh_size": 0.5, "rotation": angle})
        assert abs(rotated - upright) < 0.05 * upright
