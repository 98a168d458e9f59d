"""bsms.rollouts.motion: the best rigid fit per frame, the rigid/deformation split of motion and error, vs_rest."""

import math

import numpy as np
import pytest

from bsms.rollouts.motion import error_parts, motion_parts, rigid_fit, skill


def rotation_2d(angle: float) -> np.ndarray:
    return np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])


def rotation_3d(axis, angle: float) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


@pytest.mark.parametrize("dim", [2, 3])
def test_rigid_fit_recovers_a_rigid_motion_to_round_off(dim):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(40, dim))
    rotations = [rotation_2d(a) if dim == 2 else rotation_3d(rng.normal(size=3), a) for a in (0.0, 0.3, 2.9, -3.1)]
    shifts = rng.normal(size=(4, dim))
    frames = np.stack([points @ r.T + c for r, c in zip(rotations, shifts, strict=True)])
    np.testing.assert_allclose(rigid_fit(points, frames), frames, rtol=0, atol=1e-13)


def test_rigid_fit_never_reflects_and_uses_only_the_mask():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(30, 2))
    mirrored = points * np.array([-1.0, 1.0])  # a reflection is no rigid motion
    fit = rigid_fit(points, mirrored[None])[0]
    centred = fit - fit.mean(0)
    rotation = np.linalg.lstsq(points - points.mean(0), centred, rcond=None)[0]
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    target = points + np.array([0.5, -0.2])
    target[:5] += 10.0  # outliers outside the mask do not pull the fit
    mask = np.arange(30) >= 5
    np.testing.assert_allclose(rigid_fit(points, target[None], mask)[0], points + np.array([0.5, -0.2]),
                               rtol=0, atol=1e-13)


def test_motion_of_a_body_that_only_turns_and_slides_is_all_rigid():
    rng = np.random.default_rng(2)
    rest = rng.uniform(size=(50, 2))
    frames = np.stack([rest @ rotation_2d(0.05 * t).T + [0.01 * t, 0.0] for t in range(6)])
    parts = motion_parts(frames, np.ones(50, bool), 2.0)
    assert parts["rest_deform_rel_all"] < 1e-14
    assert parts["rest_rigid_rel_all"] == pytest.approx(parts["rest_rel_all"], rel=1e-12)
    displacement = frames[1:] - rest
    expected = math.sqrt(np.mean(np.sum(displacement**2, -1))) / 2.0
    assert parts["rest_rel_all"] == pytest.approx(expected, rel=1e-13)


def test_a_stretch_about_the_centroid_is_all_deformation():
    """Stretching a symmetric body along x about its centre neither moves nor turns its best fit."""
    x, y = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-0.5, 0.5, 3))
    rest = np.stack([x.ravel(), y.ravel()], 1)
    frames = np.stack([rest * [1 + 0.01 * t, 1.0] for t in range(4)])
    parts = motion_parts(frames, np.ones(len(rest), bool), 1.0)
    assert parts["rest_rigid_rel_all"] < 1e-15
    assert parts["rest_deform_rel_all"] == pytest.approx(parts["rest_rel_all"], rel=1e-13)


def test_error_parts_and_vs_rest():
    rng = np.random.default_rng(3)
    rest = rng.uniform(size=(30, 2))
    truth = np.stack([rest + [0.0, -0.002 * t] for t in range(5)])  # sinking by 2 mm per frame
    turned = np.stack([(f - f.mean(0)) @ rotation_2d(0.01).T + f.mean(0) for f in truth])  # a rigid error only
    mask = np.ones(30, bool)
    parts = error_parts(turned, truth, mask, 1.0)
    rel_all = math.sqrt(np.mean(np.sum((turned - truth)[1:] ** 2, -1)))
    assert parts["deform_rel_all"] < 1e-14 and parts["rigid_rel_all"] == pytest.approx(rel_all, rel=1e-12)
    result = skill(turned, truth, mask, 1.0, rel_all)
    rest_error = math.sqrt(np.mean([(0.002 * t) ** 2 for t in range(1, 5)]))
    assert result["rest_rel_all"] == pytest.approx(rest_error, rel=1e-12)
    assert result["vs_rest"] == pytest.approx(rel_all / rest_error, rel=1e-12)
    assert skill(truth[:1].repeat(5, 0), truth, mask, 1.0, rest_error)["vs_rest"] == pytest.approx(1.0, rel=1e-12)


def test_a_rollout_that_stopped_or_went_non_finite_has_infinite_parts():
    truth = np.stack([np.eye(3)[:, :2] * (1 + 0.01 * t) for t in range(4)])
    bad = truth.copy()
    bad[2, 0] = np.nan
    for predicted in (bad, truth[:2]):
        parts = error_parts(predicted, truth, np.ones(3, bool), 1.0)
        assert parts == {"rigid_rel_all": math.inf, "deform_rel_all": math.inf}
    assert skill(truth, np.repeat(truth[:1], 4, 0), np.ones(3, bool), 1.0, 0.1)["vs_rest"] == math.inf


def test_the_surrogate_benchmark_last_line_carries_the_at_rest_ratio():
    """benchmarks/surrogate_vs_solver.py ends with the line the issue fixes, vs_rest included."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from surrogate_vs_solver import verdict

    from bsms.rollouts.learned_rollouts import PHYSICS_LABEL

    rows = [{"label": "model", "kind": "learned", "speedup": 31.23, "speedup_throughput": 51.23, "rel_all": 0.00412,
             "vs_rest": 0.2871, "unstable": 0, "trajectories": 8, "dominated_by": []},
            {"label": PHYSICS_LABEL, "kind": "physics", "dominated_by": []},
            {"label": "solver, time step 2x larger", "kind": "solver", "setting": "large_step", "dominated_by": []},
            {"label": "solver, largest stable time step (3.95x-4x)", "kind": "solver", "setting": "stability_limit",
             "dominated_by": []},
            {"label": "solver, mass scaling x10000", "kind": "solver", "setting": "mass_scaling_10000",
             "dominated_by": []}]
    assert verdict(rows) == ("surrogate: speedup 31.2 x end to end (51.2 x throughput), rel RMSE all 0.00412, "
                             "vs at rest 0.287, unstable 0 of 8, dominated by none")
    rows[0]["dominated_by"] = [r["label"] for r in rows[1:]]
    assert verdict(rows).endswith("dominated by elastic_answer, large_step, stability_limit, mass_scaling_10000")
