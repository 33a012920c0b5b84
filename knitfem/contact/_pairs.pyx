# cython: language_level=3, boundscheck=False, wraparound=False
# cython: cdivision=True, initializedcheck=False
"""Compiled kernels of the yarn contact's broad phase: edge pairs in C.

The same mathematics as ``knitfem.contact.yarn_contact`` (the numpy
``segment_distance`` and ``YarnContact.edges_may_touch`` are the tested
references), one pair at a time, on the samples V and the edges (i, i + 1)
of the polyline of every yarn:

- ``edge_distances``: the distance of edges e and f, the closest points
  p0 + s d₁ and q0 + t d₂ with s, t clamped to [0, 1] (Ericson, Real-Time
  Collision Detection, 5.1.9);
- ``edges_may_touch``: whether edges e and f share no sample and one of
  their four sample pairs may touch: on different yarns, or in different
  patches of both groupings along one yarn, and not among the ``excluded``
  keys min · n + max (sorted);
- ``close_pairs``: the edge pairs e < f apart along their yarns and closer
  than ``within``, found on a grid (an edge's midpoint m_e and half length
  h_e bound its distance to f from below by |m_e − m_f| − h_e − h_f, so
  only the cells about e's within ``within`` + 2 max h can hold an f that
  close);
- ``advance``: the step filter's conservative advancement of edge pairs
  (``YarnContact._advance``).

Built by ``pip install -e .`` (setup.py).
"""

from libc.math cimport fabs, sqrt
from libc.stdint cimport int64_t, uint8_t
from libc.stdlib cimport free, malloc, realloc

import numpy as np

# Raised whenever a kernel's arguments change: knitfem.contact.yarn_contact
# refuses an extension built from an older source (run make setup).
VERSION = 2


cdef inline double clamp01(double x) nogil:
    return 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)


cdef double segment_distance(const double *p0, const double *p1, const double *q0,
                             const double *q1) nogil:
    cdef double d1[3]
    cdef double d2[3]
    cdef double r[3]
    cdef double a = 0, e = 0, b = 0, c = 0, f = 0, s, t, denom, w, dist = 0
    cdef int k
    for k in range(3):
        d1[k] = p1[k] - p0[k]
        d2[k] = q1[k] - q0[k]
        r[k] = p0[k] - q0[k]
        a += d1[k] * d1[k]
        e += d2[k] * d2[k]
        b += d1[k] * d2[k]
        c += d1[k] * r[k]
        f += d2[k] * r[k]
    denom = a * e - b * b
    s = clamp01((b * f - c * e) / denom) if denom > 1e-12 * a * e else 0.0
    t = (b * s + f) / e
    if t < 0.0:
        s = clamp01(-c / a)
    elif t > 1.0:
        s = clamp01((b - c) / a)
    t = clamp01(t)
    for k in range(3):
        w = r[k] + d1[k] * s - d2[k] * t
        dist += w * w
    return sqrt(dist)


cdef double pair_distance(const double[:, :] V, int64_t p0, int64_t p1,
                          int64_t q0, int64_t q1) nogil:
    cdef double x[4][3]
    cdef int k
    for k in range(3):
        x[0][k], x[1][k], x[2][k], x[3][k] = V[p0, k], V[p1, k], V[q0, k], V[q1, k]
    return segment_distance(x[0], x[1], x[2], x[3])


def edge_distances(const double[:, :] V, const int64_t[:, ::1] edges,
                   const int64_t[::1] e, const int64_t[::1] f):
    """Distances (n,) of the edge pairs (e_k, f_k) at the samples V."""
    cdef Py_ssize_t n = e.shape[0], k
    out = np.empty(n)
    cdef double[::1] d = out
    with nogil:
        for k in range(n):
            d[k] = pair_distance(V, edges[e[k], 0], edges[e[k], 1],
                                 edges[f[k], 0], edges[f[k], 1])
    return out


cdef inline bint excluded_key(const int64_t[::1] keys, int64_t key) nogil:
    cdef Py_ssize_t lo = 0, hi = keys.shape[0], mid
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo < keys.shape[0] and keys[lo] == key


