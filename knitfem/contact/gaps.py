"""The smallest gap between pieces of yarn, measured on sampled centrelines.

    D = min |x_i − x_j| / 2r,   capped at 1 (touching or apart),

over the pairs of centreline points (i, j) of different yarns, or of one
yarn more than 8 r apart along it (the short way round a closed yarn): two
yarn surfaces pass through each other where D < 1. The points are those of
the output frames (``io.centrelines``); arclength along each yarn is the sum
of the chords between its points in the first frame, and a yarn is closed
where its first and last points meet there (within 1e-3 of its length).

A k-d tree finds the pairs closer than 2r (its broad phase), so a frame
costs O(points) and no pair farther apart is ever formed; call it on one
rank with the gathered points.
"""

import numpy as np

__all__ = ["YarnGaps"]


class YarnGaps:
    """D of frames of one knit, and the smallest over the frames seen.

    Parameters
    ----------
    pts : (nyarn, m, 3)
        Sampled centrelines of the first frame (arclength and closure).
    radius : float
        Yarn radius r.
    """

    def __init__(self, pts, radius):
        pts = np.asarray(pts, dtype=float)
        self.radius = float(radius)
        chords = np.linalg.norm(np.diff(pts, axis=1), axis=-1)
        s = np.concatenate([np.zeros((len(pts), 1)), np.cumsum(chords, axis=1)],
                           axis=1)
        length = s[:, -1]
        closed = np.linalg.norm(pts[:, 0] - pts[:, -1], axis=-1) \
            < 1e-3 * np.maximum(length, 1e-12)
        self.s = s.ravel()
        self.perimeter = np.repeat(np.where(closed, length, np.inf), pts.shape[1])
        self.yarn = np.repeat(np.arange(len(pts)), pts.shape[1])
        self.smallest, self.time = np.inf, None

    def frame(self, pts):
        """D of one frame of sampled centrelines (nyarn, m, 3)."""
        from scipy.spatial import cKDTree          # on first use

        P = np.asarray(pts, dtype=float).reshape(-1, 3)
        r = self.radius
        pairs = cKDTree(P).query_pairs(2.0 * r, output_type="ndarray")
        if not len(pairs):
            return 1.0
        i, j = pairs[:, 0], pairs[:, 1]
        along = np.abs(self.s[i] - self.s[j])
        along = np.minimum(along, self.perimeter[i] - along)
        keep = (self.yarn[i] != self.yarn[j]) | (along > 8.0 * r)
        if not keep.any():
            return 1.0
        d = np.linalg.norm(P[i[keep]] - P[j[keep]], axis=1)
        return min(1.0, float(d.min()) / (2.0 * r))

    def add(self, t, pts):
        """Measure the frame at time t; keep the smallest D and its time."""
        gap = self.frame(pts)
        if gap < self.smallest:
            self.smallest, self.time = gap, float(t)
        return gap

    def record(self):
        """``min_yarn_gap`` (units of 2r) and ``min_yarn_gap_time_s`` (s)."""
        return dict(min_yarn_gap=float(self.smallest), min_yarn_gap_time_s=self.time)
