"""CUDA smoke test: the solver, training steps and a rollout on a GPU give what the CPU gives.

Runs wherever CUDA exists; skipped only for lack of the hardware. Everything starts from the
same data and weights as a CPU run, so the comparisons check that no tensor is left behind
on the CPU and that nothing changes meaning on the GPU.
"""

import copy

import numpy as np
import pytest
import torch
from conftest import tiny_run_config
from torch_geometric.data import Batch

from bsms.data import Scenario
from bsms.rollouts.rollout import body_size, rollout
from bsms.run import load_config, load_model, prepare_dataset, split_files
from bsms.training.trainer import Trainer
from datagen import simulate
from datagen.dataset import load

DEVICE = "cuda"
pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def trainer_on(device: str, tiny_dataset, runs, **train) -> Trainer:
    config = load_config(tiny_run_config(tiny_dataset, runs, name=f"on_{device}",
                                         train={"device": device, "steps": 4, **train}))
    return Trainer(config, dataset_folder=prepare_dataset(config, progress=False))


def test_solver_frames_on_cuda_match_the_stored_cpu_run(tiny_dataset):
    _, data_root = tiny_dataset
    stored = load(sorted((data_root / "tiny_glyphs" / "test").glob("*.h5"))[0])
    config = copy.deepcopy(stored.config)
    config["output"] = {**config["output"], "frames": 2}
    config["solver"] = {**config["solver"], "device": DEVICE}
    on_gpu = simulate(config)
    assert on_gpu.positions.shape == stored.positions[:3].shape
    # float64 on both; only the order of sums differs (atomic adds on the GPU)
    np.testing.assert_allclose(on_gpu.positions, stored.positions[:3], rtol=0,
                               atol=1e-9 * body_size(stored.mesh.nodes))


@pytest.mark.parametrize("amp", [False, True])
def test_training_steps_on_cuda_match_the_cpu(tiny_dataset, tmp_path, amp):
    cpu = trainer_on("cpu", tiny_dataset, tmp_path / "cpu")
    gpu = trainer_on(DEVICE, tiny_dataset, tmp_path / "gpu", amp=amp)
    assert all(t.device.type == torch.device(DEVICE).type for t in [*gpu.model.parameters(), *gpu.model.buffers()])
    batch = Batch.from_data_list([cpu.train_set[(i, (0, 0, i))] for i in range(2)])
    # the first step's loss and (clipped) gradients, from the same weights and batch. float32:
    # the GPU differs in the last bits (sums in another order; measured 6e-7 of a gradient's
    # scale on an H200). bfloat16 autocast keeps ~3 significant digits: single gradient entries
    # move by up to ~20% of their tensor's scale on a CPU as on a GPU (measured), so the whole
    # gradient is compared (a CPU's bfloat16 errs 2.3% of its norm; loss 1e-3 relative)
    loss_gpu, loss_cpu = gpu.train_step(batch.clone()), cpu.train_step(batch.clone())
    assert loss_gpu == pytest.approx(loss_cpu, rel=5e-3 if amp else 1e-6)
    if amp:
        grads = [torch.cat([p.grad.cpu().ravel() for p in m.parameters()]) for m in (gpu.model, cpu.model)]
        assert float((grads[0] - grads[1]).norm() / grads[1].norm()) < 0.1
    else:
        for (name, p_cpu), p_gpu in zip(cpu.model.named_parameters(), gpu.model.parameters(), strict=True):
            scale = float(p_cpu.grad.abs().max())
            torch.testing.assert_close(p_gpu.grad.cpu(), p_cpu.grad, rtol=1e-4, atol=5e-6 * scale,
                                       msg=lambda m, name=name: f"gradient of {name}: {m}")
    for name, value in cpu.model.state_dict().items():
        if "normalizer" in name:  # statistics are float64 sums of the same inputs
            torch.testing.assert_close(gpu.model.state_dict()[name].cpu(), value, rtol=1e-6, atol=0)
    assert gpu.validate() == pytest.approx(cpu.validate(), rel=3e-2 if amp else 1e-4)
    gpu.fit()  # the loop, validation and checkpoints on the GPU
    model, _, state = load_model(gpu.run_dir, "latest")  # read back on the CPU, weights_only
    assert state["step"] == 4 and all(p.device.type == "cpu" for p in model.parameters())


def test_rollout_on_cuda_matches_the_cpu(tiny_dataset, tmp_path):
    trainer = trainer_on("cpu", tiny_dataset, tmp_path)
    trainer.fit()
    trajectory = load(split_files(trainer.dataset_folder, "test")[0])
    scenario = Scenario.from_trajectory(trajectory, trainer.config.graph)
    known = scenario.full(trajectory.positions)
    start = (known[0], scenario.full(trajectory.velocities[:1], 0.0)[0])
    results = {}
    for device in ("cpu", DEVICE):
        model, _, _ = load_model(trainer.run_dir, "latest", device=device)
        results[device] = rollout(model, scenario, *start, len(known) - 1, known, device=device, precision="f32")
    assert results[DEVICE].finite
    np.testing.assert_allclose(results[DEVICE].positions, results["cpu"].positions, rtol=0,
                               atol=1e-5 * body_size(trajectory.mesh.nodes))
