"""numpy's huge-page advice follows the kernel's THP defrag policy (datagen.hugepages)."""

import numpy as np
import pytest

from datagen import hugepages

_SETTER = np._core.multiarray._set_madvise_hugepage


@pytest.fixture
def advice_on():
    before = _SETTER(True)
    yield
    _SETTER(before)


@pytest.mark.parametrize(
    "line, stalls",
    [
        ("always defer defer+madvise [madvise] never\n", True),
        ("always defer [defer+madvise] madvise never\n", True),
        ("[always] defer defer+madvise madvise never\n", False),  # every fault compacts: advice changes nothing
        ("always [defer] defer+madvise madvise never\n", False),
        ("always defer defer+madvise madvise [never]\n", False),
        ("", False),
    ],
)
def test_defrag_line(line, stalls):
    assert hugepages.stalls_on_fault(line) is stalls


def test_turned_off_only_where_it_stalls(advice_on, tmp_path):
    defrag = tmp_path / "defrag"
    defrag.write_text("always defer defer+madvise madvise [never]\n")
    assert hugepages.configure({}, defrag) is True and _SETTER(True) is True
    defrag.write_text("always defer defer+madvise [madvise] never\n")
    assert hugepages.configure({}, defrag) is False and _SETTER(False) is False


@pytest.mark.parametrize("environ", [{"BSMS_HUGEPAGES": "numpy"}, {"NUMPY_MADVISE_HUGEPAGE": "1"}])
def test_user_choice_wins(advice_on, tmp_path, environ):
    defrag = tmp_path / "defrag"
    defrag.write_text("always defer defer+madvise [madvise] never\n")
    assert hugepages.configure(environ, defrag) is True and _SETTER(True) is True


def test_no_sysfs_leaves_numpy_alone(advice_on, tmp_path):
    assert hugepages.configure({}, tmp_path / "missing") is True
