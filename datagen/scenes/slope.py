"""Sensitive-clay slope failing under its own weight (thesis §2.3.4, UMLS §3.5; after Zhao et al. 2023).

Hencky elasticity with J2 plasticity and exponential softening
kappa = (kappa_p - kappa_r) exp(-eta eps_q^p) + kappa_r (:class:`~datagen.mpm.plasticity.J2Softening`):
E = 25 MPa, nu = 0.499, kappa_p = 40.82 kPa, kappa_r = 2.45 kPa, eta = 5, rho = 2.15 t/m^3, g = 9.81.

The papers give the geometry only as a figure; ours: a slope of ``height`` H whose flat top runs
``top`` m from the back wall x = 0 to the crest, then a face at ``angle`` degrees down to the toe
on the floor y = 0; ``room`` m of floor in front of the toe for the run-out. The soil is a lattice
of cell-centred particles (``particle_spacing``) cut by the face; gravity comes on at t = 0 (the
soil starts stress free). The background is the box [0, toe + room] x [0, H + 1] (x [0, width] in
3D), meshed at ``mesh_size`` (the B-spline solver's grid spacing by default). Walls: the floor is
fixed (sticky), the back x = 0 (and in 3D the sides z = 0, z = width) are rollers (slip), the rest
separating. The floor's ghost nodes are overwritten, not folded (``Wall(..., fold=False)``): the
fold's odd mirror image holds the flow back over about a kernel width, wider for UMLS's 1-ring
than for the grid's 3x3 nodes. Measured (4 s, APIC with F-bar; benchmarks/umls_cases.py): at the
papers' resolution (``mesh_size: 0.2, particle_spacing: 0.1, room: 25``) run-out UMLS 19.0 m,
B-spline grid 20.8 m (ratio 0.915; 0.88 at 2 s, 0.92 at 3 s; with the floor folded 18.1 / 20.7 m,
0.874); at the defaults 9.92 / 12.2 m (0.81; the grid nears the far wall). At the papers'
resolution the softening localises into a curved shear band from the toe to the back by 1 s in
both solvers; at the defaults (28 particles over the height) the plastic strain spreads over the
whole sliding mass. Total energy falls every frame in all four runs.

``dim`` 2 (the default) is plane strain: with rollers on both lateral sides the 3D slope of
uniform cross-section has the same solution unless it breaks its symmetry. ``dim: 3`` runs the
3D slope; at the papers' resolution (``mesh_size: 0.2, particle_spacing: 0.1``) and a 2 m width
that is ~98k particles over ~84k steps of 4 s (the CFL step of nu = 0.499 is ~5e-5 s there), about
two hours at the 3D step's 1.2 M particle-steps/s on two cores (estimated, not run).

The solver defaults to APIC with F-bar (``solver.fbar``, :mod:`~datagen.mpm.inelastic`) against
volumetric locking. The papers used F-bar with FLIP; with FLIP both solvers are noisy at the
papers' resolution (the grid's run-out reaches 25 m by 3.8 s with plastic strains of 69; a UMLS
particle leaves the domain at 3.5 s), so both run APIC here. Per-frame diagnostics: ``runout``
(m, the advance of the foremost particle beyond the initial toe), ``plastic_strain_max``, and per
tracked particle ``plastic_strain`` (eps_q^p) and ``mean_stress`` (tr sigma / 3, Pa; negative in
compression).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..config import ConfigError
from ..mesh import Mesh
from ..mpm.boundary import Wall
from ..mpm.plasticity import J2Softening
from .base import Scene, box_domain, check_params, lattice, lattice_cells

NAME = "slope"
DEFAULTS = {
    "dim": 2, "height": 7.0, "top": 5.0, "angle": 60.0, "room": 12.0, "width": 2.0,
    "E": 25e6, "nu": 0.499, "kappa_peak": 40.82e3, "kappa_residual": 2.45e3, "eta": 5.0, "density": 2150.0,
    "gravity": 9.81, "mesh_size": 0.5, "particle_spacing": 0.25,
}
OUTPUT = {"frames": 40, "frame_interval": 0.1}
SOLVER = {"transfer": "apic", "fbar": True, "cfl": 0.5}


def params(given: dict) -> dict:
    p = check_params(NAME, DEFAULTS, given, positive=("height", "top", "room", "width", "E", "kappa_peak",
                                                      "kappa_residual", "density", "mesh_size", "particle_spacing"),
                     choices={"dim": {2, 3}})
    if not 0.0 < p["angle"] <= 90.0:
        raise ConfigError(f"params.angle must be in (0, 90] degrees, got {p['angle']!r}")
    if p["particle_spacing"] > p["height"] / 2 or p["particle_spacing"] > p["top"]:
        raise ConfigError(f"params.particle_spacing {p['particle_spacing']} is too coarse for a slope of height "
                          f"{p['height']} and top {p['top']}")
    try:
        material(p)
    except ValueError as exc:
        raise ConfigError(f"bad slope material parameters: {exc}") from None
    return p


def material(p: dict) -> J2Softening:
    return J2Softening(p["E"], p["nu"], p["density"], p["kappa_peak"], p["kappa_residual"], p["eta"])


def toe(p: dict) -> float:
    """x of the slope's toe on the floor."""
    return p["top"] + p["height"] / math.tan(math.radians(p["angle"]))


