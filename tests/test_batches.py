"""bsms.training.batches: which samples each training process draws, whole and sharded."""

import numpy as np
import pytest

from bsms.config import ConfigError
from bsms.training.batches import Batches, shard_of


def test_whole_batches_are_slices_of_a_per_epoch_permutation_split_over_processes():
    whole = Batches(23, 4, seed=7)
    per_epoch = 23 // 4
    for step in (0, 3, per_epoch, 2 * per_epoch + 1):
        epoch, k = divmod(step, per_epoch)
        expected = np.random.default_rng([7, epoch]).permutation(23)[4 * k:4 * k + 4].tolist()
        assert whole.drawn(step) == expected
    epoch = [i for step in range(per_epoch) for i in whole.drawn(step)]
    assert len(set(epoch)) == len(epoch) == 20, "an epoch draws each sample at most once"
    parts = [Batches(23, 4, seed=7, rank=r, world=2).keys(5) for r in (0, 1)]
    assert [i for i, _ in parts[0]] == whole.drawn(5)[0::2] and [i for i, _ in parts[1]] == whole.drawn(5)[1::2]
    assert parts[0][0][1] == (7, 5, whole.drawn(5)[0]), "noise keyed by (seed, step, index), as one process keys it"


def test_one_process_is_the_same_sharded_or_not():
    for step in range(12):
        assert Batches(10, 3, seed=1, shard=True).keys(step) == Batches(10, 3, seed=1).keys(step)
    assert shard_of("abcde", 0, 1, True) == list("abcde")


def test_sharded_processes_hold_disjoint_shares_and_draw_each_of_their_samples_once_an_epoch():
    files = [f"{k:05d}.h5" for k in range(7)]
    shares = [shard_of(files, r, 3, True) for r in range(3)]
    assert shares == [files[0::3], files[1::3], files[2::3]]
    assert [shard_of(files, r, 3, False) for r in range(3)] == [files] * 3
    counts = (11, 10)  # the samples of each process's share
    plans = [Batches(n, 6, seed=3, rank=r, world=2, shard=True) for r, n in enumerate(counts)]
    for plan, n in zip(plans, counts, strict=True):
        epoch = [i for step in range(n // 3) for i, _ in plan.keys(step)]
        assert len(epoch) == 3 * (n // 3) == len(set(epoch)) and max(epoch) < n
        assert all(len(plan.keys(step)) == 3 for step in range(20)), "each process draws its half of every batch"
    keys = [dict(plan.keys(4)) for plan in plans]
    assert all(key == (3, 4, r, i) for r in (0, 1) for i, key in keys[r].items()), "noise keys name the process"


def test_sharded_batches_must_split_evenly_and_fit_each_share():
    with pytest.raises(ConfigError, match=r"^config key 'train.shard' splits each batch evenly over the 2 processes; "
                                          r"set 'train.batch_size' to a multiple of 2 \(got 5\), or 'train.shard: "
                                          r"false'$"):
        Batches(40, 5, seed=0, rank=0, world=2, shard=True)
    with pytest.raises(ConfigError, match=r"^config key 'train.batch_size' \(8\) exceeds this process's share "
                                          r"\(3 samples\) of the training set$"):
        Batches(3, 8, seed=0, rank=1, world=2, shard=True)
    assert Batches(40, 5, seed=0, rank=0, world=2).size == 5, "whole batches split unevenly as before"


def test_a_share_smaller_than_the_global_batch_is_enough():
    """Sharded, a process needs batch_size / K samples, not batch_size."""
    plan = Batches(5, 8, seed=0, rank=1, world=2, shard=True)
    assert [len(plan.keys(step)) for step in range(3)] == [4, 4, 4]
    assert set(plan.drawn(0)) <= set(range(5)) and len(set(plan.drawn(0))) == 4
