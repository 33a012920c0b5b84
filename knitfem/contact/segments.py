"""Closest points of two segments, row-wise: the yarn contact's edge
distances and the step filter's lowest point of a path past a capsule."""

import numpy as np

__all__ = ["closest_parameters", "segment_distance"]


def closest_parameters(p0, p1, q0, q1):
    """(s, t) of the closest points p0 + s d₁, q0 + t d₂ of the segments p0p1
    and q0q1, row-wise (n, 3) each, s and t clamped to [0, 1] (Ericson,
    Real-Time Collision Detection, 5.1.9; q0q1 of nonzero length; p0p1 of
    zero length gives s = 0)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e = np.sum(d1 * d1, 1), np.sum(d2 * d2, 1)
    b, c, f = np.sum(d1 * d2, 1), np.sum(d1 * r, 1), np.sum(d2 * r, 1)
    a_ = np.where(a > 0, a, 1.0)
    denom = a * e - b * b
    s = np.where(denom > 1e-12 * a * e,
                 np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / e
    s = np.where(t < 0, np.clip(-c / a_, 0, 1), np.where(t > 1, np.clip((b - c) / a_, 0, 1), s))
    s = np.where(a > 0, s, 0.0)
    return s, np.clip(t, 0, 1)


def segment_distance(p0, p1, q0, q1):
    """Distance of the segments p0p1 and q0q1, row-wise (n, 3) each
    (``closest_parameters``; no segment of zero length)."""
    s, t = closest_parameters(p0, p1, q0, q1)
    return np.linalg.norm(p0 - q0 + (p1 - p0) * s[:, None] - (q1 - q0) * t[:, None], axis=1)
