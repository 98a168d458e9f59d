"""The honest chart's pieces on hand-made data: dominance and the Pareto front (bsms.evaluate.pareto), the
solver settings' config changes, the bounded search for the largest stable time step on a fake
solver, the report's 'dominated by' column and the chart's step line."""

import copy
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bsms.evaluate import pareto, report
from bsms.rollouts import solver_runs, viz
from bsms.rollouts.solver_runs import SOLVER_SETTINGS, STABILITY_FACTORS, setting_config, setting_label
from datagen.config import ConfigError
from datagen.mpm import SimulationError

INF = math.inf


# ----------------------------------------------------------------------------- dominance
def test_dominance_with_ties_and_infinities():
    assert pareto.dominates((1, 1), (2, 2)) and pareto.dominates((1, 2), (2, 2)) and pareto.dominates((2, 1), (2, 2))
    assert not pareto.dominates((2, 2), (2, 2)), "an equal point is not strictly better"
    assert not pareto.dominates((1, 3), (2, 2)) and not pareto.dominates((3, 1), (2, 2)), "a trade-off"
    assert pareto.dominates((5, 1), (1, INF)) is False, "slower dominates nothing"
    assert pareto.dominates((1, 1), (1, INF)) and pareto.dominates((0.5, 9), (1, INF))
    assert not pareto.dominates((0.5, INF), (1, INF)), "an infinitely inaccurate point dominates nothing"
    assert not pareto.dominates((0.5, INF), (1, 1))
    assert pareto.dominates((1, 1), (None, 1)) and pareto.dominates((1, 1), (float("nan"), 1)), "no time: infinitely slow"
    assert pareto.dominates((INF, 0.5), (INF, 1)), "equally (infinitely) slow, more accurate"


def test_dominated_by_and_front_closed_answers():
    points = [
        (1.0, 0.5),   # 0: fastest, least accurate of the front
        (2.0, 0.1),   # 1: front
        (2.0, 0.1),   # 2: exact tie with 1: both on the front, neither dominates the other
        (3.0, 0.1),   # 3: as accurate as 1, 2 but slower: dominated by both
        (4.0, 0.0),   # 4: the ground truth (error 0): front
        (0.5, INF),   # 5: fastest but unstable: dominated by nothing faster, on no front
        (1.0, INF),   # 6: unstable: dominated by 0 (as fast, finite); not by 5 (infinite error dominates nothing)
        (5.0, 0.2),   # 7: dominated by 1, 2, 3, 4
        (None, 0.05),  # 8: no time: dominated by 4 only
    ]
    assert pareto.dominated_by(points) == [[], [], [], [1, 2], [], [], [0], [1, 2, 3, 4], [4]]
    assert pareto.pareto_front(points) == [0, 1, 2, 4]
    assert pareto.pareto_front([(1, INF), (2, INF)]) == []
    assert pareto.pareto_front([]) == [] and pareto.dominated_by([]) == []


def rows_example():
    truth = SOLVER_SETTINGS["ground_truth"]
    return truth, [
        {"label": "model", "kind": "learned", "seconds_per_sim_second": 0.1, "rel_all": 0.02, "unstable": 0},
        {"label": "shaky", "kind": "learned", "seconds_per_sim_second": 0.05, "rel_all": 0.01, "unstable": 1},
        {"label": truth, "kind": "solver", "seconds_per_sim_second": 1.0, "rel_all": 1e-17, "unstable": 0},
        {"label": "coarse", "kind": "solver", "seconds_per_sim_second": 0.08, "rel_all": 0.01, "unstable": 0},
        {"label": "big step", "kind": "solver", "seconds_per_sim_second": 0.01, "rel_all": INF, "unstable": 1,
         "failed": "stopped"},
        {"label": "slow model", "kind": "learned", "seconds_per_sim_second": 2.0, "rel_all": 0.001, "unstable": 0},
    ]


def test_rows_are_marked_honestly():
    truth, rows = rows_example()
    assert pareto.row_point(rows[2], truth) == (1.0, 0.0), "the ground truth has zero error by definition"
    assert pareto.row_point(rows[1], truth) == (0.05, INF), "an unstable rollout counts as infinitely inaccurate"
    assert pareto.row_point(rows[4], truth) == (0.01, INF)
    front = pareto.mark_rows(rows, reference=truth)
    assert front == [3, 2]
    assert [r["dominated_by"] for r in rows] == [["coarse"], [], [], [], [], [truth]], "nothing finite is faster than shaky"
    assert [r["pareto_front"] for r in rows] == [False, False, True, True, False, False]
    lines = pareto.front_lines(rows, truth)
    assert lines[0].startswith(f"Pareto front (the step line; hollow points are dominated), fastest first: coarse; {truth}.")
    assert lines[1:] == ["", "- model: dominated by the solver (coarse).",
                         "- shaky: unstable on 1 rollout(s), so counted as infinitely inaccurate.",
                         f"- slow model: dominated by the solver ({truth})."]
    rows[3]["seconds_per_sim_second"] = 0.2  # the coarse solver is now slower than the model
    pareto.mark_rows(rows, reference=truth)
    assert rows[0]["dominated_by"] == [] and rows[0]["pareto_front"]
    assert pareto.front_lines(rows, truth)[2] == (
        "- model: no solver setting is both at least as fast and at least as accurate.")
    learned = [row for row in rows if row["kind"] == "learned"]
    pareto.mark_rows(learned)
    assert len(pareto.front_lines(learned)) == 2, "no solver ran: no claim about the solver"


