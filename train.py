"""Train a learned simulator: ``python train.py CONFIG [section.key=value ...] [--resume]``.

The same as ``bsms train`` (:mod:`bsms.training.train_cli`): generates the dataset the config names if
trajectories are missing, trains, validates, evaluates, and writes everything under
``<runs>/<name>/``. ``torchrun --nproc_per_node K train.py CONFIG`` trains on K processes.
"""

import sys

from bsms.training.train_cli import main

if __name__ == "__main__":
    sys.exit(main())
