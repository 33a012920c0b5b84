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


def _flat(pts):
    """(points (M, 3), offsets (nyarn + 1,)) of sampled centrelines given as
    ``yarn.curves.Samples`` or as an array (nyarn, m, 3)."""
    if hasattr(pts, "start"):
        return np.asarray(pts.points, dtype=float), np.asarray(pts.start)
    pts = np.asarray(pts, dtype=float)
    return pts.reshape(-1, 3), np.arange(len(pts) + 1) * pts.shape[1]


class YarnGaps:
    """D of frames of one knit, and the smallest over the frames seen.

    Parameters
    ----------
    pts : yarn.curves.Samples or ndarray (nyarn, m, 3)
        Sampled centrelines of the first frame (arclength and closure).
    radius : float
        Yarn radius r.
    """

    def __init__(self, pts, radius):
        P, start = _flat(pts)
        self.radius = float(radius)
        count = np.diff(start)
        self.yarn = np.repeat(np.arange(len(count)), count)
        chords = np.linalg.norm(np.diff(P, axis=0), axis=-1)
        chords[start[1:-1] - 1] = 0.0                   # no chord between yarns
        s = np.concatenate([[0.0], np.cumsum(chords)])
        self.s = s - s[start[:-1]][self.yarn]
        first, last = start[:-1], start[1:] - 1
        length = self.s[last]
        closed = np.linalg.norm(P[first] - P[last], axis=-1) \
            < 1e-3 * np.maximum(length, 1e-12)
        self.perimeter = np.where(closed, length, np.inf)[self.yarn]
        self.smallest, self.time = np.inf, None

    def frame(self, pts):
        """D of one frame of sampled centrelines (as given to the
        constructor)."""
        i, j, d = self.pairs(_flat(pts)[0], 2.0 * self.radius)
        if not len(d):
            return 1.0
        return min(1.0, float(d.min()) / (2.0 * self.radius))

    def pairs(self, P, distance):
        """(i, j, |x_i − x_j|) of the sample pairs (points P (M, 3) of one
        frame) closer than ``distance``, of different yarns or of one yarn
        more than 8 r apart along it."""
        from scipy.spatial import cKDTree          # on first use

        pairs = cKDTree(P).query_pairs(distance, output_type="ndarray")
        i, j = pairs[:, 0], pairs[:, 1]
        along = np.abs(self.s[i] - self.s[j])
        along = np.minimum(along, self.perimeter[i] - along)
        keep = (self.yarn[i] != self.yarn[j]) | (along > 8.0 * self.radius)
        i, j = i[keep], j[keep]
        return i, j, np.linalg.norm(P[i] - P[j], axis=1)

    def add(self, t, pts):
        """Measure the frame at time t; keep the smallest D and its time."""
        gap = self.frame(pts)
        if gap < self.smallest:
            self.smallest, self.time = gap, float(t)
        return gap

    def record(self):
        """``min_yarn_gap`` (units of 2r) and ``min_yarn_gap_time_s`` (s)."""
        return dict(min_yarn_gap=float(self.smallest), min_yarn_gap_time_s=self.time)
