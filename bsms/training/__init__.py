"""Training a learned simulator: ``python train.py CONFIG`` (= ``bsms train``).

- :mod:`bsms.training.train_cli`: the command: data, hierarchies, training, evaluation;
- :mod:`bsms.training.trainer`: the resumable, multi-process :class:`~bsms.training.trainer.Trainer`;
- :mod:`bsms.training.batches`: which samples each process draws at each step;
- :mod:`bsms.training.unroll`: multi-step (pushforward) training;
- :mod:`bsms.training.validation`: what training validates on;
- :mod:`bsms.training.training_log`: ``metrics.csv`` and TensorBoard event files.

What training shares with the tools that read a finished run (the config, the run folder, the
model) is :mod:`bsms.run`'s.
"""
