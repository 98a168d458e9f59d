"""Files for ParaView: XDMF time series of a mesh or of a run's particles, and one-frame VTU.

:func:`write_series` writes any (T, N, d) node positions on fixed cells as an XDMF time series
(the ``.xdmf`` and its ``.h5``); :func:`write_particles` writes a :class:`Trajectory`'s tracked
particles, as points, with their velocity, displacement and every per-particle diagnostic of
the run (e.g. the ``slope`` scene's ``plastic_strain`` and ``mean_stress``): a time series for
``.xdmf``, one frame for any other meshio format (``.vtu``, ``.vtk``, ...).

    traj = datagen.simulate({"scene": "slope"})
    write_particles(traj, "slope.xdmf")            # every frame
    write_particles(traj, "slope_end.vtu", frame=-1)

Every file is written atomically.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from pathlib import Path

import meshio
import numpy as np

from .atomic import atomic_path
from .trajectory import Trajectory

__all__ = ["write_series", "write_particles", "particle_fields"]

_CELL_TYPES = {1: "vertex", 2: "line", 3: "triangle", 4: "tetra"}


def _padded(values: np.ndarray, dim: int) -> np.ndarray:
    """Vectors of ``dim`` components padded to 3 (ParaView's vectors are 3D)."""
    return np.pad(values, [(0, 0)] * (values.ndim - 1) + [(0, 3 - dim)])


def _vectors(values: np.ndarray, dim: int) -> np.ndarray:
    """(N, dim) vectors padded to 3 components; other shapes as they are."""
    return _padded(values, dim) if values.ndim == 2 and values.shape[-1] == dim else values


def write_series(path, cells: np.ndarray | None, positions: np.ndarray, times: np.ndarray,
                 point_data: dict[str, np.ndarray] | None = None) -> Path:
    """XDMF time series (``path`` + its ``.h5``): the points at frame 0 with ``cells`` ((C, k)
    vertex indices; None: one vertex cell per point), and per frame point data ``position``,
    ``displacement`` (from frame 0) and every (T, N[, ...]) entry of ``point_data``."""
    path = Path(path)
    if path.suffix != ".xdmf":
        raise ValueError(f"an XDMF time series needs a .xdmf path, got {path.name!r}")
    positions = np.asarray(positions, dtype=float)
    if positions.ndim != 3 or positions.shape[-1] not in (2, 3):
        raise ValueError(f"positions must be (frames, points, 2 or 3), got shape {positions.shape}")
    if len(times) != len(positions):
        raise ValueError(f"{len(times)} times for {len(positions)} frames of positions")
    heavy = path.with_suffix(".h5")
    if heavy.exists() and (not path.exists() or not _is_xdmf_data(heavy)):
        raise ValueError(f"{heavy.name} beside {path.name} is not its XDMF data (an XDMF file keeps its arrays "
                         f"in <name>.h5 and would overwrite it): choose another name for the .xdmf")
    dim = positions.shape[-1]
    cells = np.arange(positions.shape[1])[:, None] if cells is None else np.asarray(cells)
    path.parent.mkdir(parents=True, exist_ok=True)
    # written in a private folder, then both files moved into place (the .xdmf names its .h5);
    # meshio puts the .h5 in the working folder, hence the chdir
    folder = Path(tempfile.mkdtemp(prefix=f".{path.stem}.", dir=path.parent)).resolve()
    try:
        with contextlib.chdir(folder), meshio.xdmf.TimeSeriesWriter(path.name) as writer:
            writer.write_points_cells(_padded(positions[0], dim), [(_CELL_TYPES[cells.shape[1]], cells)])
            for k, t in enumerate(times):
                data = {"position": _padded(positions[k], dim),
                        "displacement": _padded(positions[k] - positions[0], dim)}
                for name, values in (point_data or {}).items():
                    data[name] = _vectors(np.asarray(values[k]), dim)
                writer.write_data(float(t), point_data=data)
        for written in folder.iterdir():
            written.replace(path.parent / written.name)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return path


def _is_xdmf_data(path: Path) -> bool:
    """Whether ``path`` is an HDF5 file of XDMF arrays (meshio's ``data<k>`` datasets, no
    trajectory ``format_version``)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "format_version" not in f.attrs and all(name.startswith("data") for name in f)
    except OSError:
        return False


def particle_fields(trajectory: Trajectory) -> dict[str, np.ndarray]:
    """name -> (T, N[, ...]) per-particle data of a run: ``velocity`` and every diagnostic with one
    value (or vector) per tracked particle and frame."""
    frames, n = trajectory.positions.shape[:2]
    fields = {"velocity": trajectory.velocities}
    for name, values in (trajectory.diagnostics or {}).items():
        values = np.asarray(values)
        if values.ndim >= 2 and values.shape[:2] == (frames, n) and values.dtype.kind in "fiub":
            fields[name] = values.astype(float)
    return fields


def write_particles(trajectory: Trajectory, path, frame: int | None = None) -> Path:
    """The run's tracked particles as points with :func:`particle_fields`: every frame as an XDMF
    time series when ``path`` ends in ``.xdmf`` (``frame`` must then be None), else frame ``frame``
    (default the last) in the format meshio infers from the suffix (``.vtu``, ``.vtk``, ...)."""
    path = Path(path)
    fields = particle_fields(trajectory)
    positions = trajectory.positions
    if path.suffix == ".xdmf":
        if frame is not None:
            raise ValueError("an .xdmf particle file holds every frame: leave frame=None, or write one frame "
                             "to a .vtu")
        return write_series(path, None, positions, trajectory.times, fields)
    k = len(positions) - 1 if frame is None else frame
    if not -len(positions) <= k < len(positions):
        raise ValueError(f"frame {frame} is out of range: the run has {len(positions)} frames (0 to "
                         f"{len(positions) - 1})")
    dim = positions.shape[-1]
    data = {"displacement": _padded(positions[k] - positions[0], dim),
            **{name: _vectors(values[k], dim) for name, values in fields.items()}}
    mesh = meshio.Mesh(_padded(positions[k], dim), [("vertex", np.arange(len(positions[k]))[:, None])],
                       point_data=data)
    with atomic_path(path, suffix=path.suffix) as tmp:
        mesh.write(tmp)
    return path