def edges_may_touch(const int64_t[:, ::1] edges, const int64_t[::1] e,
                    const int64_t[::1] f, const int64_t[::1] patch0,
                    const int64_t[::1] patch1, const int64_t[::1] yarn,
                    const int64_t[::1] excluded):
    """Whether each edge pair (e_k, f_k) may touch (module docstring), as a
    bool array (n,)."""
    cdef Py_ssize_t n = e.shape[0], k
    cdef int p, q
    cdef int64_t i, j, nsamples = yarn.shape[0]
    cdef bint ok
    out = np.zeros(n, dtype=bool)
    cdef uint8_t[::1] may = out.view(np.uint8)
    with nogil:
        for k in range(n):
            if (edges[e[k], 0] == edges[f[k], 0] or edges[e[k], 0] == edges[f[k], 1]
                    or edges[e[k], 1] == edges[f[k], 0]
                    or edges[e[k], 1] == edges[f[k], 1]):
                continue
            ok = False
            for p in range(2):
                for q in range(2):
                    i, j = edges[e[k], p], edges[f[k], q]
                    if yarn[i] == yarn[j] and (patch0[i] == patch0[j]
                                               or patch1[i] == patch1[j]):
                        continue
                    if excluded_key(excluded, min(i, j) * nsamples + max(i, j)):
                        continue
                    ok = True
            may[k] = ok
    return out


cdef struct Found:
    int64_t *e
    int64_t *f
    double *d
    Py_ssize_t n, size


cdef int push(Found *out, int64_t e, int64_t f, double d) nogil:
    cdef Py_ssize_t size
    cdef void *grown
    if out.n == out.size:
        size = 2 * out.size + 1024
        grown = realloc(out.e, size * sizeof(int64_t))
        if grown == NULL:
            return -1
        out.e = <int64_t *> grown
        grown = realloc(out.f, size * sizeof(int64_t))
        if grown == NULL:
            return -1
        out.f = <int64_t *> grown
        grown = realloc(out.d, size * sizeof(double))
        if grown == NULL:
            return -1
        out.d = <double *> grown
        out.size = size
    out.e[out.n], out.f[out.n], out.d[out.n] = e, f, d
    out.n += 1
    return 0


