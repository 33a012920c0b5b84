"""What a scene hands to a model: yarns at rest and their constraints.

A ``Fabric`` is pure geometry (metres): the rest control points of every yarn
(all yarns have the same number of control points), the contact pairs that
hold the knit together, and the world constraints (fixed points, clamped
tangents). Models (full or reduced) are built from it.
"""

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["Fabric"]


def _empty_points():
    return (np.zeros(0, int), np.zeros(0))


@dataclass
class Fabric:
    """Rest geometry and constraint parameters.

    X : (nyarn, ncp, 3) rest control points.
    radius : yarn radius (m).
    contacts : (yarn_a, s_a, yarn_b, s_b) — P_a(s_a) − P_b(s_b) = d_ab.
    fixed : (yarn, s) — P_f(s) = x₀.
    clamped : (yarn, s) — P_f'(s) = X_f'(s) (position and direction held when
        combined with a fixed point at the same s).
    frame : (3, 3) rotation whose columns are the pattern's course, wale and
        thickness directions in the world (identity unless the scene turned
        the fabric); bounding volumes are boxes along these axes.
    """

    X: np.ndarray
    radius: float
    contacts: tuple = field(default_factory=lambda: (np.zeros(0, int), np.zeros(0),
                                                    np.zeros(0, int), np.zeros(0)))
    fixed: tuple = field(default_factory=_empty_points)
    clamped: tuple = field(default_factory=_empty_points)
    frame: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def nyarn(self):
        return self.X.shape[0]

    @property
    def ncp(self):
        return self.X.shape[1]

    def rotated(self, R, centre):
        """The same fabric turned rigidly by the rotation R about ``centre``."""
        X = (self.X - centre) @ np.asarray(R).T + centre
        return replace(self, X=X, frame=np.asarray(R) @ self.frame)
