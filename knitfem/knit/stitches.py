"""Knit and purl: the depth of every control point of a course, from a chart.

Coordinates are the jersey's (``pattern``): x along the courses, y up the
wales, z through the thickness, and the technical face is the −z side.
In a jersey loop (γ_f, depth d cos 2t) the head (t = 2πj) and the sinkers
(t = 2πj ± π) lie at +z and the legs (t = 2πj ± π/2) at −z: the legs show
as V's on the face (−z) and the heads and sinkers as purl bumps on the
back (+z). A knit stitch (course f, stitch j) is the loop of course f
pulled through the loop of course f − 1 towards the face: its legs pass in
front of (−z of) the parent's head, and its sinkers behind (+z of) the
parent's legs. A purl is the same loop pulled through from the other side:
the knit's loop mirrored through the fabric's mid-plane, z → −z, so that
every crossing with its parent has its depth order, and its rest offset,
flipped through the thickness.

A course's loop j meets two stitches: its own (its legs' lower halves and
its sinkers pass through the parent, course f − 1) and the stitch above it
(course f + 1, stitch j, pulled through its head and upper legs). With
σ = +1 for a knit and −1 for a purl, σ_low(j) the stitch's own and σ_up(j)
that of the stitch above (its own on the top course), the depth of control
point i, t_i = −π + (i − 1)Δ, Δ = 2π/8, of course f is D = d / J(2Δ) times

    head (t_i = 2πj)          σ_up(j)
    legs (t_i = 2πj ± π/2)    −(σ_up(j) + σ_low(j))/2
    sinker (t_i = 2πj + π)    (σ_low(j) + σ_low(j + 1))/2
    between (odd i)           0, or σ_low(j) beside a sinker that joins a
                              knit to a purl (t_i = 2πj ± 3π/4)

which is the jersey's d cos 2t_i / J(2Δ) (J the junction symbol) where
σ ≡ 1 and its mirror image where σ ≡ −1. Where a knit meets a purl the
loop is blended across the sinker (or across the legs, between a course
and the next one of the other kind): the sinker goes through the
mid-plane, and the points beside it keep the depth their own stitch asks
for. The stitches beyond the edges of a flat chart are its mirror image
(stitch −1 is stitch 1); a tube's wrap around.
"""

import numpy as np

__all__ = ["stitch_signs", "depths"]

HEAD, LEG_R, SINKER, LEG_L = 4, 6, 0, 2
"""Positions q = (i − 1) mod 8 of control point i within a stitch."""


def stitch_signs(purl):
    """σ (courses, stitches): +1 for a knit, −1 for a purl."""
    return 1.0 - 2.0 * np.asarray(purl, dtype=float)


def depths(purl, f, ncp, closed, d):
    """Depths z (ncp,) of the control points of course f of the chart
    ``purl`` (courses, stitches), before the factor 1/J(2Δ): a closed
    course's control points i = 0 … ncp − 1 sit at t_i, an open one's too
    (its first and last beyond the end sinkers)."""
    sigma = stitch_signs(purl)
    cols = sigma.shape[1]
    low = sigma[f]
    up = sigma[f + 1] if f + 1 < len(sigma) else low
    k = np.arange(ncp) - 1
    q, j = np.mod(k, 8), np.floor_divide(k, 8)

    def column(c):
        if closed:
            return np.mod(c, cols)
        c = np.where(c < 0, -c, c)
        c = np.where(c > cols - 1, 2 * (cols - 1) - c, c)
        return np.clip(c, 0, cols - 1)

    here, left, right = column(j), column(j - 1), column(j + 1)
    b = np.zeros(ncp)
    b = np.where(q == HEAD, up[here], b)
    b = np.where((q == LEG_L) | (q == LEG_R), -0.5 * (up[here] + low[here]), b)
    b = np.where(q == SINKER, 0.5 * (low[left] + low[here]), b)
    b = np.where((q == 7) & (low[here] != low[right]), low[here], b)
    b = np.where((q == 1) & (low[here] != low[left]), low[here], b)
    return d * b
