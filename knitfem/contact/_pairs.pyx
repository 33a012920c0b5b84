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
  keys min · n + max (sorted).

Built by ``pip install -e .`` (setup.py).
"""

from libc.math cimport sqrt
from libc.stdint cimport int64_t, uint8_t

import numpy as np

# Raised whenever a kernel's arguments change: knitfem.contact.yarn_contact
# refuses an extension built from an older source (run make setup).
VERSION = 1


cdef inline double clamp01(double x) nogil:
    return 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)


cdef double pair_distance(const double[:, :] V, int64_t p0, int64_t p1,
                          int64_t q0, int64_t q1) nogil:
    cdef double d1[3]
    cdef double d2[3]
    cdef double r[3]
    cdef double a = 0, e = 0, b = 0, c = 0, f = 0, s, t, denom, w, dist = 0
    cdef int k
    for k in range(3):
        d1[k] = V[p1, k] - V[p0, k]
        d2[k] = V[q1, k] - V[q0, k]
        r[k] = V[p0, k] - V[q0, k]
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
