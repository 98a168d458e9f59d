"""Run a few training steps of a tiny config and save the parameters (rank 0) and, per
process, the training files it holds (OUT_PT.rank<r>.json).

Used by tests/test_trainer.py, both plainly (one process) and under torchrun (several):
``python tests/ddp_worker.py CONFIG_YAML DATASET_FOLDER OUT_PT``.
"""

import json
import sys

import torch

from bsms.run import load_config
from bsms.training.trainer import Trainer


def main() -> None:
    config_path, dataset_folder, out = sys.argv[1:4]
    torch.set_num_threads(1)
    trainer = Trainer(load_config(config_path), dataset_folder=dataset_folder)
    trainer.fit()
    with open(f"{out}.rank{trainer.rank}.json", "w") as handle:
        json.dump(trainer.train_set.files, handle)
    if trainer.rank == 0:
        torch.save({k: v.clone() for k, v in trainer.model.state_dict().items()}, out)
    if trainer.world > 1:
        torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main()
