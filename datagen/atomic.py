"""Atomic file writes: write beside the target under a temporary name, rename when complete."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path"]

_UMASK = os.umask(0)  # read once (setting it back at once); mkstemp would otherwise leave 0600 files
os.umask(_UMASK)


@contextmanager
def atomic_path(path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write to; rename it to ``path`` on success.

    On an exception the temporary file is removed and ``path`` is untouched, so readers never
    see a partial file. Temporary names are ``.<stem>.<random><suffix>`` in the same folder
    (pass the target's suffix when a writer infers the format from it). The final file gets
    the usual permissions (0666 less the umask).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
