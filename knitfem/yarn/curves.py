"""Yarns of their own lengths as open cubic B-splines, for output and drawing.

The control points of all yarns are concatenated, yarn after yarn, and yarn
f's are ``points[start[f]:start[f + 1]]`` (CSR-like offsets); yarn f has
n_f − 3 segments. Each control point carries the course it knits (0 the
first knitted course), so that a yarn may knit several courses and a course
may be several yarns. A closed yarn is drawn as the open spline of its
control points with its first three repeated at its end (``Fabric.curves``).

Sampling the centrelines s = 0, 1/m, …, n_f − 3 of every yarn is one sparse
product with the (Σ_f ((n_f − 3) m + 1), N) matrix of B-spline weights,

    x(s_k) = Σ_a b_a(u_k) p_{start_f + i_k + a},   s_k = i_k + u_k,

made once for a layout and a sampling rate.
"""

import functools
from dataclasses import dataclass, replace

import numpy as np

from knitfem.yarn import bspline

__all__ = ["Curves", "Samples"]


@dataclass(frozen=True)
class Samples:
    """Sampled centrelines: points (M, 3), yarn f's at points[start[f]:
    start[f + 1]]; ``yarn`` and ``course`` (M,) of every sample."""

    points: np.ndarray
    start: np.ndarray
    yarn: np.ndarray
    course: np.ndarray

    @property
    def nyarn(self):
        return len(self.start) - 1

    def segments(self):
        """The (M − nyarn, 2) pairs of consecutive samples of one yarn."""
        inside = np.ones(len(self.points) - 1, bool)
        inside[self.start[1:-1] - 1] = False
        first = np.flatnonzero(inside)
        return np.stack([first, first + 1], axis=-1)


@dataclass(frozen=True)
class Curves:
    """Open B-spline yarns: control points (N, 3), offsets ``start``
    (nyarn + 1,) and the ``course`` (N,) of every control point."""

    points: np.ndarray
    start: np.ndarray
    course: np.ndarray

    def __array__(self, dtype=None):
        return np.asarray(self.points, dtype=dtype)

    @property
    def nyarn(self):
        return len(self.start) - 1

    def yarn(self, f):
        """Control points (n_f, 3) of yarn f."""
        return self.points[self.start[f]:self.start[f + 1]]

    def moved(self, points):
        """The same yarns with the control points ``points`` (N, 3)."""
        return replace(self, points=np.asarray(points).reshape(-1, 3))

    @property
    def nseg(self):
        """Segments (nyarn,) of each yarn, n_f − 3."""
        return np.diff(self.start) - 3

    def at(self, yarn, s):
        """Points (n, 3) P_f(s) of the yarns ``yarn`` at parameters s (n,)."""
        yarn = np.asarray(yarn, dtype=np.int64)
        k, u = bspline.locate(s, self.nseg[yarn])
        cols = (self.start[yarn] + k)[:, None] + np.arange(4)
        return np.einsum("na,nai->ni", bspline.basis(u), self.points[cols])

    def samples(self, samples):
        """Centrelines sampled ``samples`` times a segment (``Samples``)."""
        S, start, k = _sampler(np.asarray(self.start, np.int64).tobytes(), samples)
        yarn = np.repeat(np.arange(self.nyarn), np.diff(start))
        return Samples(S @ np.asarray(self.points), start, yarn, self.course[k])

    def sampling(self, samples):
        """(S, start): the sparse (M, N) B-spline weights of the samples
        ``samples`` gives (x = S p) and their offsets (nyarn + 1,)."""
        S, start, _ = _sampler(np.asarray(self.start, np.int64).tobytes(), samples)
        return S, start


@functools.lru_cache(maxsize=8)
def _sampler(start_bytes, samples):
    """(S, sample offsets, the control point nearest each sample) of the
    yarns with control-point offsets ``start`` (as bytes)."""
    from scipy import sparse

    start = np.frombuffer(start_bytes, dtype=np.int64)
    nseg = np.diff(start) - 3
    count = nseg * samples + 1
    first = np.concatenate([[0], np.cumsum(count)])
    yarn = np.repeat(np.arange(len(nseg)), count)
    j = np.arange(first[-1]) - first[yarn]
    k, u = bspline.locate(j / samples, nseg[yarn])
    cols = (start[yarn] + k)[:, None] + np.arange(4)
    S = sparse.csr_matrix((bspline.basis(u).ravel(),
                           (np.repeat(np.arange(len(j)), 4), cols.ravel())),
                          shape=(len(j), start[-1]))
    return S, first, cols[:, 1] + (u >= 0.5)
