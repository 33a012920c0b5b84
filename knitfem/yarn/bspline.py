"""Uniform cubic B-splines: basis, derivatives and Gauss quadrature.

A curve with control points p_0 … p_{n−1} has n − 3 segments; segment k,
at local parameter u ∈ [0, 1], is

    P(k + u) = Σ_{a=0}^{3} b_a(u) p_{k+a},

    b_0 = (1 − u)³/6,        b_1 = (3u³ − 6u² + 4)/6,
    b_2 = (−3u³ + 3u² + 3u + 1)/6,   b_3 = u³/6.

The global parameter s = k + u runs over [0, n − 3]. At a junction (u = 0)
P = (p_k + 4 p_{k+1} + p_{k+2})/6, so the value there is centred on p_{k+1}.

A closed (periodic) curve has no end points: its n control points make n
segments, segment k blending p_{(k+a) mod n}, and s is read modulo n.

``segments``, ``span`` and ``locate`` take one curve's n and closedness, or
arrays of them broadcast against k or s (points on yarns of their own
lengths, some closed, some open, in one vectorised call).
"""

import numpy as np

__all__ = ["basis", "gauss", "segments", "span", "locate", "curve_points",
           "junction_symbol", "periodic_interpolant"]


def basis(u, nu=0):
    """The four blending functions b_a(u) or their nu-th derivative.

    Parameters
    ----------
    u : array_like, shape (...)
        Local parameters in [0, 1].
    nu : {0, 1, 2, 3}
        Order of the derivative d^nu b_a / du^nu.

    Returns
    -------
    ndarray, shape (..., 4)
    """
    u = np.asarray(u, dtype=float)
    one = np.ones_like(u)
    if nu == 0:
        v = ((1 - u) ** 3, 3 * u**3 - 6 * u**2 + 4,
             -3 * u**3 + 3 * u**2 + 3 * u + 1, u**3)
    elif nu == 1:
        v = (-3 * (1 - u) ** 2, 9 * u**2 - 12 * u,
             -9 * u**2 + 6 * u + 3, 3 * u**2)
    elif nu == 2:
        v = (6 * (1 - u), 18 * u - 12, -18 * u + 6, 6 * u)
    elif nu == 3:
        v = (-6 * one, 18 * one, -18 * one, 6 * one)
    else:
        raise ValueError(f"derivative order nu={nu} must be 0, 1, 2 or 3")
    return np.stack(v, axis=-1) / 6.0


def gauss(nq):
    """Gauss–Legendre points and weights on [0, 1] (exact to degree 2nq − 1)."""
    x, w = np.polynomial.legendre.leggauss(nq)
    return 0.5 * (x + 1.0), 0.5 * w


def fewest_gauss_points(nseg, closed=False):
    """The fewest Gauss points a segment that keep a yarn's mass matrix
    m = Σ_{e,q} w_q ρ |X'| b(u_q) b(u_q)ᵀ positive definite.

    m is singular exactly when a nonzero spline vanishes at every Gauss point.
    An open curve of n segments has n + 3 coefficients, so it needs
    nq·n ≥ n + 3 points; Gauss points interlace the B-splines' supports
    (Schoenberg–Whitney), so that is enough: nq ≥ 1 + ⌈3/n⌉ (4 for one
    segment, 3 for two, else 2). A closed curve of n segments has n, but at
    one point a segment, the midpoint values (1, 23, 23, 1)/48 of the
    alternating spline cancel when n is even: nq ≥ 2.
    """
    return 2 if closed else 1 + -(-3 // max(int(nseg), 1))


def segments(ncp, closed=False):
    """Segments of a curve of ncp control points: ncp − 3, or ncp if closed."""
    return ncp - 3 * (1 - np.asarray(closed, dtype=int))


def span(k, ncp, closed=False):
    """Control points (..., 4) that segment k blends: k … k + 3, modulo ncp
    on a closed curve."""
    idx = np.asarray(k)[..., None] + np.arange(4)
    if np.ndim(closed) == 0:
        return idx % ncp if closed else idx
    return np.where(np.asarray(closed)[..., None], idx % np.asarray(ncp)[..., None],
                    idx)


def locate(s, nseg, closed=False):
    """Split global parameters s into (segment k, local u): s ∈ [0, nseg]
    (clipped to the end segments), or s modulo nseg on a closed curve."""
    s = np.asarray(s, dtype=float)
    s = np.where(closed, np.mod(s, nseg), s)
    k = np.clip(np.floor(s).astype(int), 0, nseg - 1)
    return k, s - k


def curve_points(P, s, nu=0, closed=False):
    """Evaluate d^nu P/ds^nu at global parameters s for control points P (n, 3)."""
    n = len(P)
    k, u = locate(s, segments(n, closed), closed)
    return np.einsum("...a,...ai->...i", basis(u, nu), P[span(k, n, closed)])


def junction_symbol(omega):
    """Symbol of the junction average (p_{k} + 4p_{k+1} + p_{k+2})/6 on e^{iωk}.

    A harmonic sampled at the control-point indices is reproduced at the
    junctions after division by (4 + 2 cos ω)/6, ω in radians per segment.
    """
    return (4.0 + 2.0 * np.cos(omega)) / 6.0


def periodic_interpolant(points):
    """Control points p (n, 3) of the closed curve through ``points`` (n, 3)
    at its junctions: (p_{i−1} + 4 p_i + p_{i+1})/6 = x_i (indices mod n),
    solved by FFT (the circulant's symbol (4 + 2 cos 2πm/n)/6 ≥ 1/3)."""
    x = np.asarray(points, dtype=float)
    n = len(x)
    symbol = junction_symbol(2 * np.pi * np.arange(n) / n)
    return np.fft.ifft(np.fft.fft(x, axis=0) / symbol[:, None], axis=0).real
