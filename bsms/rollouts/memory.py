"""Freed memory kept for reuse, so that a long inference loop does not page its arrays in anew.

glibc's malloc serves a block above its mmap threshold (128 KiB, raised as blocks are freed up
to 32 MiB) with a fresh mapping and unmaps it when freed, and gives freed memory at the top of
its heap back to the system past its trim threshold. A learned rollout allocates arrays of
megabytes per call (node products, edge inputs, a joined graph), so each call page-faults them
back in: on the press model about 9,000 page faults per call of 36,000 nodes, a quarter of the
network's time (docs/press.md at 8757482, "The mirror average in one pass"). :func:`keep_freed_memory` raises
both thresholds so that freed blocks stay in the heap and are reused without faults.

It is process-wide and acts on glibc only (elsewhere it does nothing). ``bsms.rollouts.rollout`` (every
learned rollout) and ``bsms.rollouts.solver_runs`` (the solver timed against it, on the same footing)
call it; ``BSMS_KEEP_MEMORY=0`` leaves malloc as it is. The cost: a process keeps up to
:data:`KEEP_BYTES` of freed memory it would have returned.
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform
import sys

__all__ = ["KEEP_BYTES", "keep_freed_memory"]

KEEP_BYTES = 256 << 20  # blocks up to this size come from the heap; this much freed memory is kept
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt's parameter numbers (malloc.h)


@functools.cache
def keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed blocks of up to :data:`KEEP_BYTES` for reuse (once per
    process); True where it did, False elsewhere (not glibc, or ``BSMS_KEEP_MEMORY=0``)."""
    if os.environ.get("BSMS_KEEP_MEMORY", "1") == "0" or not sys.platform.startswith("linux") \
            or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)
    mallopt = getattr(libc, "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, KEEP_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, 2 * KEEP_BYTES))