def test_report_column_dominated_by():
    _, rows = rows_example()
    pareto.mark_rows(rows, reference=rows[2]["label"])
    table = report.table(rows, [("label", "method"), ("dominated_by", "dominated by")]).splitlines()
    assert table[0] == "| method | dominated by |"
    assert table[2:] == ["| model | coarse |", "| shaky | none |", f"| {rows[2]['label']} | none |",
                         "| coarse | none |", "| big step | none |", f"| slow model | {rows[2]['label']} |"]
    assert report.fmt(["a, b", "c"]) == "a, b; c", "labels hold commas: they are joined with '; '"
    assert ("dominated_by", "dominated by") in report.COLUMNS


# ----------------------------------------------------------------------------- settings
BASE = {"scene": "glyphs", "params": {"mesh_size": 0.1, "body_size": 0.05, "E": 1e4},
        "solver": {"reference": "eulerian", "cfl": 0.3, "dt": None, "threads": 1},
        "output": {"frames": 100, "frame_interval": 0.01, "step_diagnostics": True}, "seed": 3}


def changed(**sections) -> dict:
    """BASE over 6 frames without step diagnostics, with ``sections`` merged in."""
    out = copy.deepcopy(BASE)
    out["output"].update(frames=6, step_diagnostics=False)
    for name, values in sections.items():
        out[name].update(values)
    return out


def test_setting_config_changes_exactly_one_knob():
    before = copy.deepcopy(BASE)
    expected = {
        "ground_truth": changed(),
        "adaptive": changed(solver={"reference": "adaptive"}),
        "coarse_mesh_1.5": changed(params={"mesh_size": 1.5 * 0.1}),
        "coarse_mesh": changed(params={"mesh_size": 0.2}),
        "adaptive_coarse_mesh": changed(params={"mesh_size": 0.2}, solver={"reference": "adaptive"}),
        "fewer_particles": changed(params={"body_size": 1.5 * 0.05}),
        "large_step": changed(solver={"cfl": 0.6}),
        "total": changed(solver={"reference": "total"}),
    }
    scaled = {s for s in SOLVER_SETTINGS if s.startswith("mass_scaling_")}
    assert set(expected) | {"stability_limit"} | scaled == set(SOLVER_SETTINGS)
    assert all(setting_config(BASE, s, 6) is None for s in scaled), "glyphs fall freely: no quasi-static drive"
    for setting, config in expected.items():
        assert setting_config(BASE, setting, 6) == config, setting
    assert setting_config(BASE, "stability_limit", 6, dt=0.004) == changed(solver={"dt": 0.004})
    with pytest.raises(ValueError, match="needs the time step"):
        setting_config(BASE, "stability_limit", 6)
    with pytest.raises(ValueError, match="unknown solver setting 'coarse'"):
        setting_config(BASE, "coarse", 6)
    fixed_step = copy.deepcopy(BASE)
    fixed_step["solver"]["dt"] = 0.001
    assert setting_config(fixed_step, "large_step", 6)["solver"] == {**fixed_step["solver"], "dt": 0.002}
    floor = copy.deepcopy(BASE)
    floor["params"]["min_nodes"] = 1000
    assert setting_config(floor, "fewer_particles", 6)["params"] == {**floor["params"], "body_size": 1.5 * 0.05,
                                                                      "min_nodes": 444}
    assert BASE == before, "the base config is not touched"


