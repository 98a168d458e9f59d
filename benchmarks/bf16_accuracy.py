"""What bfloat16 costs a trained model in accuracy: one-step and rollout error, bf16 against f32.

The run's model (``best.pt``) predicts, in each precision (``bsms.models.precision``):

* one step: every (frame t -> t+1) sample of the ``--split`` trajectories (no noise); the
  error is the RMSE over free nodes of the predicted next position, dt (dv - dv_true) (m);
* rollouts: each trajectory from frame 0 for all its frames (``bsms.rollouts.rollout.rollouts``, as
  ``bsms.evaluate`` does); RMSE over all steps and free body nodes (m), mean over trajectories,
  and the count of unstable rollouts.

bf16 runs on any CPU (emulated, several times slower, where the CPU has no bfloat16
instructions); its numbers are the same wherever it runs, up to the order of float sums.
Prints one line per precision and ends with
``bf16 vs f32: one-step error x a, rollout error x b``.

    python benchmarks/bf16_accuracy.py RUN_DIR [--split test] [--threads 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Batch

PRECISIONS = ("f32", "bf16")


def one_step_rmse(model, dataset, precision: str, batch_size: int = 8) -> float:
    """RMSE (m) of the next position of free nodes over every sample of ``dataset``."""
    squared, count = 0.0, 0
    for start in range(0, len(dataset), batch_size):
        batch = Batch.from_data_list([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])
        with torch.no_grad():
            change = model.physical(model(batch, precision=precision), batch).double()
        error = (change - batch.target.double()) * batch.frame_dt.double()[:, None]
        squared += float(error[batch.loss_mask].square().sum())
        count += int(batch.loss_mask.sum())
    return float(np.sqrt(squared / max(count, 1)))


def rollout_errors(model, config, trajectories, precision: str) -> dict:
    """Mean rollout RMSE (m and relative to the body size) and unstable count over ``trajectories``."""
    from bsms.data import Scenario
    from bsms.rollouts.rollout import body_size, rollout_metrics, rollouts
    from bsms.rollouts.solver_runs import free_nodes

    scenarios = [Scenario.from_trajectory(t, config.graph) for t in trajectories]
    known = [s.positions(t.positions, t.obstacle_positions) for s, t in zip(scenarios, trajectories, strict=True)]
    initial = [s.full(t.velocities[:1], 0.0)[0] for s, t in zip(scenarios, trajectories, strict=True)]
    steps = [len(k) - 1 for k in known]
    results = rollouts(model, scenarios, [k[0] for k in known], initial, steps, known, precision=precision)
    metrics = [rollout_metrics(r.positions[:, : s.n_body], t.positions, free_nodes(t), body_size(t.mesh.nodes))
               for r, s, t in zip(results, scenarios, trajectories, strict=True)]
    return {"rmse_all": float(np.mean([m["rmse_all"] for m in metrics])),
            "rel_all": float(np.mean([m["rel_all"] for m in metrics])),
            "unstable": sum(m["unstable_step"] is not None for m in metrics)}


def main() -> None:
    from bsms.data import FrameDataset
    from bsms.run import load_model, run_dataset_config, split_files
    from datagen.dataset import load

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run folder written by train.py")
    parser.add_argument("--split", default="test")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model, config, state = load_model(args.run)
    folder = Path(config.dataset.root) / run_dataset_config(args.run, config)["dataset"]
    files = split_files(folder, args.split)
    dataset = FrameDataset(files, config.graph)
    trajectories = [load(path) for path in files]
    print(f"run {args.run} (step {state['step']}), {len(files)} {args.split} trajectories, {len(dataset)} samples")
    found = {}
    for precision in PRECISIONS:
        found[precision] = {"one_step": one_step_rmse(model, dataset, precision),
                            **rollout_errors(model, config, trajectories, precision)}
        f = found[precision]
        print(f"{precision:5s} one-step RMSE {f['one_step']:.4e} m, rollout RMSE {f['rmse_all']:.4e} m "
              f"({f['rel_all']:.4f} of the body size), unstable {f['unstable']} of {len(trajectories)}")
    print(f"bf16 vs f32: one-step error x {found['bf16']['one_step'] / found['f32']['one_step']:.4f}, "
          f"rollout error x {found['bf16']['rmse_all'] / found['f32']['rmse_all']:.4f}")


if __name__ == "__main__":
    main()
