"""Rows of Γ̃: k weights on k columns each, applied to arrays of points.

A yarn control point embedded in the volume is x_i = Σ_j v_ij α_{c_ij}: its
row of Γ̃ holds the k = 32 weights of the volume control points c_ij of its
patch (``Embedding.cols``, ``vals``). The reduced model applies such rows
(Γ̃ itself, a subset of it, the shell's D) to α and their transpose to
forces at every evaluation, so ``EmbeddingRows`` keeps them in this fixed
shape and applies them by compiled loops (``_rows.pyx``, 2.4× and 1.6×
faster than scipy's sparse products on 36 000 rows, a 60×120 sleeve's
contact set) or by scipy's products (``compiled=False``: the reference the
tests hold them to).
"""

import numpy as np
from scipy import sparse

from knitfem.yarn.kernels import compiled_module

__all__ = ["EmbeddingRows", "add_at"]

VERSION = 2                 # of knitfem/lod/_rows.pyx, which this module calls


class EmbeddingRows:
    """The (m × n) matrix whose row i holds ``vals[i]`` on ``cols[i]`` (both
    (m, k)): ``R @ a`` (a (n, 3)) and ``R.T @ g`` (g (m, 3)) as arrays,
    ``rows(i)`` a subset, ``tocsr()`` scipy's copy."""

    def __init__(self, cols, vals, n, compiled=True):
        self.cols = np.ascontiguousarray(cols, dtype=np.int64)
        self.vals = np.ascontiguousarray(vals, dtype=float)
        self.shape = (len(self.cols), n)
        self.compiled = compiled
        self._kernels = compiled_module("knitfem.lod._rows", VERSION) if compiled else None
        self._csr = None if compiled else self.tocsr()
        self.T = _Transposed(self)

    def tocsr(self):
        m, k = self.cols.shape
        # scipy sorts a row's columns in place: its own copies
        return sparse.csr_matrix((self.vals.ravel().copy(), self.cols.ravel().copy(),
                                  np.arange(0, m * k + 1, k)), shape=self.shape)

    def rows(self, i):
        """The rows i, as ``EmbeddingRows``."""
        return EmbeddingRows(self.cols[i], self.vals[i], self.shape[1], self.compiled)

    def __matmul__(self, a):
        a = np.ascontiguousarray(a, dtype=float)
        if self._kernels is None:
            return self._csr @ a
        y = np.empty((self.shape[0], 3))
        self._kernels.apply(self.cols, self.vals, a.reshape(-1, 3), y)
        return y

    def transpose_times(self, g):
        """Rᵀ g, (n, 3)."""
        g = np.ascontiguousarray(g, dtype=float)
        if self._kernels is None:
            return self._csr.T @ g
        b = np.zeros((self.shape[1], 3))
        self._kernels.apply_t(self.cols, self.vals, g.reshape(-1, 3), b)
        return b


class _Transposed:
    """``R.T``: ``R.T @ g`` is ``R.transpose_times(g)``."""

    def __init__(self, R):
        self.R = R

    def __matmul__(self, g):
        return self.R.transpose_times(g)


def add_at(values, pos, x, compiled=True):
    """values[pos] += x (``pos`` and ``x`` arrays of a shape), entries at the
    same position summed and those at len(values) or past it dropped: by a
    compiled loop, or by numpy's bincount (``compiled=False``, the
    reference)."""
    pos = np.ascontiguousarray(pos, dtype=np.int64).reshape(-1)
    x = np.ascontiguousarray(x, dtype=float).reshape(-1)
    if compiled:
        compiled_module("knitfem.lod._rows", VERSION).add_at(pos, x, values)
    else:
        values += np.bincount(pos, x, minlength=len(values) + 1)[:len(values)]
