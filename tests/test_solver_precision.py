"""The compiled substeps in float32 (Model.precision, solver.precision): the kernel, the stress
coefficients, the node sums and G2P in single precision over a float64 state, against the same
substeps in float64 -- close to single-precision round-off, not equal, thread-count invariant -- and
the vibrating bar's errors against its closed form unchanged; the config's checks; the benchmark's
float32 line."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

import datagen
from datagen.mpm import Model, advance, fused
from datagen.simulation import ConfigError, resolve_config

sys.path.insert(0, str(Path(__file__).parent))
from test_fused import CASES, case_model, gap  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
from mpm_throughput import _summary  # noqa: E402
from mpm_verification import bar_errors  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


def single(model: Model) -> Model:
    return replace(model, precision="float32")


@pytest.mark.parametrize("name", [n for n in CASES if "3d" in n] + [next(iter(CASES))])
def test_float32_substeps_stay_within_single_precision_of_float64(name):
    model, state, dt = case_model(**CASES[name])
    assert fused.applies(single(model), state)
    n = 60 if model.dim == 2 else 30
    double, float32 = advance(model, state, dt, n), advance(single(model), state, dt, n)
    apart = gap(double, float32)
    # measured over every case and mode: x 4.8e-10-6.9e-9 m, v 4.4e-9-8.1e-8 m/s, F 4.3e-9-3.9e-8 on a
    # 0.4 m block moving at up to 1.2 m/s (float32 resolves 6e-8 relative): the float32 build ran and
    # stayed at its round-off
    assert 0 < apart["x"] < 2e-8 and 0 < apart["v"] < 5e-7 and 0 < apart["F"] < 2e-7
    assert float32.x.dtype == torch.float64 and float32.step == double.step == n


@pytest.mark.parametrize("reference", ["total", "adaptive"])
def test_float32_a_ulmpm_substeps_stay_within_single_precision(reference):
    model, state, dt = case_model(**CASES["3d neo-hookean flip, folded floor, sphere"], reference=reference)
    double, float32 = advance(model, state, dt, 30), advance(single(model), state, dt, 30)
    apart = gap(double, float32)
    assert 0 < apart["x"] < 2e-8 and 0 < apart["v"] < 5e-7 and 0 < apart["F"] < 2e-7  # measured as above
    assert float32.reference.rebuilds == double.reference.rebuilds


def test_float32_substeps_do_not_depend_on_the_thread_count():
    model, state, dt = case_model(**CASES["3d neo-hookean flip, folded floor, sphere"])
    one = advance(single(model), state, dt, 20)
    torch.set_num_threads(2)  # the one_thread fixture restores the count after the test
    two = advance(single(model), state, dt, 20)
    assert all(torch.equal(getattr(one, k), getattr(two, k)) for k in ("x", "v", "F", "cell"))


def test_the_vibrating_bar_in_float32_keeps_its_errors():
    """The 2D strip (the compiled substeps run 2D and 3D): the errors against the closed form in
    float32 equal float64's to 8e-6 relative; positions differ by 1.3e-7 m on a 25 m bar."""
    runs = {p: datagen.simulate({"scene": "vibrating_bar", "params": {"dim": 2}, "solver": {"precision": p}})
            for p in ("float64", "float32")}
    errors = {p: bar_errors(t) for p, t in runs.items()}
    for key, value in errors["float64"].items():
        assert abs(errors["float32"][key] - value) < 5e-5 * abs(value), key  # measured 5e-6 to 8e-6 relative
    assert errors["float64"]["displacement_rmse_rel"] < 5e-3  # measured 4.0e-3
    apart = float(np.abs(runs["float64"].positions - runs["float32"].positions).max())
    assert 0 < apart < 1e-6  # measured 1.3e-7 m
    assert runs["float32"].config["solver"]["precision"] == "float32"


@pytest.mark.parametrize("solver, message", [
    ({"precision": "float16"}, "config key 'solver.precision' must be one of float32, float64, got 'float16'"),
    ({"precision": "float32", "dtype": "float32"},
     "config key 'solver.precision' float32 is the compiled substeps' arithmetic over a float64 state; it needs "
     "solver.dtype float64 (dtype float32 runs every step in torch)"),
])
def test_the_config_checks_the_precision(solver, message):
    with pytest.raises(ConfigError) as error:
        resolve_config({"scene": "vibrating_bar", "solver": solver})
    assert str(error.value) == message


def test_the_model_refuses_an_unknown_precision():
    model, _, _ = case_model(**CASES["3d neo-hookean flip, folded floor, sphere"])
    with pytest.raises(ValueError, match=r"^unknown precision 'half'; choose one of \['float64', 'float32'\]$"):
        replace(model, precision="half")


def test_the_benchmark_prints_the_float32_line_from_its_float32_rows():
    rows = [{"dim": 3, "kind": "umls", "particles": 1000, "particle_steps_per_s": 2.0e6},
            {"dim": 3, "kind": "umls float32", "particles": 1000, "particle_steps_per_s": 2.5e6},
            {"dim": 3, "kind": "umls float32", "particles": 10, "particle_steps_per_s": 9.0e6}]
    taichi = [{"dim": 3, "particles": 1000, "precision": "float64", "particle_steps_per_s": 4.0e6},
              {"dim": 3, "particles": 1000, "precision": "float32", "particle_steps_per_s": 4.0e6}]
    assert _summary(rows, taichi, 3) == "throughput 3D: UMLS 2.00 M/s, taichi 4.00 M/s, ratio 0.500"
    assert _summary(rows, taichi, 3, "float32") == "throughput 3D float32: UMLS 2.50 M/s, taichi 4.00 M/s, ratio 0.625"
    assert _summary(rows, taichi[:1], 3, "float32") == "throughput 3D float32: UMLS 2.50 M/s, taichi n/a M/s, ratio n/a"
    assert _summary([], [], 3, "float32") == "throughput 3D float32: UMLS n/a M/s, taichi n/a M/s, ratio n/a"


def test_the_precision_benchmark_varies_one_setting_per_run():
    from solver_precision import variants

    config = {"scene": "press3d", "params": {"mesh_size": 0.012}, "solver": {"cfl": 1.0, "precision": "float32"}}
    runs = variants(config, 0.75)
    assert list(runs) == ["float64", "float32", "dt/2", "refined"]
    assert runs["float64"]["solver"] == {"cfl": 1.0, "precision": "float64"}
    assert runs["float32"]["solver"] == {"cfl": 1.0, "precision": "float32"}
    assert runs["dt/2"]["solver"] == {"cfl": 0.5, "precision": "float64"}
    assert runs["refined"]["params"]["mesh_size"] == pytest.approx(0.009, rel=1e-15)
    assert runs["refined"]["solver"] == {"cfl": 1.0, "precision": "float64"}
    assert config["solver"]["precision"] == "float32" and config["params"]["mesh_size"] == 0.012  # left as given