def soil(p: dict) -> tuple[np.ndarray, np.ndarray, Mesh, np.ndarray]:
    """Particles (P, d), their volumes (P,), the body mesh of the lattice simplices inside the soil,
    and (N,) the particle of each body vertex."""
    d = p["dim"]
    upper = [toe(p), p["height"]] + ([p["width"]] if d == 3 else [])
    points, counts, step = lattice(np.zeros(d), upper, p["particle_spacing"])
    face = p["top"] + (p["height"] - points[:, 1]) / math.tan(math.radians(p["angle"]))
    inside = points[:, 0] <= face
    cells = lattice_cells(counts)
    cells = cells[inside[cells].all(1)]
    particle = np.cumsum(inside) - 1  # lattice index -> particle index
    used = np.unique(cells)
    vertex = np.full(len(points), -1)
    vertex[used] = np.arange(len(used))
    body = Mesh.from_arrays(points[used], vertex[cells], orient=True)
    x = points[inside]
    return x, np.full(len(x), float(np.prod(step))), body, particle[used]


def _walls(dim: int) -> list[Wall]:
    return [
        # The fixed floor. Its ghost nodes are overwritten, not folded: folding (the odd mirror image,
        # second order for a clamp) holds the flow back over about a kernel width, wider for the UMLS
        # 1-ring than for the grid's 3x3 nodes (module docstring).
        Wall("sticky", lambda c, n: n[:, 1] <= -0.999, fold=False),
        Wall("slip", lambda c, n: (n[:, 0] <= -0.999) | (np.abs(n[:, -1]) >= 0.999 if dim == 3 else False)),
        Wall("separating", lambda c, n: (n[:, 1] > -0.999) & (n[:, 0] > -0.999)
             & ((np.abs(n[:, -1]) < 0.999) if dim == 3 else True)),
    ]


def build(p: dict) -> Scene:
    d = p["dim"]
    x, volume, body, tracked = soil(p)
    clay = material(p)
    upper = [toe(p) + p["room"], p["height"] + 1.0] + ([p["width"]] if d == 3 else [])
    gravity = np.zeros(d)
    gravity[1] = -p["gravity"]
    toe0 = float(x[:, 0].max())

    def frame_diagnostics(sim, state) -> dict:
        ids = torch.as_tensor(tracked, device=state.x.device)
        eps_q = state.plastic_strain
        return {"runout": state.x[:, 0].max() - toe0, "plastic_strain_max": eps_q.max(),
                "plastic_strain": eps_q[ids], "mean_stress": clay.mean_stress(
                    state.F[ids], None if state.out_of_plane is None else state.out_of_plane[ids])}

    return Scene(
        domain=box_domain(np.zeros(d), upper, p["mesh_size"]), body=body, x=x, v=np.zeros_like(x), volume=volume,
        materials=[(clay, None)], tracked=tracked, walls=_walls(d), gravity=gravity, grid_spacing=p["mesh_size"],
        frame_diagnostics=frame_diagnostics,
    )
