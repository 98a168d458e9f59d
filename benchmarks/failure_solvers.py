"""Items 3 and 4 of the failure suite (benchmarks/failures.py), reusing what other benchmarks
compute: the solver's known failures (C0 linear kernel, MLS without eta, eulerian numerical
fracture) and the learned models' rollouts (the comparison runs of benchmarks/model_comparison.py,
and a trained BSMS-GNN re-evaluated with other seedings at test time, thesis Table 4.8).
"""

from __future__ import annotations

import copy
import json
import re
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from mpm_verification import stress_noise  # noqa: E402
from reference_modes import fracture  # noqa: E402

import datagen  # noqa: E402
from datagen.mpm import SimulationError  # noqa: E402
from datagen.scenes import vibrating_bar  # noqa: E402

MODELS = ("cmp_bsms", "cmp_mgn", "cmp_grid", "cmp_gunets")


# ----------------------------------------------------------------------------- 3. the solver
def linear_kernel_failure(frames: int = 400) -> dict:
    """The C0 linear hat on the vibrating bar (UMLS §3.1): with FLIP the step at which the run
    fails (particles thrown off the mesh after non-finite/huge velocities) and the steps the
    UMLS run takes; with MUSL the stress noise at the probe particle, linear vs UMLS."""
    out = {}
    umls = datagen.simulate({"scene": "vibrating_bar"})
    out["umls_flip_steps"] = int(umls.substeps * (len(umls.times) - 1))
    try:
        datagen.simulate({"scene": "vibrating_bar", "solver": {"kernel": "linear"}})
        out["linear_flip_failed_step"], out["linear_flip_message"] = None, "completed"
    except SimulationError as exc:
        found = re.search(r"step (\d+)", str(exc))
        out["linear_flip_failed_step"] = int(found.group(1)) if found else -1
        out["linear_flip_message"] = str(exc).split(";")[0]
    traces = {}
    for kernel in ("umls", "linear"):
        traj = datagen.simulate({"scene": "vibrating_bar", "solver": {"kernel": kernel, "transfer": "musl"},
                                 "output": {"frames": frames, "frame_interval": 0.025}})
        stress = traj.diagnostics["probe_stress"][:, 0, 0, 0]
        traces[kernel] = (traj.times, stress)
        out[f"musl_noise_{kernel}"] = stress_noise(traj.times, stress, vibrating_bar.omega(traj.config["params"]))
    out["musl_noise_ratio"] = out["musl_noise_linear"] / out["musl_noise_umls"]
    out["traces"] = traces
    return out


