"""Disk cache for bi-stride hierarchies: one ``.npz`` per key, written atomically, read safely.

The key is a sha256 of everything the hierarchy depends on: the graph (canonical CSR of the
level-0 adjacency, so a mesh and its edge list give the same key), the level rule, the
seeding and its random seed, the transition option, the coarse-degree cap where one is set (an
uncapped hierarchy's key is the one it had before the cap existed) and, for ``close_center``
only, the node positions. Files are written to a temporary name and renamed (``os.replace``),
so readers never see half a file, and read with ``allow_pickle=False``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from datagen.atomic import atomic_path

__all__ = ["FORMAT_VERSION", "hierarchy_key", "cache_path", "write_npz_atomic", "read_npz"]

FORMAT_VERSION = 1


def hierarchy_key(adjacency: sp.csr_matrix, positions: np.ndarray | None, options: dict) -> str:
    """sha256 hex digest of (format version, graph, options, positions if given).

    adjacency: (N, N) CSR with sorted indices; positions: (N, d) or None when the result does
    not depend on them; options: JSON-serialisable settings (levels, seeding, ...).
    """
    digest = hashlib.sha256()
    digest.update(json.dumps({"format": FORMAT_VERSION, **options}, sort_keys=True).encode())
    digest.update(np.int64(adjacency.shape[0]).tobytes())
    digest.update(np.ascontiguousarray(adjacency.indptr, dtype=np.int64).tobytes())
    digest.update(np.ascontiguousarray(adjacency.indices, dtype=np.int64).tobytes())
    if positions is not None:
        digest.update(np.ascontiguousarray(positions, dtype=np.float64).tobytes())
    return digest.hexdigest()


def cache_path(cache_dir, key: str) -> Path:
    """Where the hierarchy with ``key`` lives inside ``cache_dir``."""
    return Path(cache_dir) / f"bistride-{key[:40]}.npz"


def write_npz_atomic(path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as an uncompressed npz at ``path`` via a temporary file and a rename."""
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez(handle, **arrays)


def read_npz(path) -> dict[str, np.ndarray]:
    """All arrays of an npz file, loaded eagerly and without pickle."""
    with np.load(Path(path), allow_pickle=False) as data:
        return {name: data[name] for name in data.files}