def close_pairs(const double[:, :] V, const int64_t[:, ::1] edges, double within,
                const double[::1] arc, const double[::1] perimeter,
                const int64_t[::1] yarn, double least):
    """Edge pairs (e, f), e < f, closer than ``within`` at the samples V and
    apart along their yarn (on different yarns, or their first samples at
    least ``least`` apart in arc length ``arc``, round a closed yarn of
    ``perimeter`` the shorter way), with their distances: three arrays,
    sorted by (e, f). The grid's cells have half the side ``within`` + 2
    max h_e at least (larger when there would be more than about 8 cells
    an edge), so the 5 × 5 × 5 cells about an edge's (25 runs of 5 keys)
    hold every f that may be that close; each pair is met once, from the
    edge that comes first in key order. Samples that are not finite (a
    state blown up) give no pairs."""
    cdef Py_ssize_t n = edges.shape[0]
    Va = np.asarray(V)
    E = np.asarray(edges)
    mid_a = 0.5 * (Va[E[:, 0]] + Va[E[:, 1]])
    half_a = 0.5 * np.linalg.norm(Va[E[:, 1]] - Va[E[:, 0]], axis=1)
    if n == 0 or not np.isfinite(mid_a).all():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    side = 0.5 * (within + 2.0 * half_a.max())
    extent = np.ptp(mid_a, axis=0)
    cells = np.prod(np.floor(extent / side) + 1)
    while cells > 8 * n + 1000:                  # at most ~8 cells an edge
        side *= max((cells / (8 * n + 1000)) ** (1 / 3), 1.25)
        cells = np.prod(np.floor(extent / side) + 1)
    cell_a = np.floor((mid_a - mid_a.min(axis=0)) / side).astype(np.int64)
    dims_a = cell_a.max(axis=0) + 1
    key_a = (cell_a[:, 0] * dims_a[1] + cell_a[:, 1]) * dims_a[2] + cell_a[:, 2]
    order_a = np.argsort(key_a, kind="stable").astype(np.int64)
    start_a = np.searchsorted(key_a[order_a], np.arange(np.prod(dims_a) + 1)).astype(np.int64)
    cdef const double[:, ::1] mid = mid_a
    cdef const double[::1] half = half_a
    cdef const int64_t[:, ::1] cell = cell_a
    cdef const int64_t[::1] dims = dims_a, order = order_a, start = start_a
    cdef Found out
    cdef Py_ssize_t first, i, j, at, end, lo, hi
    cdef int dx, dy, failed = 0
    cdef int64_t cx, cy, key, a, b
    cdef double u, v, z, w, gap, d, slack = 1e-9 * within
    out.e, out.f, out.d, out.n, out.size = NULL, NULL, NULL, 0, 0
    with nogil:
        for first in range(n):
            i = order[first]
            for dx in range(-2, 3):
                cx = cell[i, 0] + dx
                if cx < 0 or cx >= dims[0]:
                    continue
                for dy in range(-2, 3):
                    cy = cell[i, 1] + dy
                    if cy < 0 or cy >= dims[1]:
                        continue
                    key = (cx * dims[1] + cy) * dims[2]
                    at = start[key + max(cell[i, 2] - 2, 0)]
                    end = start[key + min(cell[i, 2] + 3, dims[2])]
                    for at in range(max(at, first + 1), end):
                        j = order[at]
                        lo, hi = min(i, j), max(i, j)
                        a, b = edges[lo, 0], edges[hi, 0]
                        if yarn[a] == yarn[b]:
                            gap = fabs(arc[a] - arc[b])
                            gap = min(gap, perimeter[a] - gap)
                            if not gap >= least:
                                continue
                        w = within + slack + half[i] + half[j]
                        u = mid[i, 0] - mid[j, 0]
                        v = mid[i, 1] - mid[j, 1]
                        z = mid[i, 2] - mid[j, 2]
                        if u * u + v * v + z * z >= w * w:
                            continue
                        d = pair_distance(V, edges[lo, 0], edges[lo, 1], edges[hi, 0],
                                          edges[hi, 1])
                        if d < within and push(&out, lo, hi, d) != 0:
                            failed = 1
                            break
                    if failed:
                        break
                if failed:
                    break
            if failed:
                break
    try:
        if failed:
            raise MemoryError("close_pairs: out of memory")
        e = np.array(<int64_t[:out.n]> out.e) if out.n else np.zeros(0, np.int64)
        f = np.array(<int64_t[:out.n]> out.f) if out.n else np.zeros(0, np.int64)
        dist = np.array(<double[:out.n]> out.d) if out.n else np.zeros(0)
    finally:
        free(out.e)
        free(out.f)
        free(out.d)
    ordered = np.argsort(e * n + f, kind="stable")
    return e[ordered], f[ordered], dist[ordered]


def advance(const double[:, :] V0, const double[:, :] dV, const int64_t[:, ::1] edges,
            const int64_t[::1] e, const int64_t[::1] f, const double[::1] d,
            double dmin, double keep, int rounds):
    """The smallest t in [0, 1] to which ``rounds`` rounds of conservative
    advancement bring the edge pairs (e_k, f_k), at distances d_k at the
    samples V0 and moving by dV (``YarnContact._advance``)."""
    cdef Py_ssize_t n = e.shape[0], k
    cdef int p, q, c, m
    cdef int64_t s[4]
    cdef double x[4][3]
    cdef double rel, w, u, low, t, dk, least = 1.0
    with nogil:
        for k in range(n):
            s[0], s[1], s[2], s[3] = edges[e[k], 0], edges[e[k], 1], edges[f[k], 0], edges[f[k], 1]
            rel = 0.0
            for p in range(2):
                for q in range(2):
                    w = 0.0
                    for c in range(3):
                        u = dV[s[p], c] - dV[s[2 + q], c]
                        w = w + u * u
                    rel = max(rel, sqrt(w))
            dk = d[k]
            low = dmin + keep * (dk - dmin)
            t = 0.0
            for m in range(rounds):
                t = min(t + (dk - low) / max(rel, 1e-300), 1.0)
                if t >= 1.0:
                    break
                for p in range(4):
                    for c in range(3):
                        x[p][c] = V0[s[p], c] + t * dV[s[p], c]
                dk = segment_distance(x[0], x[1], x[2], x[3])
            least = min(least, t)
    return min(max(least, 0.0), 1.0)
