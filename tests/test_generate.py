"""python -m datagen: determinism, resume after a kill, shards, metadata.json and error messages."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from datagen.config import ConfigError
from datagen.dataset import content_digest, load
from datagen.dataset_config import load_dataset_config
from datagen.generate import generate, jobs, main, parse_shard

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "configs" / "datasets" / "disks_quick.yaml"


def _digests(folder: Path) -> dict:
    return {str(p.relative_to(folder)): content_digest(p) for p in sorted(folder.rglob("*.h5"))}


def _config(tmp_path, **over) -> Path:
    """A disks_quick variant written to tmp_path (slower frames so a kill lands mid-run)."""
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump({"extends": str(QUICK), "dataset": "small", **over}))
    return path


def test_same_index_gives_same_arrays_and_file(tmp_path):
    config = _config(tmp_path, splits={"train": 2})
    generate(config, out=tmp_path / "a", progress=False)
    generate(config, out=tmp_path / "b", workers=2, progress=False)
    a, b = _digests(tmp_path / "a"), _digests(tmp_path / "b")
    assert a == b and len(a) == 2
    ta, tb = load(tmp_path / "a/small/train/00001.h5"), load(tmp_path / "b/small/train/00001.h5")
    np.testing.assert_array_equal(ta.positions, tb.positions)
    np.testing.assert_array_equal(ta.velocities, tb.velocities)
    assert ta.config == tb.config


def test_killed_run_resumes_to_the_same_files(tmp_path):
    config = _config(tmp_path, splits={"train": 6}, output={"frames": 30})
    generate(config, out=tmp_path / "whole", progress=False)
    cmd = [sys.executable, "-m", "datagen", str(config), "--out", str(tmp_path / "cut"), "--quiet"]
    folder = tmp_path / "cut" / "small" / "train"
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not list(folder.glob("*.h5")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = sorted(p.name for p in folder.glob("*.h5"))
    assert 0 < len(done) < 6, f"the kill should land mid-run, found {done}"
    before = _digests(tmp_path / "cut")
    finished = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert finished.returncode == 0, finished.stderr
    assert f"{len(done)} already complete" in finished.stdout
    after = _digests(tmp_path / "cut")
    assert after == _digests(tmp_path / "whole")
    assert all(after[k] == v for k, v in before.items())  # complete files were kept, not redone
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]  # no temporary left behind


@pytest.mark.parametrize("n", [1, 2, 3, 5, 13])
def test_shards_are_disjoint_and_complete(n):
    dconfig = load_dataset_config(ROOT / "configs" / "datasets" / "glyphs.yaml")
    every = jobs(dconfig)
    parts = [jobs(dconfig, shard=(i, n)) for i in range(n)]
    assert sum(len(p) for p in parts) == len(every) == 1200
    assert set().union(*map(set, parts)) == set(every)


def test_sharded_run_matches_a_whole_run_and_writes_metadata(tmp_path):
    config = _config(tmp_path)
    for i in range(3):
        generate(config, out=tmp_path / "sharded", shard=(i, 3), progress=False)
        assert (tmp_path / "sharded/small/metadata.json").exists() == (i == 2)  # only once complete
    generate(config, out=tmp_path / "whole", progress=False)
    assert _digests(tmp_path / "sharded") == _digests(tmp_path / "whole")
    meta = json.loads((tmp_path / "sharded/small/metadata.json").read_text())
    assert meta["dim"] == 2 and meta["counts"] == {"train": 4, "valid": 1, "test": 1}
    assert meta["dt"] == pytest.approx(0.1) and meta["statistics_split"] == "train"
    velocities = np.concatenate([load(p).velocities.reshape(-1, 2)
                                 for p in sorted((tmp_path / "whole/small/train").glob("*.h5"))])
    np.testing.assert_allclose(meta["velocity"]["mean"], velocities.mean(0), atol=1e-12)
    np.testing.assert_allclose(meta["velocity"]["std"], velocities.std(0), rtol=1e-9)
    assert np.all(np.asarray(meta["velocity_change"]["std"]) > 0)
    assert meta["bounds"]["lower"] == [0.0, 0.0] and meta["bounds"]["upper"] == [1.0, 1.0]  # the box
    assert meta["nodes"]["train"]["min"] > 0


@pytest.mark.parametrize(("text", "message"), [
    ("3/2", "need 0 <= I < N"), ("a/b", "must look like I/N"), ("1", "must look like I/N"), ("-1/2", "need 0 <= I"),
])
def test_bad_shard_spec(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_shard(text)


@pytest.mark.parametrize("over", [
    ({"family": "disk"}, "unknown family 'disk'"),
    ({"splits": {"training": 3}}, "'splits' must map some of train, valid, test"),
    ({"splits": {"train": -1}}, "'splits.train' must be a count >= 0"),
    ({"colour": 1}, "unknown config key 'colour'; a dataset config accepts: dataset, family, output, params, ranges, redraws, retry_cfl, seed, solver, splits"),
    ({"redraws": -1}, "dataset config key 'redraws' must be an integer >= 0 (how many times a trajectory the solver "
                      "cannot run is drawn afresh), got -1"),
    ({"retry_cfl": [0.3]}, "dataset config key 'retry_cfl' = [0.3] has 0.3 after 0.3: give CFL numbers in (0, 1], "
                           "each smaller than the one before and than solver.cfl (0.3)"),
    ({"retry_cfl": [0.2, 0.2]}, "has 0.2 after 0.2"),
    ({"retry_cfl": 0.1}, "dataset config key 'retry_cfl' must be a list of numbers, got 0.1"),
    ({"ranges": {"radius": [0.3, 0.1]}}, "ranges.radius must be a number or [low, high]"),
    ({"params": {"mesh_sise": 0.1}}, "unknown config key 'params.mesh_sise'; scene 'disks' accepts: "),
])
def test_cli_reports_config_errors_without_traceback(tmp_path, capsys, over):
    over, message = over
    code = main([str(_config(tmp_path, **over)), "--out", str(tmp_path), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert err.startswith("error: ") and message in err


def test_cli_subprocess_exits_nonzero_with_one_line(tmp_path):
    run = subprocess.run([sys.executable, "-m", "datagen", str(QUICK), "--shard", "3/2"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stderr.strip() == "error: --shard 3/2: need 0 <= I < N (shards are numbered 0 to N-1)"


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_stop_request_swallowed_by_a_finalizer_still_stops_generation(tmp_path):
    """A KeyboardInterrupt raised by a signal handler inside a finalizer is printed and dropped
    by Python; the recorded request stops generation before the next trajectory or frame."""
    from datagen import interrupts

    class Finalized:
        def __del__(self):
            interrupts.request()

    class Broken:
        def __del__(self):
            raise ValueError("not an interrupt")

    seen = []
    hook = sys.unraisablehook
    sys.unraisablehook = seen.append
    try:
        interrupts.install([])  # the quiet hook, in front of ``seen``
        Finalized()  # the handler fires in __del__: the KeyboardInterrupt is swallowed, and not printed
        assert seen == [], "a recorded interrupt is not reported as an unraisable exception"
        Broken()  # any other exception in a finalizer still is
        assert [type(u.exc_value) for u in seen] == [ValueError]
    finally:
        sys.unraisablehook = hook
    try:
        assert interrupts.pending()
        with pytest.raises(KeyboardInterrupt):
            generate(QUICK, out=tmp_path, splits=["valid"], progress=False)
        assert not list(tmp_path.rglob("*.h5")), "nothing was generated"
        interrupts.clear()
        interrupts.check()  # cleared: no longer raises
    finally:
        interrupts.clear()


def test_an_unstable_trajectory_is_run_again_at_the_retry_cfl_numbers(tmp_path, monkeypatch):
    """The solver reports every run above CFL 0.12 unstable: a trajectory is retried at 0.2 (still
    unstable), then at 0.1, and its file is the run at 0.1, its config saying so; without a CFL
    number left the error names the trajectory."""
    import datagen.generate as gen
    from datagen.mpm.errors import SimulationError
    from datagen.simulation import simulate

    tried = []

    def fragile(config):
        tried.append(config["solver"]["cfl"])
        if config["solver"]["cfl"] > 0.12:
            raise SimulationError("step 3: 1 of 9 particles left the mesh")
        return simulate(config)

    monkeypatch.setattr(gen, "simulate", fragile)
    config = _config(tmp_path, splits={"train": 1}, retry_cfl=[0.2, 0.1])
    generate(config, out=tmp_path / "a", progress=False)
    assert tried == [0.3, 0.2, 0.1]
    made = load(tmp_path / "a/small/train/00000.h5")
    assert made.config["solver"]["cfl"] == 0.1
    direct = simulate({**made.config})
    np.testing.assert_array_equal(made.positions, direct.positions)
    with pytest.raises(SimulationError, match=r"^train trajectory 0 of small \(the last of 2 runs\): step 3: 1 of 9 "
                                              r"particles left the mesh$"):
        generate(_config(tmp_path, splits={"train": 1}, retry_cfl=[0.2]), out=tmp_path / "b", progress=False)


def test_a_trajectory_the_solver_cannot_run_is_drawn_afresh(tmp_path, monkeypatch):
    """Draw 0 of train trajectory 1 fails at every CFL number: it is replaced by its redraw 1 (the key
    [seed, split, index, 1]); trajectory 0 is untouched; without redraws the error stands."""
    import datagen.generate as gen
    from datagen.dataset_config import trajectory_config
    from datagen.mpm.errors import SimulationError
    from datagen.simulation import simulate

    dconfig = load_dataset_config(_config(tmp_path, splits={"train": 2}, retry_cfl=[0.1], redraws=2))
    doomed = trajectory_config(dconfig, "train", 1)["seed"]
    tried = []

    def fragile(config):
        tried.append((config["seed"], config["solver"]["cfl"]))
        if config["seed"] == doomed:
            raise SimulationError("the state became non-finite (NaN or inf)")
        return simulate(config)

    monkeypatch.setattr(gen, "simulate", fragile)
    generate(dconfig, out=tmp_path / "a", progress=False)
    redrawn = trajectory_config(dconfig, "train", 1, draw=1)
    assert redrawn["seed"] != doomed and redrawn["params"] != trajectory_config(dconfig, "train", 1)["params"]
    assert tried[1:] == [(doomed, 0.3), (doomed, 0.1), (redrawn["seed"], 0.3)]
    for index, drawn in ((1, redrawn), (0, trajectory_config(dconfig, "train", 0))):
        stored = load(tmp_path / f"a/small/train/{index:05d}.h5").config  # resolved: defaults added
        assert stored["seed"] == drawn["seed"] and {k: stored["params"][k] for k in drawn["params"]} == drawn["params"]
    with pytest.raises(SimulationError, match=r"^train trajectory 1 of small \(the last of 2 runs\): the state"):
        generate({**dconfig, "redraws": 0}, out=tmp_path / "b", progress=False)


def test_retry_cfl_is_checked_against_the_solvers_default_cfl_when_none_is_given():
    dconfig = load_dataset_config(QUICK)
    del dconfig["solver"]["cfl"]
    with pytest.raises(ConfigError, match=r"has 0.5 after 0.3: "):  # the solver's default CFL number, 0.3
        load_dataset_config({**dconfig, "retry_cfl": [0.5]})
    assert load_dataset_config({**dconfig, "retry_cfl": [0.2]})["retry_cfl"] == [0.2]
