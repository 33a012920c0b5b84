# cython: language_level=3, boundscheck=False, wraparound=False
# cython: cdivision=True, initializedcheck=False
"""Compiled products with rows of k weights on k columns (``EmbeddingRows``).

For rows i of weights v_ij on columns c_ij (j < k) and arrays of three
components,

    apply:    y_i = Σ_j v_ij a_{c_ij}          (y (m, 3), a (n, 3)),
    apply_t:  b_c += Σ_{(i, j): c_ij = c} v_ij g_i   (b (n, 3), g (m, 3)),

one row at a time: the three components of a row kept in registers, where
scipy's sparse product with several vectors loops over them at every entry.
``knitfem.lod.rows`` keeps scipy's product as the tested reference. And
``add_at``, values[p_i] += x_i (positions past the end dropped), for the
reduced tangent's values (``sparse_tangent``), where numpy's bincount
fills and adds an array of the values' length.

Built by ``pip install -e .`` (setup.py).
"""

from libc.stdint cimport int64_t

# Raised whenever a kernel's arguments change: knitfem.lod.rows refuses an
# extension built from an older source (run make setup).
VERSION = 1


def apply(const int64_t[:, ::1] cols, const double[:, ::1] vals,
          const double[:, ::1] a, double[:, ::1] y):
    """y_i = Σ_j v_ij a_{c_ij}."""
    cdef Py_ssize_t m = cols.shape[0], k = cols.shape[1], i, j
    cdef double s0, s1, s2, v
    cdef int64_t c
    with nogil:
        for i in range(m):
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            for j in range(k):
                c = cols[i, j]
                v = vals[i, j]
                s0 += v * a[c, 0]
                s1 += v * a[c, 1]
                s2 += v * a[c, 2]
            y[i, 0] = s0
            y[i, 1] = s1
            y[i, 2] = s2


def apply_t(const int64_t[:, ::1] cols, const double[:, ::1] vals,
            const double[:, ::1] g, double[:, ::1] b):
    """b_{c_ij} += v_ij g_i over every entry."""
    cdef Py_ssize_t m = cols.shape[0], k = cols.shape[1], i, j
    cdef double g0, g1, g2, v
    cdef int64_t c
    with nogil:
        for i in range(m):
            g0 = g[i, 0]
            g1 = g[i, 1]
            g2 = g[i, 2]
            for j in range(k):
                c = cols[i, j]
                v = vals[i, j]
                b[c, 0] += v * g0
                b[c, 1] += v * g1
                b[c, 2] += v * g2


def add_at(const int64_t[::1] pos, const double[::1] x, double[::1] values):
    """values[pos_i] += x_i, positions at or past the end dropped."""
    cdef Py_ssize_t m = pos.shape[0], n = values.shape[0], i
    cdef int64_t p
    with nogil:
        for i in range(m):
            p = pos[i]
            if p < n:
                values[p] += x[i]
