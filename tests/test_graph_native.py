"""The compiled bi-stride loops (bsms/graph/native.py) against the scipy/csgraph code they replace."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.sparse as sp
from graph_meshes import shape_mesh, side_by_side
from scipy.sparse import csgraph

from bsms.graph import bistride_levels, native
from bsms.graph import seeding as seeding_module
from bsms.graph.bfs import bfs_depths, off_diagonal_pattern
from bsms.graph.contact import coarse_images
from bsms.graph.pooling import bistride_pool, closed_rows


@pytest.fixture
def scipy_only(monkeypatch):
    """Run a callable with the compiled loops switched off (BSMS_NATIVE=0)."""

    def run(function, *args, **kwargs):
        with monkeypatch.context() as patch:
            patch.setenv("BSMS_NATIVE", "0")
            native.library.cache_clear()
            try:
                return function(*args, **kwargs)
            finally:
                native.library.cache_clear()

    return run


def _levels_of(mesh, count: int):
    """(closed rows, scipy's pooled adjacency) of the first ``count`` poolings from node 0's component seeds."""
    adjacency = mesh.adjacency()
    n_components, labels = csgraph.connected_components(adjacency, directed=False)
    out = []
    for _ in range(count):
        seeds = np.array([np.flatnonzero(labels == c)[0] for c in range(n_components)])
        kept = bistride_pool(adjacency, labels, seeds)
        closed = closed_rows(adjacency, kept)
        pooled = off_diagonal_pattern(closed @ closed.T)
        out.append((closed, pooled))
        adjacency, labels = pooled, labels[kept]
    return out


@pytest.mark.parametrize("parts", [("box",), ("sphere", "box"), ("glyph", "annulus")])
@pytest.mark.parametrize("dense", [False, True])
def test_pooled_adjacency_equals_scipys_product(parts, dense):
    mesh = side_by_side([shape_mesh(kind, 0.06) for kind in parts], 0.2)
    for closed, expected in _levels_of(mesh, 4):
        got = native.pooled_adjacency(closed, dense=dense)
        assert got.shape == expected.shape
        assert np.array_equal(got.indptr, expected.indptr)
        assert np.array_equal(got.indices, expected.indices)
        assert np.all(got.data == 1.0)


@pytest.mark.parametrize("n_sources", [1, 5, 64, 70])
def test_multi_source_sums_equal_one_search_per_source(n_sources):
    adjacency = shape_mesh("box", 0.09).adjacency()
    sources = np.random.default_rng(n_sources).choice(adjacency.shape[0], n_sources, replace=False)
    node_sums, source_sums = native.multi_source_sums(adjacency, sources)
    depths = np.stack([bfs_depths(adjacency, source) for source in sources])
    assert np.array_equal(node_sums, depths.sum(axis=0))
    assert np.array_equal(source_sums, depths.sum(axis=1))


def _same(a, b) -> None:
    for x, y in zip(a.levels, b.levels, strict=True):
        for name in ("kept", "edge_index", "node_weights", "seeds"):
            assert np.array_equal(getattr(x, name), getattr(y, name)), name
        for kind in ("down", "up") if x.down is not None else ():
            for name in ("rows", "cols", "weights"):
                assert np.array_equal(getattr(getattr(x, kind), name), getattr(getattr(y, kind), name))


@pytest.mark.parametrize("parts", [("box", "sphere"), ("glyph", "square with holes")])
def test_compiled_hierarchy_equals_the_scipy_one(parts, scipy_only, monkeypatch):
    mesh = side_by_side([shape_mesh(kind, 0.06) for kind in parts], 0.2)
    monkeypatch.setattr(seeding_module, "EXACT_MIN_AVE_WORK", 100)  # every component by the sampled search
    for seeding in ("min_ave", "close_center"):
        compiled = bistride_levels(mesh, levels=5, seeding=seeding)
        _same(compiled, scipy_only(bistride_levels, mesh, levels=5, seeding=seeding))


def test_a_failing_compiler_warns_once_and_scipy_builds_the_same_levels(monkeypatch, tmp_path):
    mesh = shape_mesh("sphere", 0.09)
    expected = bistride_levels(mesh, levels=4)
    native.library.cache_clear()
    monkeypatch.setenv("BSMS_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "false")
    try:
        with pytest.warns(RuntimeWarning, match=r"could not build the compiled bi-stride loops \(false failed"):
            assert native.library() is None
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # cached: no second warning
            _same(bistride_levels(mesh, levels=4), expected)
        assert not list(tmp_path.rglob("*.so"))
    finally:
        native.library.cache_clear()


def test_compiled_coarse_images_equal_numpys_bit_for_bit(scipy_only, monkeypatch):
    """Contact pairs one level down (eq. 4.1): the compiled pass returns numpy's array exactly --
    symmetric and one-directional pairs, sorted or not, repeats, self-pairs, no pairs -- and grows
    its reused output buffer when a call needs more room."""
    rng = np.random.default_rng(5)
    monkeypatch.setattr(native, "_OUT", [np.empty((2, 3), dtype=np.int64)])
    for trial in range(300):
        n, m = int(rng.integers(1, 60)), int(rng.integers(1, 30))
        reach = sp.csr_matrix((rng.random((n, m)) < rng.uniform(0.02, 0.5)).astype(float))
        reach.sort_indices()
        pairs = rng.integers(0, n, (2, int(rng.integers(0, 3 * n))))
        if trial % 2:
            pairs = np.concatenate([pairs, pairs[::-1]], axis=1)
        if trial % 3 == 0:
            pairs = pairs[:, np.lexsort((pairs[1], pairs[0]))]
        compiled = coarse_images(pairs, reach)
        expected = scipy_only(coarse_images, pairs, reach)
        assert compiled.dtype == expected.dtype == np.int64 and compiled.shape == expected.shape
        assert np.array_equal(compiled, expected), trial
    assert native._OUT[0].shape[1] > 3
