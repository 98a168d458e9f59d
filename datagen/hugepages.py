"""Whether numpy asks the kernel for transparent huge pages, chosen from the kernel's policy.

numpy marks every large array ``madvise(MADV_HUGEPAGE)``. Where the kernel's THP ``defrag``
setting is ``madvise`` or ``defer+madvise``, a page fault in such a region compacts memory
synchronously until a 2 MiB page is free. On a machine whose memory is fragmented (a VM that
has run for hours, a page cache full of datasets) that stall dominates code that allocates
large transient arrays: building a 1M-tetrahedron bi-stride hierarchy measured 6.5 s with
numpy's default against 4.3 s without it, and single runs of 14-22 s, nearly all of it system
time. Plain 4 KiB pages cost a few percent in TLB misses at worst, so bsms turns numpy's
advice off on such kernels when :mod:`datagen` is imported.

``BSMS_HUGEPAGES=numpy`` keeps numpy's default; an explicit ``NUMPY_MADVISE_HUGEPAGE`` (numpy's
own switch) is always respected.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["DEFRAG", "stalls_on_fault", "configure"]

DEFRAG = Path("/sys/kernel/mm/transparent_hugepage/defrag")
_STALLING = {"madvise", "defer+madvise"}  # direct compaction on faults in madvised regions


def stalls_on_fault(defrag_text: str) -> bool:
    """True when the kernel's THP defrag setting (the sysfs line, the choice in brackets,
    e.g. ``always defer defer+madvise [madvise] never``) compacts synchronously on a fault in
    a region marked MADV_HUGEPAGE."""
    chosen = [word[1:-1] for word in defrag_text.split() if word.startswith("[") and word.endswith("]")]
    return bool(chosen) and chosen[0] in _STALLING


def configure(environ=os.environ, defrag: Path = DEFRAG) -> bool:
    """Turn numpy's huge-page advice off where it stalls (see the module docstring).

    Returns whether numpy's advice is on afterwards. Leaves it alone when the user chose:
    ``BSMS_HUGEPAGES=numpy`` or ``NUMPY_MADVISE_HUGEPAGE`` set.
    """
    current = np._core.multiarray._get_madvise_hugepage()
    if environ.get("BSMS_HUGEPAGES") == "numpy" or "NUMPY_MADVISE_HUGEPAGE" in environ:
        return current
    try:
        text = defrag.read_text()
    except OSError:  # not Linux, or no THP: nothing to choose
        return current
    if current and stalls_on_fault(text):
        np._core.multiarray._set_madvise_hugepage(False)
        return False
    return current