def test_settings_without_their_knob_are_skipped():
    adaptive = copy.deepcopy(BASE)
    adaptive["solver"]["reference"] = "adaptive"
    assert setting_config(adaptive, "adaptive", 6) is None and setting_config(adaptive, "adaptive_coarse_mesh", 6) is None
    assert setting_config(adaptive, "total", 6)["solver"]["reference"] == "total"
    total = copy.deepcopy(BASE)
    total["solver"]["reference"] = "total"
    assert setting_config(total, "total", 6) is None and setting_config(total, "adaptive", 6) is not None
    assert solver_runs.run_solver(SimpleNamespace(config=total), "total", 6, 0.5) == {
        "skipped": "the data already used the total reference configuration", "setting": "total"}
    no_mesh = copy.deepcopy(BASE)
    del no_mesh["params"]["mesh_size"]
    for setting in ("coarse_mesh", "coarse_mesh_1.5", "adaptive_coarse_mesh"):
        assert setting_config(no_mesh, setting, 6) is None, setting
    trajectory = SimpleNamespace(config=adaptive)
    assert solver_runs.run_solver(trajectory, "adaptive", 6, 0.5) == {
        "skipped": "the data already used the adaptive reference configuration", "setting": "adaptive"}
    assert solver_runs.run_solver(SimpleNamespace(config=no_mesh), "coarse_mesh", 6, 0.5) == {
        "skipped": "the scene has no knob for coarse_mesh", "setting": "coarse_mesh"}


def test_setting_labels():
    assert setting_label("coarse_mesh", [{"dt_factor": 2.0}]) == "solver, background mesh 2x coarser"
    base = SOLVER_SETTINGS["stability_limit"]
    assert setting_label("stability_limit", [{"dt_factor": 4.0}, {"dt_factor": 4.0}]) == f"{base} (4x)"
    assert setting_label("stability_limit", [{"dt_factor": 8.0}, {"dt_factor": 2.0}]) == f"{base} (2x-8x)"
    assert setting_label("stability_limit", [{"skipped": "why"}]) == base


# ----------------------------------------------------------------------------- stability limit
class FakeSolver:
    """simulate() of a 2-node trajectory: error 1e-3 x factor, failing (SimulationError) above
    ``fails_above`` x the data's time step and unstable (error 1 m) above ``unstable_above``."""

    def __init__(self, fails_above=INF, unstable_above=INF):
        self.fails_above, self.unstable_above, self.calls = fails_above, unstable_above, []
        self.truth = np.zeros((7, 2, 2))
        self.truth[:, 1, 0] = 1.0  # body size 1 m
        self.truth[:, :, 1] = np.linspace(0, -0.1, 7)[:, None]
        self.trajectory = SimpleNamespace(
            config=copy.deepcopy(BASE), positions=self.truth, times=np.arange(7) * 0.05, dt=0.05 / 16, substeps=16,
            mesh=SimpleNamespace(nodes=self.truth[0]), node_type=None, body_id=None)

    def __call__(self, config):
        dt = config["solver"]["dt"]
        self.calls.append((dt, config["solver"]["threads"]))
        dt = dt or self.trajectory.dt  # null: the data's own step
        factor = dt / self.trajectory.dt
        if factor > self.fails_above:
            raise SimulationError(f"the state became non-finite at dt = {dt}\nmore")
        substeps = math.ceil(0.05 / dt - 1e-9)
        error = 1.0 if factor > self.unstable_above else 1e-3 * factor
        return SimpleNamespace(positions=self.truth + error, wall_time=0.6 / factor, dt=0.05 / substeps,
                               substeps=substeps, body_id=None, mesh=SimpleNamespace(nodes=self.truth[0]),
                               setup_time=0.0, preroll_time=0.0)


def search(monkeypatch, fake: FakeSolver, done=None) -> dict:
    monkeypatch.setattr(solver_runs, "simulate", fake)
    return solver_runs.run_solver(fake.trajectory, "stability_limit", 6, 0.5, threads=3, done=done)


def test_search_stops_at_the_first_failure(monkeypatch):
    fake = FakeSolver(fails_above=4)
    result = search(monkeypatch, fake)
    assert result["dt_factor"] == 4.0 and result["setting"] == "stability_limit" and result["substeps"] == 4
    assert result["rel_all"] == pytest.approx(4e-3 * math.sqrt(2) / 1.0, rel=1e-12) and result["unstable_step"] is None
    assert result["seconds_per_sim_second"] == pytest.approx(0.15 / 0.3, rel=1e-12), "the stable run IS the point"
    assert [(t["factor"], t["stable"]) for t in result["search"]] == [(2.0, True), (4.0, True), (8.0, False)]
    assert result["search"][-1]["failed"] == f"the state became non-finite at dt = {8 * (0.05 / 16)}"
    assert fake.calls == [(f * (0.05 / 16), 3) for f in (2, 4, 8)], "one run per try, on the evaluation's threads"


