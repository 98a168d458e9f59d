"""Particle files for ParaView (datagen.export): what is written reads back exactly."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

import datagen
import datagen.dataset
from datagen.export import particle_fields, write_particles, write_series

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def slope():
    return datagen.simulate({"scene": "slope", "params": {"mesh_size": 1.0, "particle_spacing": 0.5},
                             "output": {"frames": 2, "frame_interval": 0.05}})


def test_particle_fields_are_the_per_particle_diagnostics(slope):
    fields = particle_fields(slope)
    # per-particle diagnostics only: runout and plastic_strain_max are one value per frame
    assert set(fields) == {"velocity", "plastic_strain", "mean_stress"}
    assert np.array_equal(fields["plastic_strain"], slope.diagnostics["plastic_strain"])
    assert fields["plastic_strain"][-1].max() > 0.0


def test_xdmf_time_series_of_particles_reads_back(tmp_path, slope):
    path = write_particles(slope, tmp_path / "out" / "slope.xdmf")
    assert path.is_file() and (path.parent / "slope.h5").is_file()
    assert sorted(p.name for p in path.parent.iterdir()) == ["slope.h5", "slope.xdmf"]  # no leftovers
    n = slope.positions.shape[1]
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        assert np.array_equal(points[:, :2], slope.positions[0]) and np.all(points[:, 2] == 0)
        assert cells[0].type == "vertex" and len(cells[0].data) == n
        assert reader.num_steps == len(slope.times)
        for k in range(reader.num_steps):
            t, data, _ = reader.read_data(k)
            assert t == pytest.approx(slope.times[k], rel=1e-12)
            assert np.array_equal(data["position"][:, :2], slope.positions[k])
            assert np.array_equal(data["displacement"][:, :2], slope.positions[k] - slope.positions[0])
            assert np.array_equal(data["velocity"][:, :2], slope.velocities[k])
            assert np.array_equal(data["plastic_strain"], slope.diagnostics["plastic_strain"][k])
            assert np.array_equal(data["mean_stress"], slope.diagnostics["mean_stress"][k])


def test_one_frame_vtu_reads_back(tmp_path, slope):
    path = write_particles(slope, tmp_path / "end.vtu")
    mesh = meshio.read(path)
    assert np.array_equal(mesh.points[:, :2], slope.positions[-1])
    assert np.array_equal(mesh.point_data["plastic_strain"], slope.diagnostics["plastic_strain"][-1])
    first = meshio.read(write_particles(slope, tmp_path / "first.vtu", frame=0))
    assert np.array_equal(first.points[:, :2], slope.positions[0]) and not first.point_data["displacement"].any()


def test_bad_requests_name_the_fix(tmp_path, slope):
    with pytest.raises(ValueError, match=r"^an \.xdmf particle file holds every frame: leave frame=None"):
        write_particles(slope, tmp_path / "a.xdmf", frame=1)
    with pytest.raises(ValueError, match=r"^frame 3 is out of range: the run has 3 frames \(0 to 2\)$"):
        write_particles(slope, tmp_path / "a.vtu", frame=3)
    with pytest.raises(ValueError, match=r"^an XDMF time series needs a \.xdmf path, got 'a\.vtu'$"):
        write_series(tmp_path / "a.vtu", None, slope.positions, slope.times)
    assert not any(tmp_path.iterdir())


def test_an_xdmf_never_overwrites_a_trajectory_file_of_its_name(tmp_path, slope):
    trajectory_file = datagen.dataset.save(tmp_path / "run.h5", slope)
    before = trajectory_file.read_bytes()
    with pytest.raises(ValueError, match=r"^run\.h5 beside run\.xdmf is not its XDMF data .*choose another name"):
        write_particles(slope, tmp_path / "run.xdmf")
    assert trajectory_file.read_bytes() == before and not (tmp_path / "run.xdmf").exists()
    write_particles(slope, tmp_path / "series.xdmf")
    write_particles(slope, tmp_path / "series.xdmf")  # its own data: rewritten
