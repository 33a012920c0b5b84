"""Opening a knit's template until no yarn comes within 2r of another.

A pattern's template (``stitches``) has every crossing the right way round
but, where knits meet purls, yarns pass closer than a yarn's thickness. Its
control points P are moved, as little and as smoothly as will do, to the
minimum of

    E(P) = Σ_(i,j) (δ − |x_i − x_j|)₊²  +  λ |L (P − P₀)|²  +  μ |P − P₀|²,

x = S P the centreline samples (``Fabric.sampling``), the pairs (i, j) those
of ``gaps.YarnGaps`` (different yarns, or one yarn more than 8 r apart along
it) closer than δ = 2.25 r, L the second differences of each yarn's control
points (wrapping round a closed yarn) and P₀ the template. E is minimised by
L-BFGS, in rounds of ``ROUND`` iterations, until no two samples are closer
than 2.08 r: 4 % beyond touching, as a jersey's, and past the yarn contact's
barrier band (0.072 r). The start has every crossing the right way round and
all its gaps positive, and the moves only push close pairs apart: the tests
check that every crossing keeps its depth order. A round moves no coordinate
more than ``REACH`` = r/2 from where it began (L-BFGS-B's bounds): the
penalty sees a pair only while it is closer than δ, and an unbounded line
search jumps yarns through one another between two looks (the 10×10 seed's
template moved up to 15 r and its courses slipped out of 62 of their 180
interlocks; bounded, it moves 3.5 r at most and keeps them all). ``hold_crossings`` then moves the two yarns
of every crossing the least that puts them a given distance apart (a
jersey's, so that a pattern's template is as near its crossings' 2r as a
jersey's is).
"""

import numpy as np

from knitfem.contact.gaps import YarnGaps
from knitfem.yarn.curves import Samples

__all__ = ["open_up", "hold_crossings", "CLEARANCE"]

CLEARANCE, ENOUGH = 2.25, 2.08
"""δ / r, and the smallest distance / r at which the opening stops."""
SMOOTH, STAY = 1e-2, 1e-4
"""λ and μ, against the squared gap deficits (lengths in units of r ~ 1)."""
SAMPLES = 8
ROUND, ROUNDS = 100, 40
REACH = 0.5
"""The largest move of a coordinate in a round, in yarn radii."""


def second_differences(fabric):
    """Sparse L: P_{i−1} − 2 P_i + P_{i+1} along every yarn (indices mod n_f
    on a closed yarn, interior points on an open one)."""
    from scipy import sparse

    rows = []
    for f in range(fabric.nyarn):
        first, n = fabric.yarn_start[f], fabric.yarn_ncp[f]
        i = np.arange(n) if fabric.closed[f] else np.arange(1, n - 1)
        rows.append(first + np.stack([(i - 1) % n, i, (i + 1) % n], axis=1))
    cols = np.concatenate(rows)
    return sparse.csr_matrix((np.tile([1.0, -2.0, 1.0], len(cols)),
                              (np.repeat(np.arange(len(cols)), 3), cols.ravel())),
                             shape=(len(cols), fabric.npoints))


def open_up(fabric):
    """Control points (N, 3) of ``fabric`` (whose yarn radius sets r) moved
    until every gap is at least 2.08 r (module docstring); RuntimeError if
    ``ROUNDS`` rounds do not get there."""
    from scipy import optimize

    S, start = fabric.sampling(SAMPLES)
    X0 = fabric.X
    nsample = np.diff(start)
    gaps = YarnGaps(Samples(S @ X0, start, np.repeat(np.arange(len(nsample)),
                                                     nsample), None), fabric.radius)
    L = second_differences(fabric)
    delta = CLEARANCE * fabric.radius
    scale = 1.0 / fabric.radius**2

    def energy(v):
        P = v.reshape(-1, 3)
        x = S @ P
        i, j, d = gaps.pairs(x, delta)
        short = delta - d
        g = np.zeros_like(x)
        push = (-2.0 * short / d)[:, None] * (x[i] - x[j])
        np.add.at(g, i, push)
        np.add.at(g, j, -push)
        dP = P - X0
        LdP = L @ dP
        E = np.sum(short**2) + SMOOTH * np.sum(LdP**2) + STAY * np.sum(dP**2)
        G = S.T @ g + 2 * SMOOTH * (L.T @ LdP) + 2 * STAY * dP
        return scale * E, scale * G.ravel()

    P = X0.copy()
    reach = REACH * fabric.radius
    for _ in range(ROUNDS):
        if not len(gaps.pairs(S @ P, ENOUGH * fabric.radius)[2]):
            return P
        v = P.ravel()
        P = optimize.minimize(energy, v, jac=True, method="L-BFGS-B",
                              bounds=optimize.Bounds(v - reach, v + reach),
                              options=dict(maxiter=ROUND)).x.reshape(-1, 3)
    raise RuntimeError(f"the template could not be opened to 2.08 r within "
                       f"{ROUNDS * ROUND} iterations (smallest gap "
                       f"{gaps.frame(S @ P):.3f} x 2r)")


def hold_crossings(fabric, held, tol, iterations=50):
    """Control points (N, 3) of ``fabric`` moved the least that puts the two
    points of every crossing (``Fabric.contacts``) ``held`` apart:
    Gauss–Newton steps of least norm on φ_c = |r_c| − held, r_c = P_a(s_a) −
    P_b(s_b), ΔP = −Jᵀ (J Jᵀ)⁻¹ φ. RuntimeError if they do not converge."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    ya, sa, yb, sb = fabric.contacts
    (ca, wa), (cb, wb) = fabric.point_rows(ya, sa), fabric.point_rows(yb, sb)
    cols = np.concatenate([ca, cb], axis=1)                 # (n, 8)
    w = np.concatenate([wa, -wb], axis=1)
    n = len(cols)
    rows = np.repeat(np.arange(n), 24)
    P = fabric.X.copy()
    for _ in range(iterations):
        r = np.einsum("nk,nkd->nd", w, P[cols])
        dist = np.linalg.norm(r, axis=1)
        phi = dist - held
        if not n or np.abs(phi).max() < tol:
            return P
        J = sparse.csr_matrix(((w[:, :, None] * (r / dist[:, None])[:, None, :]).ravel(),
                               (rows, (3 * cols[:, :, None] + np.arange(3)).ravel())),
                              shape=(n, P.size))
        P -= (J.T @ spsolve((J @ J.T).tocsc(), phi)).reshape(-1, 3)
    raise RuntimeError(f"the crossings cannot be held {held:g} apart (off by "
                       f"{np.abs(phi).max():.3g})")