def test_search_counts_the_bound_and_keeps_to_its_budget(monkeypatch):
    fake = FakeSolver(unstable_above=2)  # error beyond 0.5 x body size from x4 on
    result = search(monkeypatch, fake)
    assert result["dt_factor"] == 2.0 and [t["stable"] for t in result["search"]] == [True, False]
    assert result["search"][1]["unstable_step"] == 1 and "failed" not in result["search"][1]
    fake = FakeSolver()  # never fails: the budget stops it (x16 still takes 4 steps a frame)
    fake.trajectory.substeps, fake.trajectory.dt = 64, 0.05 / 64
    result = search(monkeypatch, fake)
    assert len(fake.calls) == len(STABILITY_FACTORS) == 4 and result["dt_factor"] == 16.0 and result["substeps"] == 4
    fake.trajectory.substeps, fake.trajectory.dt = 4, 0.05 / 4  # x4 reaches one step per frame: stop there
    fake.calls.clear()
    result = search(monkeypatch, fake)
    assert len(fake.calls) == 2 and result["dt_factor"] == 4.0 and result["substeps"] == 1


def test_search_reuses_runs_already_made(monkeypatch):
    fake = FakeSolver(fails_above=1)  # not even x2: the data's own step is the limit
    truth_run = {"rel_all": 0.0, "unstable_step": None, "dt_factor": 1.0, "substeps": 16,
                 "max_difference_from_stored": 0.0, "setting": "ground_truth"}
    result = search(monkeypatch, fake, done={"ground_truth": truth_run})
    assert len(fake.calls) == 1 and result["dt_factor"] == 1.0 and result["rel_all"] == 0.0
    assert "max_difference_from_stored" not in result and result["setting"] == "stability_limit"
    assert truth_run["setting"] == "ground_truth", "the reused run is not changed"
    fake = FakeSolver(fails_above=1)
    result = search(monkeypatch, fake)  # no ground truth run to reuse: made here at the data's settings
    assert result["dt_factor"] == 1.0 and len(fake.calls) == 2 and fake.calls[1] == (None, 3)
    doubled = {"rel_all": 1e-3, "unstable_step": None, "dt_factor": 2.0, "substeps": 8, "setting": "large_step"}
    fake = FakeSolver(fails_above=4)
    result = search(monkeypatch, fake, done={"large_step": doubled})
    assert [t["factor"] for t in result["search"]] == [2.0, 4.0, 8.0] and len(fake.calls) == 2, "x2 is large_step"


def test_invalid_setting_configs_are_skipped(monkeypatch):
    def refuse(config):
        raise ConfigError("config key 'solver.cfl' must be in (0, 1], got 1.2\ndetails")

    monkeypatch.setattr(solver_runs, "simulate", refuse)
    result = solver_runs.run_solver(FakeSolver().trajectory, "large_step", 6, 0.5)
    assert result == {"skipped": "config key 'solver.cfl' must be in (0, 1], got 1.2", "setting": "large_step"}


# ----------------------------------------------------------------------------- chart
def test_chart_draws_the_front_as_a_step_line(monkeypatch, tmp_path):
    figures = []
    save = viz._save
    monkeypatch.setattr(viz, "_save", lambda fig, path: (figures.append(fig), save(fig, path))[1])
    points = [
        {"label": "truth", "kind": "ground_truth", "seconds_per_sim_second": 1.0, "error": 0.0, "unstable": 0,
         "front": True, "dominated": False},
        {"label": "model", "kind": "learned", "seconds_per_sim_second": 0.1, "error": 0.02, "unstable": 0,
         "front": True, "dominated": False},
        {"label": "coarse", "kind": "solver", "seconds_per_sim_second": 0.2, "error": 0.05, "unstable": 0,
         "front": False, "dominated": True},
        {"label": "fast", "kind": "solver", "seconds_per_sim_second": 0.3, "error": 0.001, "unstable": 0,
         "front": True, "dominated": False},
        {"label": "boom", "kind": "solver", "seconds_per_sim_second": 0.05, "error": INF, "unstable": 1,
         "front": False, "dominated": False},
    ]
    path = viz.speed_accuracy_chart(points, tmp_path / "chart.png", ylabel="rollout RMSE / body size")
    assert path.read_bytes().startswith(b"\x89PNG")
    (ax,) = figures[0].axes
    (line,) = [line for line in ax.get_lines() if line.get_label() == "Pareto front"]
    floor = 0.001 / 3
    np.testing.assert_allclose(line.get_xdata(), [0.1, 0.3, 1.0, 3.0])  # to the right edge (3 x slowest)
    np.testing.assert_allclose(line.get_ydata(), [0.02, 0.001, floor, floor])
    assert line.get_drawstyle() == "steps-post"
    notes = sorted(t.get_text() for t in ax.texts)
    assert notes == ["boom (unstable)", "coarse (dominated)", "fast", "model", "truth"]
    faces = [c.get_facecolor() for c in ax.collections]  # scatter order: model, coarse, fast, boom
    assert [len(f) and f[0][3] > 0 for f in faces] == [True, False, True, False], "dominated and unstable: hollow"
    assert ax.get_ylabel() == "rollout RMSE / body size"
