"""The BSMS-GNN authors' conversion of DeepMind's datasets: one HDF5 file per trajectory,
``<root>/<dataset>/<split>/<index>.h5``, holding one dataset per field with the frames first,
``(T, N, F)`` (static fields such as ``mesh_pos``, ``cells`` and ``node_type`` repeated for
every frame).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bsms.datasets.errors import SourceError

__all__ = ["read_trajectory", "read_split"]


def read_trajectory(path, fields=None) -> dict[str, np.ndarray]:
    """``{field: (T, ...) array}`` of one authors' file (``fields``: these only, default all)."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise SourceError(path, "the file does not exist")
    if not h5py.is_hdf5(path):
        raise SourceError(path, "not an HDF5 file: the authors' conversion writes one .h5 per trajectory")
    try:
        with h5py.File(path, "r") as f:
            names = list(f) if fields is None else list(fields)
            missing = [name for name in names if name not in f]
            if missing:
                raise SourceError(path, f"the file lacks this field (it holds {', '.join(sorted(f))})",
                                  field=missing[0])
            out = {name: f[name][()] for name in names}
    except OSError as exc:
        raise SourceError(path, f"truncated or corrupt ({exc}); convert it again") from None
    frames = {name: a.shape[0] if a.ndim else 0 for name, a in out.items()}
    if len(set(frames.values())) > 1:
        name = max(frames, key=lambda k: frames[k] != next(iter(frames.values())))
        raise SourceError(path, f"{frames[name]} frames where the other fields have "
                                f"{next(iter(frames.values()))}", field=name)
    return out


def read_split(folder, split: str, fields=None) -> Iterator[tuple[int, dict]]:
    """(index, trajectory) of every ``<index>.h5`` in ``folder/split``, in index order."""
    files = sorted((Path(folder) / split).glob("*.h5"), key=lambda p: (not p.stem.isdigit(), int(p.stem)
                                                                       if p.stem.isdigit() else 0, p.stem))
    if not files:
        raise SourceError(Path(folder) / split, "no .h5 trajectory files there")
    for path in files:
        if not path.stem.isdigit():
            raise SourceError(path, "authors' files are named <index>.h5")
        yield int(path.stem), read_trajectory(path, fields)
