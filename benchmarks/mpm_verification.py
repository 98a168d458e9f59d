"""Verification of the MPM solver against closed forms and the structured B-spline solver.

Reproduces, at larger sizes than the tests, UMLS §3.1 (vibrating bar: UMLS eq. 34, convergence,
cell-crossing stress noise of the linear hat), App. D.1 (APIC rotating square: momenta),
§3.2 (colliding disks) and §3.3 (cantilever on rotated meshes). Writes ``results.json`` and
the plots (``bar_convergence.png``, ``bar_stress.png``, ``cantilever_tip.png``) to --out.
Everything stored or printed is measured by this run.

Reading the convergence series: ``convergence`` is the default bar (the mirror ghosts beyond the
fixed end folded onto the nodes they mirror); ``convergence_overwrite`` only overwrites the
ghosts' velocities after the update, which leaves the clamp a fraction of a cell beyond x = 0
and the error first order in dx; ``convergence_small_amplitude`` (v0 = 0.1) has no cell
crossings on the coarse meshes; ``convergence_bspline`` is the structured B-spline solver, whose
grid nodes beyond the clamp are folded mirror ghosts too.

    python benchmarks/mpm_verification.py [--out runs/mpm_verification] [--quick] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

import datagen  # noqa: E402
from datagen.mpm import SimulationError  # noqa: E402
from datagen.scenes import vibrating_bar  # noqa: E402

CONVERGENCE_DT = 1e-3  # below the CFL step of every size (400 cells: 1.9e-3); the CFL step gives the same errors


def stress_noise(t: np.ndarray, stress: np.ndarray, omega: float) -> float:
    """RMS left by a least-squares fit of the smooth response (constant, omega and 3 omega harmonics)."""
    basis = np.stack([np.ones_like(t)] + [f(k * omega * t) for k in (1, 3) for f in (np.sin, np.cos)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, stress, rcond=None)
    return float(np.sqrt(np.mean((stress - basis @ coef) ** 2)))


def bar_errors(traj) -> dict:
    """Centre-of-mass RMSE (UMLS eq. 34) and particle-displacement RMSE, relative to their amplitudes;
    the relative errors of the first mode's frequency and amplitude, fitted to the particle displacements."""
    p = traj.config["params"]
    cm = traj.diagnostics["center_of_mass"][:, 0]
    cm_rmse = np.sqrt(np.mean((cm - vibrating_bar.center_of_mass(p, traj.times)) ** 2))
    X = traj.positions[0, :, 0]
    omega, beta = vibrating_bar.omega(p), np.pi / (2 * p["length"])
    amplitude = p["v0"] / omega
    shape = np.sin(beta * X)
    exact = amplitude * np.sin(omega * traj.times)[:, None] * shape[None, :]
    u = traj.positions[:, :, 0] - X[None, :]
    q = (u @ shape) / (shape @ shape)  # first-mode coefficient of the displacement
    fit = least_squares(lambda z: z[0] * np.sin(z[1] * traj.times + z[2]) - q, [amplitude, omega, 0.0]).x
    return {
        "cm_rmse_rel": float(cm_rmse / vibrating_bar.amplitude(p)),
        "displacement_rmse_rel": float(np.sqrt(np.mean((u - exact) ** 2)) / amplitude),
        "omega_rel_error": float(fit[1] / omega - 1.0),
        "amplitude_rel_error": float(fit[0] / amplitude - 1.0),
    }


def _convergence(cells: list[int], params: dict | None = None, solver: dict | None = None) -> list[dict]:
    """bar_errors over one period at each size, with one small fixed dt for all sizes."""
    out = []
    for n in cells:
        traj = datagen.simulate({"scene": "vibrating_bar", "params": {"n_cells": n, **(params or {})},
                                 "solver": {"dt": CONVERGENCE_DT, **(solver or {})}})
        out.append({"n_cells": n, "dx": 25.0 / n, **bar_errors(traj)})
    return out


COARSE, FINE = (12, 50), (100, 400)  # cells: the paper's coarse range (dx 2 m to 0.5 m) and the fine one


def _slope(series: list[dict], cells: tuple[int, int] = COARSE) -> float | None:
    """Least-squares slope of log(displacement RMSE) against log(dx) over the sizes within ``cells``
    (None with fewer than two)."""
    rows = [c for c in series if cells[0] <= c["n_cells"] <= cells[1]]
    if len(rows) < 2:
        return None
    dx = np.array([c["dx"] for c in rows])
    err = np.array([c["displacement_rmse_rel"] for c in rows])
    return float(np.polyfit(np.log(dx), np.log(err), 1)[0])