def _interior_faces(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(F, 2) node pairs of the interior edges of a triangle mesh and (F, 2) their two cells."""
    cells = mesh.cells
    faces = np.sort(np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [0, 2]]]), axis=1)
    owner = np.tile(np.arange(len(cells)), 3)
    _, inverse, counts = np.unique(faces, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    pairs = order[counts[inverse[order]] == 2].reshape(-1, 2)
    return faces[pairs[:, 0]], owner[pairs]


def eta_jumps(n: int = 300, seed: int = 7) -> dict:
    """Largest jump of the weights (and of h |grad w|) when a particle crosses an interior face
    of a 2D mesh by 1e-7, with and without UMLS's diminishing factor eta (UMLS Fig. 7; the
    test suite's tests/test_kernels.py measures the same)."""
    from datagen.layer import with_extra_layer
    from datagen.mpm.kernels import MeshTables, umls_kernel
    from datagen.shapes import polygon

    mesh = polygon([(0, 0), (1.5, 0), (1.5, 1.0), (0.6, 1.3), (0, 1.0)], size=0.09)
    tables = MeshTables.build(with_extra_layer(mesh))
    rng = np.random.default_rng(seed)
    faces, cells = _interior_faces(mesh)
    pick = rng.choice(len(faces), size=min(n, len(faces)), replace=False)
    faces, cells = faces[pick], cells[pick]
    a, b = mesh.nodes[faces[:, 0]], mesh.nodes[faces[:, 1]]
    on_face = a + rng.uniform(0.2, 0.8, size=(len(a), 1)) * (b - a)
    normal = np.stack([(b - a)[:, 1], -(b - a)[:, 0]], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    h = np.linalg.norm(b - a, axis=1)
    out = {"mesh_nodes": mesh.n_nodes, "crossings": len(faces)}
    for eta in (True, False):
        k0 = umls_kernel(tables, torch.tensor(on_face - 5e-8 * normal), eta=eta)
        k1 = umls_kernel(tables, torch.tensor(on_face + 5e-8 * normal), eta=eta)
        w0, g0, w1, g1 = (_dense(k, tables.n_nodes, part) for k in (k0, k1) for part in ("weight", "grad"))
        jump = np.maximum((w1 - w0).abs().amax(dim=1).numpy(), (g1 - g0).norm(dim=-1).amax(dim=1).numpy() * h)
        name = "eta" if eta else "no_eta"
        out[f"{name}_jumps"] = jump
        out[f"{name}_median"], out[f"{name}_max"] = float(np.median(jump)), float(jump.max())
    return out


def _dense(kernel, n_nodes: int, part: str) -> torch.Tensor:
    """(P, n_nodes) weights or (P, n_nodes, d) gradients of a KernelResult, summed per node
    (empty slots hold zeros)."""
    index = kernel.index.clamp(min=0)
    if part == "weight":
        return torch.zeros(index.shape[0], n_nodes, dtype=kernel.weight.dtype).scatter_add_(1, index, kernel.weight)
    d = kernel.grad.shape[-1]
    out = torch.zeros(index.shape[0], n_nodes, d, dtype=kernel.weight.dtype)
    return out.scatter_add_(1, index[..., None].expand(-1, -1, d), kernel.grad)


def fracture_by_mode(scenes: tuple[str, ...] = ("stretched_bar", "rotating_plate")) -> dict:
    """Largest fraction of torn body-mesh edges (longer than two background cells) per scene and
    reference mode (benchmarks/reference_modes.py's measure); the eulerian and total runs'
    positions of the first scene at its most torn frame, for the picture."""
    out = {}
    for scene in scenes:
        for mode in ("eulerian", "total", "adaptive"):
            traj = datagen.simulate({"scene": scene, "solver": {"reference": mode, "threads": 1}})
            out[(scene, mode)] = fracture(traj)
            if scene == scenes[0] and mode in ("eulerian", "total"):
                edges = traj.mesh.edges
                lengths = np.linalg.norm(traj.positions[:, edges[:, 0]] - traj.positions[:, edges[:, 1]], axis=-1)
                frame = int(np.argmax((lengths > 2 * traj.config["params"]["mesh_size"]).mean(axis=1)))
                out[("picture", mode)] = (traj.positions[frame], edges, lengths[frame] > 2 * traj.config["params"][
                    "mesh_size"])
    return out


# ----------------------------------------------------------------------------- 4. learned rollouts
def comparison_rows(runs: Path = Path("runs"), prefix: str = "cmp_") -> dict[str, dict]:
    """run name -> its learned row (rmse_all, rel_all, first_unstable_step, unstable, trajectories)
    in the evaluation/metrics.json files of the runs named ``prefix``*: the comparison runs (cmp_*)
    by default, or a training study's runs (benchmarks/press_studies.py --prefix). One evaluation
    with ``--compare`` writes every compared run's row into the first run's file; rows are keyed
    by their label, the run name."""
    out = {}
    for path in sorted(runs.glob(f"{prefix}*/evaluation/metrics.json")):
        try:
            rows = json.loads(path.read_text())["rows"]
        except (OSError, ValueError, KeyError):
            continue
        for row in rows:
            if row.get("kind") == "learned" and str(row.get("label", "")).startswith(prefix):
                out.setdefault(row["label"], row)
    return out


def seeding_sensitivity(run: Path, trajectories: int, steps: int | None) -> dict:
    """Rollout errors of a trained model with the test-time graphs built with each seeding
    (min_ave, random, close_center; the training seeding first), on the first ``trajectories``
    of the test split, ``steps`` steps (None: all). -> {seeding: {rmse_1, rmse_50, rmse_all}}."""
    from bsms.data import Scenario
    from bsms.fields import initial_velocity, world_positions
    from bsms.rollouts.rollout import body_size, rollout_metrics, rollouts
    from bsms.rollouts.solver_runs import free_nodes
    from bsms.run import dataset_folder, load_model, split_files
    from datagen.dataset import load

    model, config, _ = load_model(run)
    folder, _ = dataset_folder(run, config)
    data = [load(path) for path in split_files(folder, "test")[:trajectories]]
    trained = config.graph.seeding
    out = {"trained": trained, "run": str(run)}
    for seeding in dict.fromkeys((trained, "min_ave", "close_center", "random")):
        options = copy.deepcopy(config.graph)
        options.seeding = seeding
        scenarios = [Scenario.from_trajectory(t, options, spec=model.spec) for t in data]
        truths = [world_positions(model.spec, t) for t in data]
        frames = [len(w) - 1 if steps is None else min(steps, len(w) - 1) for w in truths]
        known = [s.positions(w[: n + 1], None if t.obstacle_positions is None else t.obstacle_positions[: n + 1])
                 for s, w, n, t in zip(scenarios, truths, frames, data, strict=True)]
        initial = [s.full(initial_velocity(model.spec, t, w)[None], 0.0)[0]
                   for s, t, w in zip(scenarios, data, truths, strict=True)]
        results = rollouts(model, scenarios, [k[0] for k in known], initial, frames, known)
        metrics = [rollout_metrics(r.positions[:, : s.n_body], w[: n + 1], free_nodes(t), body_size(t.mesh.nodes))
                   for r, s, w, n, t in zip(results, scenarios, truths, frames, data, strict=True)]
        out[seeding] = {key: float(np.nanmean([m[key] for m in metrics])) for key in ("rmse_1", "rmse_50", "rmse_all")}
    return out
