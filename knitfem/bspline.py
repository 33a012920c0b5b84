"""Uniform cubic B-splines: basis, derivatives and Gauss quadrature.

A curve with control points p_0 … p_{n−1} has n − 3 segments; segment k,
at local parameter u ∈ [0, 1], is

    P(k + u) = Σ_{a=0}^{3} b_a(u) p_{k+a},

    b_0 = (1 − u)³/6,        b_1 = (3u³ − 6u² + 4)/6,
    b_2 = (−3u³ + 3u² + 3u + 1)/6,   b_3 = u³/6.

The global parameter s = k + u runs over [0, n − 3]. At a junction (u = 0)
P = (p_k + 4 p_{k+1} + p_{k+2})/6, so the value there is centred on p_{k+1}.
"""

import numpy as np

__all__ = ["basis", "gauss", "locate", "curve_points", "junction_symbol"]


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


def locate(s, nseg):
    """Split global parameters s ∈ [0, nseg] into (segment k, local u)."""
    s = np.asarray(s, dtype=float)
    k = np.clip(np.floor(s).astype(int), 0, nseg - 1)
    return k, s - k


def curve_points(P, s, nu=0):
    """Evaluate d^nu P/ds^nu at global parameters s for control points P (n, 3)."""
    k, u = locate(s, len(P) - 3)
    B = basis(u, nu)
    idx = k[..., None] + np.arange(4)
    return np.einsum("...a,...ai->...i", B, P[idx])


def junction_symbol(omega):
    """Symbol of the junction average (p_{k} + 4p_{k+1} + p_{k+2})/6 on e^{iωk}.

    A harmonic sampled at the control-point indices is reproduced at the
    junctions after division by (4 + 2 cos ω)/6, ω in radians per segment.
    """
    return (4.0 + 2.0 * np.cos(omega)) / 6.0
