"""The embedding's rows applied by compiled loops against scipy's products."""

import numpy as np
import pytest

from knitfem.lod.rows import EmbeddingRows


@pytest.fixture
def rows():
    """Rows of 32 weights on unsorted columns, some repeated in a row (a
    periodic volume's wrap round lists a column twice)."""
    rng = np.random.default_rng(0)
    cols = rng.integers(0, 50, (400, 32))
    cols[:, 5] = cols[:, 9]
    return cols, rng.standard_normal(cols.shape), 50


def test_compiled_rows_are_scipys_products(rows):
    cols, vals, n = rows
    R, ref = EmbeddingRows(cols, vals, n), EmbeddingRows(cols, vals, n, compiled=False)
    rng = np.random.default_rng(1)
    a, g = rng.standard_normal((n, 3)), rng.standard_normal((len(cols), 3))
    # measured 0 and 0 (the same sums; the bound allows another order)
    assert np.allclose(R @ a, ref @ a, rtol=0, atol=1e-14 * np.abs(ref @ a).max())
    assert np.allclose(R.T @ g, ref.T @ g, rtol=0, atol=1e-14 * np.abs(ref.T @ g).max())
    dense = np.zeros((len(cols), n))
    np.add.at(dense, (np.arange(len(cols))[:, None], cols), vals)
    assert np.allclose(ref @ a, dense @ a, rtol=0, atol=1e-13)


def test_a_subset_of_rows_applies_those_rows(rows):
    cols, vals, n = rows
    R = EmbeddingRows(cols, vals, n)
    a = np.random.default_rng(2).standard_normal((n, 3))
    some = np.array([3, 7, 7, 399])
    assert np.array_equal(R.rows(some) @ a, (R @ a)[some])


def test_compiled_add_at_is_bincounts():
    """values[pos] += x with repeated positions summed and those at the end
    dropped, as numpy's bincount adds them."""
    from knitfem.lod.rows import add_at

    rng = np.random.default_rng(3)
    pos = rng.integers(0, 101, (50, 9))                 # 100: dropped
    x = rng.standard_normal(pos.shape)
    a, b = np.ones(100), np.ones(100)
    add_at(a, pos, x)
    add_at(b, pos, x, compiled=False)
    assert (pos == 100).any() and len(np.unique(pos)) < pos.size
    # measured 1.8e-15 (sums of up to 9 terms in another order)
    assert np.allclose(a, b, rtol=0, atol=1e-14)
