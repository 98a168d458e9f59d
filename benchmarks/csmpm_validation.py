"""CSMPM's gas against closed forms and finer runs (thesis §3.3.1, Kwatra et al. 2009).

1D: Sod's and Lax's shock tubes at ``--cells`` resolutions against (a) the exact Riemann
solution (L1 density error) and (b) a ``--reference``-cell run: the squared density deviation
e_dm = sum (rho - rho_b)^2 / (sum rho_b)^2 (thesis eq. 3.38), rho_b the reference averaged onto
the coarse cells; the convergence order per case from the two finest resolutions.
2D: the central circular shock at ``--circular`` resolutions against a ``--circular-reference``
run (e_dm, its order), per velocity/pressure order of ``--schemes`` (B1B0, B2B1: the thesis'
ablation; the reference is B1B0, as the thesis' is Kwatra's; the last line gives the first
scheme's order). Orders are the slopes between the two finest resolutions; e_dm's
normalisation by (sum rho_b)^2 and its square make its order about 2 x the L1 order + the
dimension, so the L1 orders (against the exact solution in 1D, the reference run in 2D) are the
ones comparable across cases; the last line gives those. Every run: the most CG iterations of
any pressure solve. Solver: the scene defaults (CFL 0.5 on |u| + c). Ends with exactly
``csmpm: sod L1 density error E at N cells (order p), circular shock order q, CG iterations max K``.

    python benchmarks/csmpm_validation.py [--cells 128 256 512 1024 2048] [--reference 4096]
        [--circular 64 128 256] [--circular-reference 512] [--pictures docs/images]

``--performance 128 256 512 1024`` also times ``--steps`` steps of the circular shock at each
resolution (acoustic CFL 0.5, after two steps of the blast): cell-steps per second and CG
iterations per step, one thread.

``--pictures DIR`` also draws ``csmpm_sod.png`` (Sod at 128 and 512 cells over the exact
solution), ``csmpm_circular_shock.png`` and ``csmpm_stair_flow.png`` (schlieren: exp(-k |grad
rho| / max |grad rho|), Woodward and Colella's Mach 3 step at t = 0.5, 1, 2, 4, 60 cells per unit),
``csmpm_b2b1.png`` (the circular shock's errors per scheme against resolution), and with the gas
coupled to MPM solids ``csmpm_lifting_cylinder.png`` (400 cells per unit length, to t = 0.36),
``csmpm_shell_explosion.png`` (128^2) and ``csmpm_bullet.png`` (100 cells per unit length):
schlieren of the gas, solid cells blue, the body's nodes orange over them (``--picture-sets gas
coupled`` picks).

``--coupling`` also runs the coupled solver's closed-box check (a 4x pressure jump hitting an
elastic disk, 64^2 cells, 300 steps): gas mass drift, the largest per-step difference between
the momentum change of gas and solid together and the walls' pressure impulse, and the drift of
the total energy (gas, the solid's kinetic and elastic).

``--outlets`` also measures the outlets (``euler.Grid.outlet``) on a 1D tube of 200 cells over
[0, 1], walled on the left, its right end an outlet to a far field at rest at p = rho = 1
(acoustic CFL 0.5): the amplitude of the wave reflected by a right-going acoustic pulse (1e-3 of
the pressure) over the pulse's, once it has left (t = 0.9 / c), and the mean pressure 3 s after
the tube started at rest at p = 1.1.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import datagen  # noqa: E402
from datagen.csmpm import b2b1, euler, gas  # noqa: E402

TUBES = {  # name: (left, right, end time) on [0, 1], interface 0.5
    "sod": ([1.0, 0.0, 1.0], [0.125, 0.0, 0.1], 0.2),
    "lax": ([0.445, 0.698, 3.528], [0.5, 0.0, 0.571], 0.13),
}


def _tube(name: str, cells: int):
    left, right, end = TUBES[name]
    return datagen.simulate({"scene": "shock_tube", "params": {"left": left, "right": right, "cells": cells},
                             "output": {"frames": 1, "frame_interval": end}})


def _coarsen(field: np.ndarray, factor: int) -> np.ndarray:
    """Block means of a (n,) or (n, n) cell field by ``factor`` per axis."""
    if field.ndim == 1:
        return field.reshape(-1, factor).mean(1)
    n = field.shape[0] // factor
    return field.reshape(n, factor, n, factor).mean(axis=(1, 3))


def e_dm(rho: np.ndarray, reference: np.ndarray) -> float:
    """Thesis eq. 3.38: sum (rho - rho_b)^2 / (sum rho_b)^2, rho_b the reference on rho's cells."""
    rho_b = _coarsen(reference, reference.shape[0] // rho.shape[0])
    return float(np.sum((rho - rho_b) ** 2) / np.sum(rho_b) ** 2)


def l1_reference(rho: np.ndarray, reference: np.ndarray) -> float:
    """Mean |rho - rho_b| over rho's cells, rho_b the reference averaged onto them."""
    return float(np.mean(np.abs(rho - _coarsen(reference, reference.shape[0] // rho.shape[0]))))


def _order(errors: list[float], cells: list[int]) -> float:
    return float(np.log(errors[-2] / errors[-1]) / np.log(cells[-1] / cells[-2]))


def schlieren(rho: np.ndarray, k: float = 15.0) -> np.ndarray:
    """Numerical schlieren of a 2D density field (NaN where there is no gas)."""
    gx, gy = np.gradient(np.where(np.isnan(rho), np.nanmean(rho), rho))
    g = np.hypot(gx, gy)
    return np.where(np.isnan(rho), np.nan, np.exp(-k * g / g[~np.isnan(rho)].max()))


def _grid_field(t, values: np.ndarray, dx: float) -> np.ndarray:
    """A per-cell field of a 2D gas trajectory on its full grid (NaN at cells it does not hold)."""
    x = t.fields["x"]
    ij = np.round(x / dx - 0.5).astype(int)
    out = np.full(ij.max(0) + 1, np.nan)
    out[ij[:, 0], ij[:, 1]] = values
    return out


def pictures(folder: Path, circular: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.4))
    left, right, end = TUBES["sod"]
    fine = np.linspace(0, 1, 2001)
    exact, _ = gas.exact_riemann(left, right, fine, end, interface=0.5)
    for cells, style in ((128, "o"), (512, ".")):
        t = _tube("sod", cells)
        for a, name in zip(ax, ("density", "velocity", "pressure"), strict=True):
            a.plot(t.fields["x"], t.fields[name][-1], style, ms=2.5, label=f"{cells} cells")
    for a, name, values in zip(ax, ("density", "velocity", "pressure"), exact, strict=True):
        a.plot(fine, values, "k-", lw=0.8, label="exact")
        a.set_title(f"Sod, t = {end}: {name}")
        a.set_xlabel("x")
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(folder / "csmpm_sod.png", dpi=100)
    plt.close(fig)
    t = datagen.simulate({"scene": "circular_shock", "params": {"cells": circular}})
    dx = 2.0 / circular
    fig, ax = plt.subplots(1, 3, figsize=(11, 3.8))
    for a, k in zip(ax, (2, 6, 10), strict=True):
        a.imshow(schlieren(_grid_field(t, t.fields["density"][k], dx)).T, origin="lower", extent=[-1, 1, -1, 1],
                 cmap="gray")
        a.set_title(f"circular shock, t = {t.times[k]:.3g}")
    fig.tight_layout()
    fig.savefig(folder / "csmpm_circular_shock.png", dpi=100)
    plt.close(fig)
    t = datagen.simulate({"scene": "stair_flow", "params": {"cells": 60},
                          "output": {"frames": 8, "frame_interval": 0.5}})
    fig, ax = plt.subplots(4, 1, figsize=(9, 10))
    for a, k in zip(ax, (1, 2, 4, 8), strict=True):
        a.imshow(schlieren(_grid_field(t, t.fields["density"][k], 1 / 60)).T, origin="lower", extent=[0, 3, 0, 1],
                 cmap="gray")
        a.set_title(f"stair flow (Mach 3 inlet, outlet right), t = {t.times[k]:.3g}")
    fig.tight_layout()
    fig.savefig(folder / "csmpm_stair_flow.png", dpi=90)
    plt.close(fig)


def coupled_pictures(folder: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    cases = [("lifting_cylinder", {"cells": 400}, {"frames": 12}, (4, 8, 12), [0, 1, 0, 0.2], (3, 1),
              "Mach 3 shock, cylinder on the floor"),
             ("shell_explosion", {}, {}, (1, 3, 6), [0, 1, 0, 1], (1, 3), "elastic ring, 10x pressure inside"),
             ("bullet", {}, {}, (2, 5, 10), [0, 3, 0, 1], (3, 1), "static barrel, 50x pressure behind the bullet")]
    for name, params, output, frames, extent, layout, title in cases:
        start = time.perf_counter()
        t = datagen.simulate({"scene": name, "params": params, "output": output})
        dx = 1.0 / t.config["params"]["cells"]
        print(f"{name}: {t.substeps} steps, {time.perf_counter() - start:.0f} s, CG iterations max "
              f"{int(t.diagnostics['cg_iterations'].max())}, floored cell-steps {int(t.diagnostics['floored'].sum())}")
        shown = list(frames)
        centres = zip(t.times[shown], t.diagnostics["centre"][shown], strict=True)
        print(f"{name}: the body's centre " + ", ".join(f"({x:.3f}, {y:.3f}) at t = {when:.2f}"
                                                         for when, (x, y) in centres))
        size = (10, 6.5) if layout == (3, 1) else (12, 4.2)
        fig, ax = plt.subplots(*layout, figsize=size)
        for a, k in zip(np.ravel(ax), frames, strict=True):
            rho = np.where(t.fields["solid"][k], np.nan, t.fields["density"][k])
            cmap = matplotlib.colormaps["gray"].with_extremes(bad="tab:blue")  # solid cells
            a.imshow(schlieren(_grid_field(t, rho, dx)).T, origin="lower", extent=extent, cmap=cmap)
            a.plot(t.positions[k, :, 0], t.positions[k, :, 1], ",", color="tab:orange")
            a.set_xlim(extent[:2])
            a.set_ylim(extent[2:])
            a.set_title(f"{name.replace('_', ' ')} ({title}), t = {t.times[k]:.3g}", fontsize=9)
        fig.tight_layout()
        fig.savefig(folder / f"csmpm_{name}.png", dpi=90)
        plt.close(fig)


def coupling(cells: int = 64, steps: int = 300) -> int:
    """The closed-box conservation check of the coupled solver; returns the most CG iterations."""
    from datagen import shapes
    from datagen.csmpm import coupled, euler
    from datagen.mpm.materials import NeoHookean

    dx = 1.0 / cells
    grid = euler.Grid((cells, cells), dx, (("wall", "wall"), ("wall", "wall")))
    solid = coupled.Solid.from_mesh(shapes.disk(0.12, 0.5 * dx, center=(0.55, 0.5)),
                                    NeoHookean(E=200.0, nu=0.3, density=3.0), p0=1.0)
    x = (np.arange(cells) + 0.5) * dx
    left = (x < 0.25)[:, None] & np.ones(cells, bool)
    state = gas.conserved(np.where(left, 2.0, 1.0), np.zeros((2, cells, cells)), np.where(left, 4.0, 1.0))

    def totals():
        return (state[0].sum() * dx * dx, state[1:3].sum((1, 2)) * dx * dx + solid.momentum,
                state[3].sum() * dx * dx + coupled.solid_energy(solid))

    mass0, momentum, energy0 = totals()
    worst, drift, most, start = 0.0, 0.0, 0, time.perf_counter()
    for _ in range(steps):
        dt = coupled.time_step(state, solid, grid)
        state, solid, info = coupled.step(state, solid, grid, dt)
        p = info.pressure
        wall = -dt * dx * np.array([p[-1].sum() - p[0].sum(), p[:, -1].sum() - p[:, 0].sum()])
        mass, now, energy = totals()
        worst = max(worst, float(np.abs(now - momentum - wall).max()))
        drift = max(drift, abs(energy / energy0 - 1.0))
        momentum, most = now, max(most, info.cg_iterations)
    print(f"coupling, closed box {cells}^2, {steps} steps ({time.perf_counter() - start:.1f} s): mass drift "
          f"{abs(mass / mass0 - 1):.1e}, momentum against the walls' impulse {worst:.1e} per step (solid momentum "
          f"{solid.momentum[0]:.3f}), energy drift {drift:.1e}, CG iterations max {most}")
    return most


def performance(resolutions: list[int], steps: int) -> None:
    from datagen.csmpm import euler
    from datagen.csmpm.scenes import _initial, resolve

    print(f"{'cells':>10}{'cell-steps/s':>14}{'s/step':>9}{'CG mean':>9}{'CG max':>8}")
    for n in resolutions:
        config = resolve({"scene": "circular_shock", "params": {"cells": n}})
        grid, state, *_ = _initial("circular_shock", config["params"])
        for _ in range(2):  # the blast under way, caches warm
            state, _ = euler.step(state, grid, euler.time_step(state, grid, 0.5, 1.0))
        iterations, start = [], time.perf_counter()
        for _ in range(steps):
            state, info = euler.step(state, grid, euler.time_step(state, grid, 0.5, 1.0))
            iterations.append(info.cg_iterations)
        seconds = (time.perf_counter() - start) / steps
        print(f"{f'{n}^2':>10}{n * n / seconds:>14.3g}{seconds:>9.3f}{np.mean(iterations):>9.1f}{max(iterations):>8}")


def _outlet_run(state: np.ndarray, outlet: str, attenuation: float, seconds: float) -> np.ndarray:
    n = state.shape[1]
    grid = euler.Grid((n,), 1.0 / n, (("wall", "open"),), outlet=outlet, attenuation=attenuation,
                      outflow=gas.conserved(np.array(1.0), np.array([0.0]), np.array(1.0)))
    t = 0.0
    while t < seconds - 1e-12:
        dt = min(euler.time_step(state, grid, 0.5, 1.0), seconds - t)
        state, _ = euler.step(state, grid, dt)
        t += dt
    return state


def outlets(n: int = 200) -> None:
    """The outlets' reflection of a leaving pressure pulse and relaxation of an overpressure."""
    x, c = (np.arange(n) + 0.5) / n, np.sqrt(gas.GAMMA)
    dp = 1e-3 * np.exp(-(((x - 0.5) / 0.05) ** 2))
    pulse = gas.conserved(1.0 + dp / c**2, (dp / c)[None], 1.0 + dp)
    over = gas.conserved(np.full(n, 1.1 ** (1 / gas.GAMMA)), np.zeros((1, n)), np.full(n, 1.1))
    print(f"{'outlet':<22}{'reflected':>11}{'mean p at 3 s':>15}")
    for outlet, a in (("extrapolate", 1.0), ("attenuate", 0.9), ("attenuate", 0.5), ("attenuate", 0.0),
                      ("characteristic", 1.0)):
        state = _outlet_run(pulse.copy(), outlet, a, 0.9 / c)
        reflected = np.abs(gas.pressure(state) - 1.0 - c * state[1] / state[0]).max() / 2 / 1e-3
        relaxed = gas.pressure(_outlet_run(over.copy(), outlet, a, 3.0)).mean()
        label = outlet if outlet != "attenuate" else f"attenuate (a = {a:g})"
        print(f"{label:<22}{reflected:>11.4f}{relaxed:>15.5f}")


def _circular_run(cells: int, scheme: str):
    start = time.perf_counter()
    t = datagen.simulate({"scene": "circular_shock", "params": {"cells": cells}, "solver": {"scheme": scheme}})
    return t, t.fields["density"][-1].reshape(cells, cells), time.perf_counter() - start


def circular(resolutions: list[int], n_ref: int, schemes: list[str], folder: Path | None) -> tuple[dict, int]:
    """The circular shock at ``resolutions`` per scheme against one B1B0 run at ``n_ref``^2 (the
    thesis' ablation, Fig. 3.5 right); with ``folder`` also ``csmpm_b2b1.png``. -> (per scheme its
    L1 order, the most CG iterations of any run)."""
    reference, rho_ref, _ = _circular_run(n_ref, "B1B0")
    cg_max = int(reference.diagnostics["cg_iterations"].max())
    orders, curves = {}, {}
    for scheme in schemes:
        dm, ref = [], []
        for cells in resolutions:
            t, rho, seconds = _circular_run(cells, scheme)
            dm.append(e_dm(rho, rho_ref))
            ref.append(l1_reference(rho, rho_ref))
            k = int(t.diagnostics["cg_iterations"].max())
            cg_max = max(cg_max, k)
            print(f"{'circular ' + scheme:<16}{cells:>7}{'-':>12}{ref[-1]:>12.3e}{dm[-1]:>12.3e}{k:>8}{t.substeps:>8}"
                  f"{seconds:>8.1f}")
        orders[scheme], curves[scheme] = _order(ref, resolutions), (ref, dm)
        print(f"circular_shock {scheme}: order {orders[scheme]:.2f} (L1 against {n_ref}^2 cells of B1B0), "
              f"{_order(dm, resolutions):.2f} (e_dm)")
    if folder is not None:
        _ablation_picture(folder, resolutions, n_ref, curves)
    return orders, cg_max


def _ablation_picture(folder: Path, resolutions: list[int], n_ref: int, curves: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(1, 2, figsize=(8, 3.2))
    for scheme, (ref, dm) in curves.items():
        for a, values in zip(ax, (ref, dm), strict=True):
            a.loglog(resolutions, values, "o-", label=scheme)
    for a, title in zip(ax, ("L1 density error", "e_dm (thesis eq. 3.38)"), strict=True):
        a.set_xlabel("cells per side")
        a.set_title(f"circular shock: {title}\nagainst a {n_ref}$^2$ B1B0 run", fontsize=9)
        a.legend()
    fig.tight_layout()
    fig.savefig(folder / "csmpm_b2b1.png", dpi=100)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", type=int, nargs="+", default=[128, 256, 512, 1024, 2048])
    parser.add_argument("--reference", type=int, default=4096)
    parser.add_argument("--circular", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--circular-reference", type=int, default=512)
    parser.add_argument("--schemes", nargs="+", choices=b2b1.SCHEMES, default=list(b2b1.SCHEMES),
                        help="the circular shock's velocity/pressure orders (the last line: the first)")
    parser.add_argument("--pictures", type=Path, default=None, help="folder for the pictures (none: no pictures)")
    parser.add_argument("--picture-sets", nargs="+", choices=["gas", "coupled"], default=["gas", "coupled"])
    parser.add_argument("--coupling", action="store_true", help="run the coupled solver's closed-box check")
    parser.add_argument("--performance", type=int, nargs="*", default=[], help="circular shock resolutions to time")
    parser.add_argument("--steps", type=int, default=5, help="steps timed per --performance resolution")
    parser.add_argument("--outlets", action="store_true", help="measure the outlets' reflection and relaxation")
    args = parser.parse_args(argv)
    if args.outlets:
        outlets()
    if args.performance:
        performance(args.performance, args.steps)
    cg_max, summary = 0, {}
    if args.pictures is not None and "gas" in args.picture_sets:
        pictures(args.pictures, args.circular[-1])
    if args.pictures is not None and "coupled" in args.picture_sets:
        coupled_pictures(args.pictures)
    if args.coupling:
        cg_max = coupling()
    print(f"{'case':<16}{'cells':>7}{'L1 exact':>12}{'L1 ref':>12}{'e_dm':>12}{'CG max':>8}{'steps':>8}{'s':>8}")
    for name in TUBES:
        reference = _tube(name, args.reference)
        cg_max = max(cg_max, int(reference.diagnostics["cg_iterations"].max()))
        l1, ref, dm = [], [], []
        for cells in args.cells:
            start = time.perf_counter()
            t = _tube(name, cells)
            seconds = time.perf_counter() - start
            left, right, end = TUBES[name]
            (exact, _, _), _ = gas.exact_riemann(left, right, t.fields["x"], end, interface=0.5)
            rho = t.fields["density"][-1]
            l1.append(float(np.abs(rho - exact).mean()))
            dm.append(e_dm(rho, reference.fields["density"][-1]))
            ref.append(l1_reference(rho, reference.fields["density"][-1]))
            k = int(t.diagnostics["cg_iterations"].max())
            cg_max = max(cg_max, k)
            print(f"{name:<16}{cells:>7}{l1[-1]:>12.3e}{ref[-1]:>12.3e}{dm[-1]:>12.3e}{k:>8}{t.substeps:>8}"
                  f"{seconds:>8.1f}")
        summary[name] = (l1, dm)
        print(f"{name}: order {_order(l1, args.cells):.2f} (L1 against the exact solution), "
              f"{_order(ref, args.cells):.2f} (L1 against {args.reference} cells), "
              f"{_order(dm, args.cells):.2f} (e_dm against {args.reference} cells)")
    orders, k = circular(args.circular, args.circular_reference, args.schemes, args.pictures)
    cg_max = max(cg_max, k)
    circular_order = orders[args.schemes[0]]
    l1 = summary["sod"][0]
    print(f"csmpm: sod L1 density error {l1[-1]:.3g} at {args.cells[-1]} cells (order {_order(l1, args.cells):.2f}), "
          f"circular shock order {circular_order:.2f}, CG iterations max {cg_max}")


if __name__ == "__main__":
    main()
