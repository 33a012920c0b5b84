"""Textile measures of a knit: loop length, spacings, Munden's constants, curl.

A knit's dimensions are read from its loop heads H (courses × wales, 3): the
course spacing c_s is the distance between the heads of consecutive
courses, the wale spacing w_s the distance between neighbouring heads in a
course, both in the fabric's tangent plane there and the median over the
middle of the swatch (its edges curl). With
ℓ the yarn length a stitch (the loop length), Munden's dimensionless
constants are

    k_c = ℓ / c_s,   k_w = ℓ / w_s,   k_s = k_c k_w,

courses and wales a unit length times ℓ, and stitches a unit area times ℓ²
(Munden, J. Text. Inst. 50, 1959): a relaxed plain jersey has k_c ≈ 5.0–5.5,
k_w ≈ 3.8–4.3, k_s ≈ 19–22, whatever its yarn, which is why they are the
measure of a relaxed knit.

Sides. The technical face of a knit is the side on which its loops' legs
show as V's; the back shows the heads and sinkers as purl bumps. In the
pattern's frame (``Fabric.frame``: course, wale and thickness directions)
the heads and sinkers lie on the +thickness side of the legs at the
interlocks, so +thickness is the back. A plain jersey curls at its edges:
the courses' ends (left and right) roll to the face, the first and last
courses (bottom and top) to the back.
"""

import numpy as np

__all__ = ["EDGES", "spacings", "surface_normals", "munden", "curl",
           "loop_length", "turned"]

EDGES = ("bottom", "top", "left", "right")


def _middle(n):
    """Indices of the middle half of n (at least two where n allows)."""
    lo, hi = n // 4, n - n // 4
    if hi - lo < 2:
        lo, hi = 0, n
    return slice(lo, hi)


def surface_normals(heads, reach=2):
    """Unit normals (courses, wales, 3) of the fabric at its loop heads H:
    (H[r, c+k] − H[r, c−k]) × (H[r+k, c] − H[r−k, c]), k = ``reach``
    (one-sided at the edges), normalised (0 where a swatch of one course or
    wale has none). Two heads k apart are of one kind in every pattern whose
    repeat divides 2k (ribs, garter, seed for k = 2), so a rib's knit and
    purl heads on either side of the fabric do not tilt it; on a swatch
    curled with a uniform curvature the symmetric difference is the tangent
    at the middle head."""
    H = np.asarray(heads, dtype=float)
    R, C = H.shape[:2]
    c, r = np.arange(C), np.arange(R)
    u = H[:, np.minimum(c + reach, C - 1)] - H[:, np.maximum(c - reach, 0)]
    v = H[np.minimum(r + reach, R - 1)] - H[np.maximum(r - reach, 0)]
    n = np.cross(u, v)
    size = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.divide(n, size, out=np.zeros_like(n), where=size > 0)


def spacings(heads, normal=None):
    """(course spacing, wale spacing) [m]: medians over the middle of the
    swatch of |H[r+1, c] − H[r, c]| and |H[r, c+1] − H[r, c]| for loop heads
    ``heads`` (courses, wales, 3), in the fabric's plane where its unit
    ``normal`` is given: one (3,) for a flat swatch, or one a head
    (courses, wales, 3; ``surface_normals``) for its tangent plane there, a
    difference then projected on the plane normal to the mean of its two
    heads' normals. A rib's knit and purl heads lie on either side of the
    fabric, and its wales are as far apart as the width they take; a curled
    swatch's heads are as far apart as along its surface. NaN where the
    swatch has one course (one wale)."""
    H = np.asarray(heads, dtype=float)
    rows, cols = _middle(H.shape[0]), _middle(H.shape[1])
    mid = H[rows, cols]
    up, across = np.diff(mid, axis=0), np.diff(mid, axis=1)
    if normal is not None:
        n = np.broadcast_to(np.asarray(normal, dtype=float), H.shape)[rows, cols]
        up = _in_plane(up, n[:-1], n[1:])
        across = _in_plane(across, n[:, :-1], n[:, 1:])
    up, across = (np.linalg.norm(d, axis=-1) for d in (up, across))
    return (float(np.median(up)) if up.size else np.nan,
            float(np.median(across)) if across.size else np.nan)


def _in_plane(d, a, b):
    """The differences d (..., 3) less their parts along the mean of the
    unit normals a and b of their two ends (b turned to agree with a)."""
    side = np.where(np.einsum("...d,...d->...", a, b) < 0, -1.0, 1.0)
    m = a + side[..., None] * b
    m /= np.linalg.norm(m, axis=-1, keepdims=True)
    return d - np.einsum("...d,...d->...", d, m)[..., None] * m


def munden(loop_length, course_spacing, wale_spacing):
    """Munden's constants (k_c, k_w, k_s) = (ℓ/c_s, ℓ/w_s, k_c k_w)."""
    kc, kw = loop_length / course_spacing, loop_length / wale_spacing
    return float(kc), float(kw), float(kc * kw)


def loop_length(lengths, stitches):
    """Yarn length a stitch ℓ [m]: the total length of the yarns ``lengths``
    over their ``stitches``."""
    return float(np.sum(lengths) / np.sum(stitches))


def turned(X, P):
    """The rotation R that best carries the points X (n, 3) onto P (n, 3)
    after centring both, min_R Σ|R (X_i − X̄) − (P_i − P̄)|² (Kabsch): from
    the SVD U Σ Vᵀ of Σ (P_i − P̄)(X_i − X̄)ᵀ, R = U diag(1, 1, det U Vᵀ) Vᵀ.
    A template's directions carried to a deformed knit by it are rigid
    invariants of the knit."""
    X = np.asarray(X, dtype=float) - np.mean(X, axis=0)
    P = np.asarray(P, dtype=float) - np.mean(P, axis=0)
    U, _, Vt = np.linalg.svd(P.T @ X)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def curl(heads, back, radius):
    """How each edge of a swatch curls out of its middle's plane.

    The plane is the least-squares plane of the middle half of the loop
    heads H (courses, wales, 3), its normal n oriented along ``back`` (the
    world direction of the technical back). An edge's offset is the mean of
    (H − c)·n over its heads (c the middle's centroid), its angle the turn
    of that offset over its in-plane distance from c. Returns, for each of
    ``EDGES``, a dict: ``side`` ("back" or "face"; "flat" within 0.05 of the
    yarn ``radius``), ``offset_m`` (signed: > 0 towards the back) and
    ``angle_deg``.
    """
    H = np.asarray(heads, dtype=float)
    mid = H[_middle(H.shape[0]), _middle(H.shape[1])].reshape(-1, 3)
    c = mid.mean(axis=0)
    n = np.linalg.svd(mid - c, full_matrices=False)[2][-1]
    if n @ np.asarray(back, dtype=float) < 0:
        n = -n
    edges = dict(bottom=H[0], top=H[-1], left=H[:, 0], right=H[:, -1])
    out = {}
    for name in EDGES:
        d = edges[name] - c
        offset = float(np.mean(d @ n))
        inplane = float(np.linalg.norm(np.mean(d - np.outer(d @ n, n), axis=0)))
        side = "flat" if abs(offset) < 0.05 * radius else (
            "back" if offset > 0 else "face")
        out[name] = dict(side=side, offset_m=offset,
                         angle_deg=float(np.degrees(np.arctan2(offset, inplane))))
    return out
