"""benchmarks/ensemble.py: the mean of runs' predicted positions, scored as each run is."""

import sys
from pathlib import Path

import pytest
from conftest import tiny_run_config

from bsms.run import load_config, prepare_dataset
from bsms.training.trainer import Trainer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import ensemble  # noqa: E402


def train(dataset, runs, name, seed):
    config = load_config(tiny_run_config(dataset, runs, name=name, train={"steps": 4, "valid_every": 4,
                                                                          "checkpoint_every": 4, "seed": seed}))
    Trainer(config, dataset_folder=prepare_dataset(config, progress=False)).fit()
    return str(runs / name)


def test_the_mean_of_one_run_twice_is_that_run_and_of_two_runs_is_scored_alike(tiny_dataset, tmp_path, capsys):
    first, second = train(tiny_dataset, tmp_path, "a", 0), train(tiny_dataset, tmp_path, "b", 1)
    assert ensemble.main([first, first, "--trajectories", "2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    row_a, row_mean, last = lines[2], lines[4], lines[-1]
    assert row_a.split("|")[2:] == row_mean.split("|")[2:]  # identical predictions: the mean is each
    each = float(row_a.split("|")[2].split()[0])
    assert last == f"ensemble: vs at rest {each:.3g} of the mean of 2 runs, each {each:.3g}-{each:.3g}"
    assert ensemble.main([first, second, "--trajectories", "2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    runs = [float(line.split("|")[2].split()[0]) for line in lines[2:4]]
    mean = float(lines[4].split("|")[2].split()[0])
    assert runs[0] != runs[1]  # two seeds, two models
    # the RMSE of the mean of predictions is at most the mean of their RMSEs (Minkowski), per trajectory
    assert mean <= sum(runs) / 2 + 2e-3  # printed to 3 digits
    with pytest.raises(SystemExit):
        ensemble.main([first])


def test_one_run_scored_on_another_folder_matches_its_rows_on_its_own(tiny_dataset, tiny_folder, tmp_path, capsys):
    import shutil

    from bsms.run import split_files

    first = train(tiny_dataset, tmp_path, "a", 0)
    assert ensemble.main([first, first, "--trajectories", "2"]) == 0
    own = capsys.readouterr().out.strip().splitlines()[2]
    other = tmp_path / "elsewhere"
    (other / "test").mkdir(parents=True)
    for path in split_files(tiny_folder, "test")[:2]:
        shutil.copy(path, other / "test" / path.name)
    assert ensemble.main([first, "--data", str(other)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[2] == own and len(lines) == 4
    assert lines[-1] == f"ensemble: vs at rest {float(own.split('|')[2].split()[0]):.3g} of 1 run on {other}"


def test_weighted_means_run_from_the_first_run_to_the_others(tiny_dataset, tmp_path, capsys):
    """--weights 1 scores the first run's rollouts, 0 the second's, 0.5 the plain mean."""
    first, second = train(tiny_dataset, tmp_path, "a", 0), train(tiny_dataset, tmp_path, "b", 1)
    assert ensemble.main([first, second, "--trajectories", "2", "--weights", "1", "0", "0.5"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    cells = [line.split("|")[2:] for line in lines[2:8]]
    assert lines[5].startswith("| weight 1 on a |") and cells[3] == cells[0]
    assert lines[6].startswith("| weight 0 on a |") and cells[4] == cells[1]
    assert lines[7].startswith("| weight 0.5 on a |") and cells[5] == cells[2]
    with pytest.raises(SystemExit):
        ensemble.main([first, second, "--weights", "1.5"])
    assert capsys.readouterr().err.strip().endswith("error: --weights must lie in [0, 1], got [1.5]")