def vibrating_bar_study(out: Path, quick: bool) -> dict:
    """UMLS eq. 34 at 80 cells (1D and 2D strip), convergence in dx, stress noise linear vs UMLS.

    Convergence (1D, one period, dt = CONVERGENCE_DT): the default bar (fixed end: folded
    mirror ghosts, v0 = 0.75 as in the paper), the small amplitude v0 = 0.1 (no cell crossing
    on coarse meshes), and the fixed end without the fold (``overwrite``, the treatment before);
    the full run adds 200 and 400 cells and the structured B-spline solver (its grid nodes
    beyond the clamp are folded mirror ghosts too). Slopes of log(displacement RMSE) against
    log(dx): ``convergence_slope_coarse*`` at 12-50 cells (the paper's coarse range, dx 2 m to
    0.5 m), ``convergence_slope_12_100*``, and in the full run ``convergence_slope_fine*`` at 100-400 cells.
    """
    res = {}
    for dim in (1, 2):
        traj = datagen.simulate({"scene": "vibrating_bar", "params": {"dim": dim}})
        res[f"{dim}d_80_cells"] = {**bar_errors(traj), "wall_time_s": traj.wall_time}
    cells = [12, 25, 50, 100] if quick else [12, 25, 50, 100, 200, 400]
    coarse = [n for n in cells if n <= 100]
    series = {
        "convergence": _convergence(cells),
        "convergence_small_amplitude": _convergence(cells, {"v0": 0.1}),
        "convergence_overwrite": _convergence(coarse, {"fixed_end": "overwrite"}),
    }
    if not quick:
        series["convergence_bspline"] = _convergence(coarse, solver={"kernel": "bspline"})
    for name, rows in series.items():
        res[name] = rows
        res[name.replace("convergence", "convergence_slope_coarse")] = _slope(rows)  # 12-50 cells
        res[name.replace("convergence", "convergence_slope_12_100")] = _slope(rows, (12, 100))
        if not quick and name in ("convergence", "convergence_small_amplitude"):
            res[name.replace("convergence", "convergence_slope_fine")] = _slope(rows, FINE)  # 100-400 cells
    _plot_convergence(out / "bar_convergence.png", series)
    res["stress_noise"] = _bar_noise(out)
    return res


_SERIES_LABELS = {
    "convergence": "UMLS, v0 = 0.75 (paper)",
    "convergence_small_amplitude": "UMLS, v0 = 0.1",
    "convergence_overwrite": "UMLS, v0 = 0.75, ghosts not folded (before)",
    "convergence_bspline": "B-spline grid, folded mirror ghosts, v0 = 0.75",
}


def _plot_convergence(path: Path, series: dict[str, list[dict]]) -> None:
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for name, rows in series.items():
        dx = np.array([c["dx"] for c in rows])
        err = np.array([c["displacement_rmse_rel"] for c in rows])
        ax.loglog(dx, err, "o-", label=f"{_SERIES_LABELS[name]} (slope {_slope(rows):.2f} at 12-50 cells)")
    rows = series["convergence"]
    dx = np.array([c["dx"] for c in rows])
    ax.loglog(dx, rows[0]["displacement_rmse_rel"] * (dx / dx[0]) ** 2, "k--", lw=0.8, label="slope 2")
    ax.set_xlabel("cell size dx [m]")
    ax.set_ylabel("RMSE of particle displacement / amplitude")
    ax.set_title("Vibrating bar (UMLS §3.1), one period")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _bar_noise(out: Path) -> dict:
    """Stress at the particle nearest x0 = 12.75 m: UMLS vs the linear hat (both with MUSL)."""
    traces, res = {}, {}
    for kernel in ("umls", "linear"):
        traj = datagen.simulate({"scene": "vibrating_bar", "solver": {"kernel": kernel, "transfer": "musl"},
                                 "output": {"frames": 400, "frame_interval": 0.025}})
        stress = traj.diagnostics["probe_stress"][:, 0, 0, 0]
        traces[kernel] = (traj.times, stress)
        res[kernel] = stress_noise(traj.times, stress, vibrating_bar.omega(traj.config["params"]))
    res["ratio_linear_over_umls"] = res["linear"] / res["umls"]
    try:  # the linear hat with plain FLIP (the paper's transfer) blows up: record where
        datagen.simulate({"scene": "vibrating_bar", "solver": {"kernel": "linear"}})
        res["linear_flip"] = "completed"
    except SimulationError as exc:
        res["linear_flip"] = str(exc)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for kernel, (t, s) in traces.items():
        ax.plot(t, s, lw=0.9, label=kernel)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("sigma_xx at x0 = 12.75 m [Pa]")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "bar_stress.png", dpi=120)
    plt.close(fig)
    return res


