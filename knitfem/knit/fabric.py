"""What a scene hands to a model: yarns at rest and their constraints.

A ``Fabric`` is pure geometry (metres): the rest control points of every yarn
(all yarns have the same number of control points), the contact pairs that
hold the knit together, and the world constraints (fixed points, clamped
tangents). Models (full or reduced) are built from it.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from knitfem.yarn import bspline

__all__ = ["Fabric"]


def _empty_points():
    return (np.zeros(0, int), np.zeros(0))


@dataclass
class Fabric:
    """Rest geometry and constraint parameters.

    Attributes
    ----------
    X : ndarray
        (nyarn, ncp, 3) rest control points.
    radius : float
        Yarn radius (m).
    contacts : tuple
        (yarn_a, s_a, yarn_b, s_b): P_a(s_a) − P_b(s_b) = d_ab.
    fixed : tuple
        (yarn, s): P_f(s) = x₀.
    clamped : tuple
        (yarn, s): P_f'(s) = X_f'(s) (position and direction held when
        combined with a fixed point at the same s).
    frame : ndarray
        (3, 3) rotation whose columns are the pattern's course, wale and
        thickness directions in the world (identity unless the scene turned
        the fabric); bounding volumes are boxes along these axes.
    loads : tuple
        (yarn, s, F): constant point forces F (n, 3) [N] at P_f(s).
    start : tuple
        (R, centre): the start state is the rest X turned rigidly by the
        rotation R about ``centre`` (``start_points``); rest quantities
        (energies, contacts) stay those of X, world holds are taken where the
        start state puts them.
    bodies : tuple
        Rigid bodies the yarns keep out of (``colliders``).
    friction : float
        Coulomb coefficient μ between the yarns and the bodies.
    closed : bool
        Every yarn a closed curve (a course knitted in the round): ncp
        segments, control points read modulo ncp (``bspline``).
    natural : the yarn is straight at rest (natural curvature κ₀ = 0): X
        gives the rest lengths only, and the loops are bent (prestressed);
        else X is a stress-free template, κ₀ its curvature.
    start_X : (nyarn, ncp, 3) control points of the start state where it is
        not the rest turned (a relaxed knit, a scaled template), or None.
    separation : the distance the contacts hold between the two centrelines
        (2r for yarns that touch), or None for the rest's.
    """

    X: np.ndarray
    radius: float
    contacts: tuple = field(default_factory=lambda: (np.zeros(0, int), np.zeros(0),
                                                    np.zeros(0, int), np.zeros(0)))
    fixed: tuple = field(default_factory=_empty_points)
    clamped: tuple = field(default_factory=_empty_points)
    frame: np.ndarray = field(default_factory=lambda: np.eye(3))
    loads: tuple = field(default_factory=lambda: (np.zeros(0, int), np.zeros(0),
                                                 np.zeros((0, 3))))
    start: tuple = field(default_factory=lambda: (np.eye(3), np.zeros(3)))
    bodies: tuple = ()
    friction: float = 0.0
    closed: bool = False
    natural: bool = False
    start_X: np.ndarray = None
    separation: float = None

    @property
    def nyarn(self):
        return self.X.shape[0]

    @property
    def ncp(self):
        return self.X.shape[1]

    @property
    def nseg(self):
        """Segments (elements) a yarn."""
        return bspline.segments(self.ncp, self.closed)

    def connectivity(self, yarn_start, yarn_end):
        """Global control points (elements, 4) of the segments of yarns
        [start, end), yarn after yarn (control point f · ncp + i)."""
        first = np.arange(yarn_start, yarn_end)[:, None, None] * self.ncp
        return (first + bspline.span(np.arange(self.nseg), self.ncp, self.closed)
                ).reshape(-1, 4)

    def open_splines(self, P):
        """The same curves as open splines, for output and drawing: a closed
        yarn's first three control points repeated at its end (nyarn, ncp + 3, 3)."""
        P = np.asarray(P)
        return np.concatenate([P, P[:, :3]], axis=1) if self.closed else P

    def load_vector(self, yarn_start, yarn_end):
        """Generalised forces of the point loads on yarns [start, end):
        F at P_f(s), s = k + u, adds b_a(u) F to control point k + a of yarn f.
        Returns (control points of those yarns, 3)."""
        Q = np.zeros((yarn_end - yarn_start, self.ncp, 3))
        yarn, s, F = self.loads
        mine = (yarn >= yarn_start) & (yarn < yarn_end)
        k, u = bspline.locate(s[mine], self.nseg, self.closed)
        idx = (yarn[mine] - yarn_start, bspline.span(k, self.ncp, self.closed))
        np.add.at(Q, (idx[0][:, None], idx[1]),
                  bspline.basis(u)[..., None] * np.asarray(F)[mine][:, None])
        return Q.reshape(-1, 3)

    def turn(self, points):
        """Points (…, 3) turned as the start turns the fabric (``start``)."""
        R, centre = self.start
        return (points - centre) @ np.asarray(R).T + centre

    def start_points(self):
        """Control points (nyarn, ncp, 3) of the start state: ``start_X``, or
        X, turned."""
        return self.turn(self.X if self.start_X is None else self.start_X)

    def started_turned(self, R):
        """The same fabric (same rest) started turned by R about its centroid."""
        return replace(self, start=(np.asarray(R, float),
                                    self.X.reshape(-1, 3).mean(axis=0)))

    def rotated(self, R, centre):
        """The same fabric turned rigidly by the rotation R about ``centre``."""
        X, S = ((P - centre) @ np.asarray(R).T + centre if P is not None else None
                for P in (self.X, self.start_X))
        return replace(self, X=X, start_X=S, frame=np.asarray(R) @ self.frame)
