"""The UMLS paper's two cases, run and drawn: the sensitive-clay ``slope`` and the ``expansion``.

The slope runs on the unstructured mesh (UMLS) and on the structured B-spline grid of the same
spacing (``solver.kernel: bspline``), both APIC with F-bar as the scene sets, at two resolutions:
the scene's defaults (0.5 m mesh, 0.25 m particles) and the papers' (0.2 m mesh, 0.1 m
particles; 25 m of floor in front of the toe so that neither run reaches the far wall). The
expansion runs once (UMLS on the conforming sphere). Every run is kept in ``--out`` as a
trajectory file (a second call reuses it: delete it to re-run) with its particles as an XDMF time
series for ParaView (velocity, displacement, and the slope's ``plastic_strain`` and ``mean_stress``).

Pictures (``--images``, default docs/images, with ``--quick`` the run folder):
``umls_slope_runout.png`` (run-out over time, both solvers and resolutions),
``umls_slope_plastic_strain.png`` (the papers' resolution at 1 s, when the shear band has
formed, and at the end, coloured by the equivalent plastic strain, both solvers) and
``umls_expansion.png`` (the wall's contact force, the farthest particle's distance from the
centre and the total energy over time). The last line is exactly

    umls cases: slope run-out UMLS U m, B-spline B m (ratio R), expansion distance max D m of 0.5 m, energy rises N

(U, B, R = U / B: the papers' resolution at the last frame; N: frames whose total energy is above
the previous frame's).

    python benchmarks/umls_cases.py [--quick] [--out runs/umls_cases]

Times on one thread: the default-resolution slope about 1.5 min UMLS and 1 min B-spline, the
papers' resolution ~13 and ~10 min, the expansion 2 min. ``--quick``: the slope at one resolution
only, a 1 m mesh with 0.5 m particles, and a 0.1 m container mesh for the expansion (a minute or
two).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import matplotlib
import numpy as np
import torch

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import datagen  # noqa: E402
from datagen.dataset import load, save  # noqa: E402
from datagen.export import write_particles  # noqa: E402

QUICK = {"slope": {"mesh_size": 1.0, "particle_spacing": 0.5}, "expansion": {"mesh_size": 0.1, "body_size": 0.1}}
PAPER_SLOPE = {"mesh_size": 0.2, "particle_spacing": 0.1, "room": 25.0}  # UMLS §3.5's resolution
BAND_TIME = 1.0  # s: the papers' resolution has formed its shear band
SOLVERS = {"umls": {}, "bspline": {"kernel": "bspline"}}
RESOLUTIONS = (("default", "defaults (0.5 m mesh)", {}), ("paper", "papers' resolution (0.2 m mesh)", PAPER_SLOPE))
QUICK_RESOLUTIONS = (("quick", "1 m mesh", QUICK["slope"]),)


def run(name: str, config: dict, out: Path) -> datagen.Trajectory:
    """The run's trajectory, from ``out/<name>.h5`` when it is there, else simulated and saved
    (with its particles in ``out/<name>_particles.xdmf``)."""
    path = out / f"{name}.h5"
    if path.is_file():
        return load(path)
    start = time.perf_counter()
    print(f"running {name} ...", flush=True)
    trajectory = datagen.simulate(config)
    save(path, trajectory)
    write_particles(trajectory, out / f"{name}_particles.xdmf")
    print(f"  {name}: {trajectory.n_particles} particles, {trajectory.substeps * (len(trajectory.times) - 1)} steps, "
          f"{time.perf_counter() - start:.0f} s", flush=True)
    return trajectory


def draw_runout(slopes: dict, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.8))
    finest = list(slopes)[-1][0]
    for (resolution, label), trajectory in slopes.items():
        ax.plot(trajectory.times, trajectory.diagnostics["runout"], label=f"{label}, {resolution}",
                ls="-" if "UMLS" in label else "--", lw=2 if resolution == finest else 1)
    ax.set(xlabel="time (s)", ylabel="run-out (m)", title="Sensitive-clay slope: run-out of the toe")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def draw_plastic_strain(slopes: dict, path: Path) -> None:
    """The finest pair (the last run) at BAND_TIME and at the end, coloured by the equivalent plastic strain."""
    finest = list(slopes)[-1][0]
    shown_runs = {label: t for (resolution, label), t in slopes.items() if resolution == finest}
    fig, axes = plt.subplots(len(shown_runs), 2, figsize=(15, 2.4 * len(shown_runs)), squeeze=False,
                             gridspec_kw={"width_ratios": [1, 2.2]})
    for row, (label, trajectory) in zip(axes, shown_runs.items(), strict=True):
        band = int(np.argmin(np.abs(trajectory.times - BAND_TIME)))
        for ax, k, top in ((row[0], band, 1.0), (row[1], -1, 5.0)):
            x = trajectory.positions[k]
            shown = ax.scatter(x[:, 0], x[:, 1], c=trajectory.diagnostics["plastic_strain"][k], s=1.5,
                               cmap="magma_r", vmin=0.0, vmax=top)
            ax.set_aspect("equal")
            ax.set(ylabel="y (m)", title=f"{label}, t = {trajectory.times[k]:.1f} s: eq. plastic strain")
            fig.colorbar(shown, ax=ax, shrink=0.8)
    for ax in axes[-1]:
        ax.set_xlabel("x (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def total_energy(d: dict) -> np.ndarray:
    return d["kinetic_energy"] + d["elastic_energy"] + d["gravitational_energy"]


def draw_expansion(trajectory, radius: float, path: Path) -> None:
    d, t = trajectory.diagnostics, trajectory.times
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    axes[0].plot(t, d["contact_force"])
    axes[0].set(xlabel="time (s)", ylabel="force (N)", title="contact force of the container")
    axes[1].plot(t, d["distance_max"], label="farthest particle")
    axes[1].axhline(radius, color="k", ls="--", lw=1, label="container")
    axes[1].set(xlabel="time (s)", ylabel="distance from the centre (m)", title="inside the container")
    axes[1].legend()
    axes[2].semilogy(t, total_energy(d))
    axes[2].set(xlabel="time (s)", ylabel="energy (J)", title="total energy (never rises)")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="coarse meshes: a minute or two in all")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "umls_cases", help="run folder")
    parser.add_argument("--images", type=Path, default=None,
                        help="where the pictures go (default docs/images; with --quick the run folder)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = args.out / ("quick" if args.quick else "default")
    out.mkdir(parents=True, exist_ok=True)
    args.images = args.images or (out if args.quick else ROOT / "docs" / "images")
    args.images.mkdir(parents=True, exist_ok=True)
    expansion_params = QUICK["expansion"] if args.quick else {}
    resolutions = QUICK_RESOLUTIONS if args.quick else RESOLUTIONS
    slopes = {}
    for key, resolution, params in resolutions:
        for name, solver, label in (("umls", SOLVERS["umls"], "UMLS (unstructured mesh)"),
                                    ("bspline", SOLVERS["bspline"], "B-spline grid")):
            slopes[resolution, label] = run(f"slope_{name}_{key}", {"scene": "slope", "params": params,
                                                                    "solver": {**solver, "threads": args.threads}}, out)
    expansion = run("expansion", {"scene": "expansion", "params": expansion_params,
                                  "solver": {"threads": args.threads}}, out)
    radius = float(expansion.config["params"]["radius"])
    draw_runout(slopes, args.images / "umls_slope_runout.png")
    draw_plastic_strain(slopes, args.images / "umls_slope_plastic_strain.png")
    draw_expansion(expansion, radius, args.images / "umls_expansion.png")
    for _, resolution, _ in resolutions:  # the last (finest) one is reported on the last line
        umls, grid = (slopes[resolution, label].diagnostics["runout"]
                      for label in ("UMLS (unstructured mesh)", "B-spline grid"))
        times = slopes[resolution, "UMLS (unstructured mesh)"].times
        print(f"{resolution}: time (s), run-out UMLS (m), run-out B-spline (m)")
        for k in range(0, len(times), max(1, len(times) // 8)):
            print(f"{times[k]:8.2f}  {umls[k]:16.3f}  {grid[k]:20.3f}")
        print("  frames whose total energy rose: " + ", ".join(
            f"{label} {int(np.sum(np.diff(total_energy(t.diagnostics)) > 0))}"
            for (r, label), t in slopes.items() if r == resolution))
    rises = int(np.sum(np.diff(total_energy(expansion.diagnostics)) > 0))
    print(f"pictures in {args.images}: umls_slope_runout.png, umls_slope_plastic_strain.png, umls_expansion.png; "
          f"particles (ParaView) in {out}")
    print(f"umls cases: slope run-out UMLS {umls[-1]:#.3g} m, B-spline {grid[-1]:#.3g} m "
          f"(ratio {umls[-1] / grid[-1]:.3g}), "
          f"expansion distance max {expansion.diagnostics['distance_max'].max():.3g} m of {radius:g} m, "
          f"energy rises {rises}")


if __name__ == "__main__":
    main()
