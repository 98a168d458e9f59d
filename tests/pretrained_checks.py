"""Checks shared by the tests of the committed models in ``pretrained/``.

``exported(name)``: the folder's weights are weights-only loadable, small and a BSMS-GNN's; returns the
folder and its ``dataset.json``. ``fresh_rollout``: one trajectory drawn from the exported dataset's
ranges with a seed no split uses, simulated, then predicted by the model through the code
``bsms.evaluate`` runs; returns its metrics (finite and stable checked).
"""

import json
from pathlib import Path

import numpy as np
import torch

from bsms.rollouts.learned_rollouts import learned_rollouts
from bsms.run import load_model
from datagen.dataset import load
from datagen.generate import generate

PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"
FRESH_SEED = 987_654


def exported(name: str) -> tuple[Path, dict]:
    folder = PRETRAINED / name
    weights = folder / "checkpoints" / "best.pt"
    assert weights.is_file() and weights.stat().st_size < 10 * 2**20
    state = torch.load(weights, map_location="cpu", weights_only=True)
    assert "optimizer" not in state and state["config"]["model"]["name"] == "bsms_gnn"
    return folder, json.loads((folder / "dataset.json").read_text())


def fresh_rollout(folder: Path, tmp_path: Path, frames: int | None = None) -> dict:
    dconfig = json.loads((folder / "dataset.json").read_text())
    dconfig.update(dataset="fresh", seed=FRESH_SEED, splits={"test": 1})
    if frames is not None:
        dconfig["output"] = {**dconfig["output"], "frames": frames}
    generate(dconfig, out=tmp_path, splits=["test"], workers=1, progress=False)
    trajectory = load(next((tmp_path / "fresh" / "test").glob("*.h5")))
    model, config, _ = load_model(folder)
    steps = len(trajectory.times) - 1
    (metrics, result), = learned_rollouts(model, config.graph, [trajectory], tmp_path / "cache", [steps])
    assert np.isfinite(result.positions).all() and metrics["unstable_step"] is None
    return metrics