def rotating_square_study(quick: bool) -> dict:
    """APIC + UMLS (App. D.1, paper settings): relative drift of linear and angular momentum."""
    frames = 10 if quick else 50
    traj = datagen.simulate({"scene": "rotating_square",
                             "output": {"frames": frames, "frame_interval": 1e-3, "step_diagnostics": True}})
    steps = traj.step_diagnostics
    p = traj.config["params"]
    scale = float(traj.diagnostics["mass"][0]) * p["speed"]
    L0 = float(traj.diagnostics["angular_momentum"][0])
    return {
        "steps": int(len(steps["momentum"])),
        "linear_momentum_max_rel": float(np.abs(steps["momentum"]).max() / scale),
        "angular_momentum_max_rel_drift": float(np.abs(steps["angular_momentum"] - L0).max() / abs(L0)),
        "wall_time_s": traj.wall_time,
    }


def colliding_disks_study(quick: bool) -> dict:
    """UMLS at the paper's settings vs a fine B-spline run: momentum and kinetic energy recovery."""
    runs = {
        "umls": ({"kernel": "umls"}, {}),
        "linear_musl": ({"kernel": "linear", "transfer": "musl"}, {}),
        "bspline_fine": ({"kernel": "bspline", "grid_spacing": 0.0125}, {"body_size": 0.00625}),
    }
    res = {}
    for name, (solver, params) in runs.items():
        try:
            traj = datagen.simulate({"scene": "colliding_disks", "solver": solver, "params": params})
        except SimulationError as exc:
            res[name] = {"error": str(exc)}
            continue
        ke = traj.diagnostics["kinetic_energy"]
        scale = float(traj.diagnostics["mass"][0]) * np.linalg.norm(traj.velocities[0], axis=1).max()
        res[name] = {"ke_recovered": float(ke[-1] / ke[0]), "ke_min": float(ke.min() / ke[0]),
                     "momentum_max_rel": float(np.abs(traj.diagnostics["momentum"]).max() / scale),
                     "particles": traj.n_particles, "wall_time_s": traj.wall_time}
    if "ke_recovered" in res["umls"] and "ke_recovered" in res["bspline_fine"]:
        fine = res["bspline_fine"]["ke_recovered"]
        res["umls_ke_recovery_rel_error"] = abs(res["umls"]["ke_recovered"] - fine) / fine
    return res


def _tip_series(kernel: str, params: dict, solver: dict | None = None, seconds: float = 1.5):
    solver = {"kernel": kernel, **(solver or {})}
    traj = datagen.simulate({"scene": "cantilever", "params": params, "solver": solver,
                             "output": {"frames": round(seconds / 0.01), "frame_interval": 0.01}})
    tip = int(np.argmin(np.linalg.norm(traj.positions[0] - [10.0, 1.0], axis=1)))
    return traj.times, traj.positions[:, tip, 1] - traj.positions[0, tip, 1]


def cantilever_study(out: Path, quick: bool) -> dict:
    """Tip deflection on rotated meshes (UMLS §3.3) vs the fine structured B-spline solver."""
    seconds = 0.8 if quick else 1.5
    t, fine = _tip_series("bspline", {"particle_spacing": 0.0625}, {"grid_spacing": 0.125}, seconds)
    res = {"bspline_max_deflection": float(-fine.min()), "meshes": {}}
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(t, fine, "k", lw=2, label="structured B-spline solver (h = 0.125 m)")
    for size in (0.5, 0.4):
        per = {}
        for angle in (0.0, 15.0, 30.0, 45.0):
            _, dy = _tip_series("umls", {"mesh_size": size, "rotation": angle}, None, seconds)
            rmse = float(np.sqrt(np.mean((dy - fine) ** 2)))
            per[f"{angle:g}"] = {"max_deflection": float(-dy.min()),
                                 "rel_error_vs_bspline": float(abs(dy.min() - fine.min()) / -fine.min()),
                                 "rmse_vs_bspline_rel": rmse / float(-fine.min())}
            ax.plot(t, dy, lw=0.8, label=f"UMLS mesh {size} m, {angle:g} deg")
        upright = per["0"]["max_deflection"]
        for record in per.values():
            record["rel_change_vs_unrotated"] = abs(record["max_deflection"] - upright) / upright
        res["meshes"][f"{size:g}"] = per
    ax.set_xlabel("t [s]")
    ax.set_ylabel("tip y-displacement [m]")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "cantilever_tip.png", dpi=120)
    plt.close(fig)
    return res


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/mpm_verification"))
    parser.add_argument("--quick", action="store_true", help="smaller sizes, for a smoke run")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    results, start = {}, time.perf_counter()
    for name, study in (("vibrating_bar", lambda: vibrating_bar_study(args.out, args.quick)),
                        ("rotating_square", lambda: rotating_square_study(args.quick)),
                        ("colliding_disks", lambda: colliding_disks_study(args.quick)),
                        ("cantilever", lambda: cantilever_study(args.out, args.quick))):
        t0 = time.perf_counter()
        results[name] = study()
        print(f"{name}: {time.perf_counter() - t0:.0f} s\n{json.dumps(results[name], indent=1)}", flush=True)
    results["total_seconds"] = time.perf_counter() - start
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out / 'results.json'}")


if __name__ == "__main__":
    main()
