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
fills and adds an array of the values' length; ``quadrature_product``,
the contact's Σ_q (c_q c_qᵀ) ⊗ H_q a group of elements at a time
(``sparse_tangent.QuadratureProduct``, whose numpy loop is its reference).

Built by ``pip install -e .`` (setup.py).
"""

from libc.stdint cimport int64_t
from cython.view cimport array as cvarray

from knitfem.blas cimport dgemm_

# Raised whenever a kernel's arguments change: knitfem.lod.rows refuses an
# extension built from an older source (run make setup).
VERSION = 2


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


def quadrature_product(const double[:, ::1] C, const double[:, ::1] H6,
                       const int64_t[::1] bounds, const int64_t[::1] width,
                       const int64_t[::1] first, const int64_t[::1] pos,
                       double[::1] values):
    """values[pos] += Σ_q c_q c_qᵀ ⊗ H_q, a group at a time.

    Group g is the quadrature points (rows) bounds[g] to bounds[g + 1] of C
    (their weights on the group's w = width[g] columns, the first w of a
    row) and of H6 (the entries i ≤ j of their symmetric 3 × 3 blocks, in
    the order (0,0), (0,1), (0,2), (1,1), (1,2), (2,2)). With Z_q = c_q ⊗ H6_q
    and V = C_gᵀ Z (dgemm), V[k, 6l + s] goes to pos[first[g] + 9 (k w + l)
    + s] and, for the three pairs i < j, V[l, 6k + (1, 2, 4)] to the slots
    s = 6, 7, 8 (the entries i > j, transposed); positions at or past
    len(values) are dropped."""
    cdef Py_ssize_t ng = width.shape[0], wmax = C.shape[1], n = values.shape[0]
    cdef Py_ssize_t g, q, k, l, s, maxrows = 0
    cdef int w, m, rows, ldc = <int>wmax
    cdef int64_t at, p
    cdef double one = 1.0, zero = 0.0, c
    cdef int lower[3]
    lower[:] = [1, 2, 4]
    for g in range(ng):
        maxrows = max(maxrows, bounds[g + 1] - bounds[g])
    cdef double[::1] Z = cvarray((max(maxrows * 6 * wmax, 1),), sizeof(double), "d")
    cdef double[::1] V = cvarray((max(6 * wmax * wmax, 1),), sizeof(double), "d")
    with nogil:
        for g in range(ng):
            w = <int>width[g]
            m = 6 * w
            rows = <int>(bounds[g + 1] - bounds[g])
            if rows == 0:
                continue
            for q in range(rows):
                for k in range(w):
                    c = C[bounds[g] + q, k]
                    for s in range(6):
                        Z[q * m + 6 * k + s] = c * H6[bounds[g] + q, s]
            # V (w × 6w, row-major) = C_gᵀ Z: column-major Vᵀ = Zᵀ C_g
            dgemm_("N", "T", &m, &w, &rows, &one, &Z[0], &m,
                   &C[bounds[g], 0], &ldc, &zero, &V[0], &m)
            for k in range(w):
                for l in range(w):
                    at = first[g] + 9 * (k * w + l)
                    for s in range(9):
                        p = pos[at + s]
                        if p < n:
                            if s < 6:
                                values[p] += V[k * m + 6 * l + s]
                            else:
                                values[p] += V[l * m + 6 * k + lower[s - 6]]
