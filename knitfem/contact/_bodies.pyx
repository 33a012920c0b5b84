# cython: language_level=3, boundscheck=False, wraparound=False
# cython: cdivision=True, initializedcheck=False
"""Compiled signed distances of the rigid bodies, one point at a time.

The same mathematics as ``knitfem.contact.colliders`` (``Sphere.phi`` and
``Capsule.phi``, the tested references), in one pass over the points
instead of numpy's temporaries:

- ``sphere_phi``: φ = |x − c| − R;
- ``capsule_phi``: φ = |x − a − t (b − a)| − R, t = (x − a)·(b − a)/|b − a|²
  clamped to [0, 1].

Built by ``pip install -e .`` (setup.py).
"""

from libc.math cimport sqrt

# Raised whenever a kernel's arguments change: knitfem.contact.colliders
# refuses an extension built from an older source (run make setup).
VERSION = 1


def sphere_phi(const double[:, ::1] x, const double[::1] c, double R, double[::1] out):
    """out[i] = |x_i − c| − R."""
    cdef Py_ssize_t i
    cdef double d0, d1, d2
    with nogil:
        for i in range(x.shape[0]):
            d0 = x[i, 0] - c[0]
            d1 = x[i, 1] - c[1]
            d2 = x[i, 2] - c[2]
            out[i] = sqrt(d0 * d0 + d1 * d1 + d2 * d2) - R


def capsule_phi(const double[:, ::1] x, const double[::1] a, const double[::1] b,
                double R, double[::1] out):
    """out[i] = |x_i − q_i| − R, q_i the point of the segment ab nearest x_i."""
    cdef Py_ssize_t i
    cdef double u0 = b[0] - a[0], u1 = b[1] - a[1], u2 = b[2] - a[2]
    cdef double L2 = u0 * u0 + u1 * u1 + u2 * u2
    cdef double d0, d1, d2, t
    with nogil:
        for i in range(x.shape[0]):
            d0 = x[i, 0] - a[0]
            d1 = x[i, 1] - a[1]
            d2 = x[i, 2] - a[2]
            t = (d0 * u0 + d1 * u1 + d2 * u2) / L2
            t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
            d0 = x[i, 0] - (a[0] + t * u0)
            d1 = x[i, 1] - (a[1] + t * u1)
            d2 = x[i, 2] - (a[2] + t * u2)
            out[i] = sqrt(d0 * d0 + d1 * d1 + d2 * d2) - R
