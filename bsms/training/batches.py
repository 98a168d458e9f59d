"""Which training samples each process draws at each step (:class:`bsms.training.trainer.Trainer`).

Whole (``train.shard: false``, the default): every process holds every training trajectory, and
the samples of step ``s`` are a slice of a per-epoch permutation of all of them, a function of
(seed, s) only. Launched with ``torchrun --nproc_per_node K``, process r takes every K-th sample
of that global batch, so K processes update exactly as one process does.

Sharded (``train.shard: true``): process r of K holds only the training trajectories r, r + K,
r + 2K, ... (each with its mirror image), so the training set's memory is divided by K -- a
data set too large to hold K times fits. Each process draws ``batch_size / K`` samples per step
from a per-epoch permutation of its own samples, a function of (seed, r, s): every sample of a
process is drawn once per epoch of that process, and each global batch takes the same number
from every share. The updates are then not those of one process (the batch is drawn per share),
but they are again a function of the seed and the step only, so a resumed run continues
exactly. With one process, ``train.shard`` changes nothing.

A sample's noise is drawn from its key, (seed, s, index) whole or (seed, s, r, index) sharded,
so it does not depend on which data-loading worker builds the sample.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from bsms.config import ConfigError

__all__ = ["Batches", "shard_of"]


def shard_of(items: Sequence, rank: int, world: int, shard: bool) -> list:
    """The training files process ``rank`` of ``world`` holds: every ``world``-th from ``rank``
    when sharded (and more than one process), all of them otherwise."""
    return list(items[rank::world]) if shard and world > 1 else list(items)


class Batches:
    """The sample indices (into the process's own training set) and noise keys of each step.

    n_samples: how many samples this process holds; batch_size: the global batch
    (``train.batch_size``); sharded batches need it divisible by ``world``. source: where the
    samples come from, for the error when they are fewer than a batch.
    """

    def __init__(self, n_samples: int, batch_size: int, seed: int, rank: int = 0, world: int = 1,
                 shard: bool = False, source: str = "the training set"):
        self.sharded = bool(shard and world > 1)
        if self.sharded and batch_size % world:
            raise ConfigError(f"config key 'train.shard' splits each batch evenly over the {world} processes; set "
                              f"'train.batch_size' to a multiple of {world} (got {batch_size}), or 'train.shard: "
                              "false'")
        self.size = batch_size // world if self.sharded else batch_size
        if n_samples < self.size:
            where = (f"this process's share ({n_samples} samples) of the training set" if self.sharded
                     else f"the {n_samples} training samples of {source}")
            raise ConfigError(f"config key 'train.batch_size' ({batch_size}) exceeds {where}")
        self.n, self.seed, self.rank, self.world = int(n_samples), int(seed), int(rank), int(world)

    def drawn(self, step: int) -> list[int]:
        """The samples drawn at ``step`` from the permutation this process follows: the global batch
        when whole, this process's own batch when sharded."""
        epoch, k = divmod(step, self.n // self.size)
        stream = [self.seed, epoch, self.rank] if self.sharded else [self.seed, epoch]
        order = np.random.default_rng(stream).permutation(self.n)
        return [int(i) for i in order[k * self.size:(k + 1) * self.size]]

    def keys(self, step: int) -> list[tuple[int, tuple[int, ...]]]:
        """(sample index, noise key) of each sample this process trains on at ``step``."""
        if self.sharded:
            return [(i, (self.seed, step, self.rank, i)) for i in self.drawn(step)]
        return [(i, (self.seed, step, i)) for i in self.drawn(step)[self.rank::self.world]]
