"""The `expansion` scene (thesis §2.3.5): a compressed elastic body released inside a spherical container."""

from __future__ import annotations

import numpy as np
import pytest

import datagen
from datagen import shapes
from datagen.config import ConfigError

pytestmark = pytest.mark.usefixtures("one_thread")

SMALL = {"mesh_size": 0.1, "body_size": 0.08}  # 509 particles, 1850 background nodes with the extra layer


def _energy(d: dict) -> np.ndarray:
    return d["kinetic_energy"] + d["elastic_energy"] + d["gravitational_energy"]


def test_expansion_stays_inside_loses_energy_every_frame_and_comes_to_rest():
    traj = datagen.simulate({"scene": "expansion", "params": SMALL,
                             "output": {"frames": 8, "frame_interval": 0.005}})
    d = traj.diagnostics
    # Released from F = 0.75 I: all the energy (1.43e6 J) is elastic at t = 0.
    assert d["kinetic_energy"][0] == 0.0 and d["elastic_energy"][0] > 1e6
    assert np.allclose(np.linalg.norm(traj.positions[0], axis=1).max(), 0.75 * 0.9 * 0.5, rtol=1e-12)
    # Never outside the container, tolerance 0: the separating wall acts on the nodes, whose kernel support
    # reaches ~1 h into the body, so the body stops short of the wall (measured max distance 0.413 m at h = 0.1).
    distance = np.linalg.norm(traj.positions, axis=2).max()
    assert distance <= 0.5 and d["distance_max"].max() <= 0.5
    assert d["distance_max"].max() > 0.4  # it expanded to the wall
    # Total energy never rises from frame to frame (measured: the largest frame change is -80 J, a fall; within
    # a frame the explicit step's energy error moves it by up to 4% of e0 during the violent first expansion).
    energy = _energy(d)
    e0 = energy[0]
    assert np.diff(energy).max() <= 0.0
    # At rest by the end: kinetic energy 1.8e-6 of the initial energy after 0.04 s (the contact is inelastic).
    assert d["kinetic_energy"][-1] <= 1.5e-5 * e0
    assert d["contact_force"].max() > 100.0 and np.isfinite(d["contact_force"]).all()


def test_expansion_takes_any_tetrahedral_mesh_file_scaled_to_fit(tmp_path):
    path = tmp_path / "cube.vtu"
    shapes.box((2.0, 1.0, 1.0), 0.5, origin=(3.0, 3.0, 3.0)).write(path)
    traj = datagen.simulate({"scene": "expansion", "params": {**SMALL, "mesh": str(path), "extent": 0.8},
                             "output": {"frames": 1, "frame_interval": 0.002}})
    x0 = traj.positions[0]
    assert np.isclose(np.linalg.norm(x0, axis=1).max(), 0.75 * 0.8 * 0.5, rtol=1e-12)
    centre = 0.5 * (x0.min(0) + x0.max(0))  # the box's vertex-volume centroid, up to its unstructured tets
    assert np.abs(centre).max() < 0.01 and np.allclose(x0.max(0) - x0.min(0), [0.49, 0.245, 0.245], rtol=0.01)
    assert np.linalg.norm(traj.positions[-1], axis=1).max() <= 0.5


def test_expansion_names_a_bad_mesh_file(tmp_path):
    with pytest.raises(ConfigError, match="params.mesh"):
        datagen.simulate({"scene": "expansion", "params": {"mesh": str(tmp_path / "missing.msh")}})
    flat = tmp_path / "flat.vtu"
    shapes.rectangle(1.0, 1.0, 0.5).write(flat)
    with pytest.raises(ConfigError, match="tetrahedral"):
        datagen.simulate({"scene": "expansion", "params": {"mesh": str(flat)}})
