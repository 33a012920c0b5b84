"""What a scene hands to a model: yarns at rest and their constraints.

A ``Fabric`` is pure geometry (metres): the rest control points of every yarn
(yarns of their own lengths, concatenated yarn after yarn), the contact pairs
that hold the knit together, and the world constraints (fixed points, clamped
tangents). Models (full or reduced) are built from it.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from knitfem.yarn import bspline
from knitfem.yarn.curves import Curves

__all__ = ["Fabric"]


def _empty_points():
    return (np.zeros(0, int), np.zeros(0))


@dataclass
class Fabric:
    """Rest geometry and constraint parameters.

    Attributes
    ----------
    X : ndarray
        (N, 3) rest control points of all yarns, yarn after yarn (given as
        (nyarn, ncp, 3) for yarns of one length, or as a list of (n_f, 3)).
    radius : float
        Yarn radius (m).
    yarn_start : ndarray
        (nyarn + 1,) offsets: yarn f's control points are
        X[yarn_start[f]:yarn_start[f + 1]] (derived when X is given by yarn).
    course : ndarray
        (N,) the course every control point knits, 0 the first knitted
        course (default: yarn f knits course f).
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
    closed : ndarray
        (nyarn,) bool, or one bool for every yarn: a closed curve (a course
        knitted in the round) of n_f segments, control points read modulo
        n_f (``bspline``).
    natural : bool
        The yarn is straight at rest (natural curvature κ₀ = 0): X gives the
        rest lengths only, and the loops are bent (prestressed); else X is a
        stress-free template, κ₀ its curvature.
    start_X : ndarray or None
        (N, 3) control points of the start state where it is not the rest
        turned (a relaxed knit, a scaled template).
    separation : float or None
        The distance the contacts hold between the two centrelines (2r for
        yarns that touch), or None for the rest's.
    contact_X : ndarray or None
        (N, 3) control points whose gaps the yarn contact takes for the
        rest's (its band and the pairs it leaves out), where X's are not
        the knit's: a natural knit's template at its own size, X being that
        template scaled to another loop length; None for X.
    """

    X: np.ndarray
    radius: float
    yarn_start: np.ndarray = None
    course: np.ndarray = None
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
    closed: np.ndarray = False
    natural: bool = False
    start_X: np.ndarray = None
    separation: float = None
    contact_X: np.ndarray = None

    def __post_init__(self):
        if self.yarn_start is None:
            one = isinstance(self.X, np.ndarray) and self.X.ndim == 2
            yarns = [np.asarray(P, dtype=float) for P in ([self.X] if one else self.X)]
            self.yarn_start = np.cumsum([0] + [len(P) for P in yarns])
            self.X = np.concatenate(yarns) if yarns else np.zeros((0, 3))
        self.yarn_start = np.asarray(self.yarn_start, dtype=np.int64)
        self.closed = np.broadcast_to(np.asarray(self.closed, bool), (self.nyarn,))
        if self.course is None:
            self.course = self.yarn_of
        self.course = np.asarray(self.course, dtype=np.int64)

    @property
    def nyarn(self):
        return len(self.yarn_start) - 1

    @property
    def npoints(self):
        """Control points of all yarns, N."""
        return int(self.yarn_start[-1])

    @property
    def yarn_ncp(self):
        """Control points (nyarn,) of each yarn, n_f."""
        return np.diff(self.yarn_start)

    @property
    def yarn_nseg(self):
        """Segments (elements) (nyarn,) of each yarn."""
        return bspline.segments(self.yarn_ncp, self.closed)

    @property
    def yarn_of(self):
        """The yarn (N,) of every control point."""
        return np.repeat(np.arange(self.nyarn), self.yarn_ncp)

    def yarn(self, f):
        """Rest control points (n_f, 3) of yarn f."""
        return self.X[self.yarn_start[f]:self.yarn_start[f + 1]]

    def segments(self, yarn_start, yarn_end):
        """(yarn f, segment k) of every segment of yarns [start, end), yarn
        after yarn."""
        f = np.arange(yarn_start, yarn_end)
        nseg = self.yarn_nseg[f]
        first = np.concatenate([[0], np.cumsum(nseg)])
        return np.repeat(f, nseg), np.arange(first[-1]) - np.repeat(first[:-1], nseg)

    def connectivity(self, yarn_start, yarn_end):
        """Global control points (elements, 4) of the segments of yarns
        [start, end), yarn after yarn (yarn f's k-th blends control points
        yarn_start[f] + span(k))."""
        f, k = self.segments(yarn_start, yarn_end)
        return self.yarn_start[f][:, None] + bspline.span(
            k, self.yarn_ncp[f], self.closed[f])

    def point_rows(self, yarn, s, nu=0):
        """B-spline weights of d^nu P_f/ds^nu at P_f(s) for yarns ``yarn``
        and parameters s (n,): (global control points (n, 4), weights (n, 4))."""
        yarn = np.asarray(yarn, dtype=np.int64)
        ncp, closed = self.yarn_ncp[yarn], self.closed[yarn]
        k, u = bspline.locate(s, bspline.segments(ncp, closed), closed)
        return (self.yarn_start[yarn][:, None] + bspline.span(k, ncp, closed),
                bspline.basis(u, nu))

    def _drawn(self):
        """(index, start): the control points of the yarns as open splines
        (``curves``), as indices into X, and their offsets."""
        extra = 3 * self.closed
        ncp = self.yarn_ncp + extra
        start = np.concatenate([[0], np.cumsum(ncp)])
        f = np.repeat(np.arange(self.nyarn), ncp)
        i = np.arange(start[-1]) - start[f]
        return self.yarn_start[f] + np.where(i < self.yarn_ncp[f], i,
                                             i - self.yarn_ncp[f]), start

    def curves(self, P):
        """The yarns with control points P (N, 3) as open splines, for output
        and drawing (``curves.Curves``): a closed yarn's first three control
        points repeated at its end."""
        index, start = self._drawn()
        return Curves(np.asarray(P).reshape(-1, 3)[index], start, self.course[index])

    def sampling(self, samples):
        """(S, start): the sparse (M, N) weights of the centreline samples
        ``curves(P).samples(samples)`` on the control points, x = S P, and
        the samples' offsets (nyarn + 1,)."""
        from scipy import sparse

        index, start = self._drawn()
        S, first = Curves(index, start, self.course[index]).sampling(samples)
        pick = sparse.csr_matrix((np.ones(len(index)), (np.arange(len(index)), index)),
                                 shape=(len(index), self.npoints))
        return (S @ pick).tocsr(), first

    def load_vector(self, yarn_start, yarn_end):
        """Generalised forces of the point loads on yarns [start, end):
        F at P_f(s), s = k + u, adds b_a(u) F to control point k + a of yarn f.
        Returns (control points of those yarns, 3)."""
        first, last = self.yarn_start[yarn_start], self.yarn_start[yarn_end]
        Q = np.zeros((last - first, 3))
        yarn, s, F = self.loads
        mine = (yarn >= yarn_start) & (yarn < yarn_end)
        cols, b = self.point_rows(yarn[mine], np.asarray(s)[mine])
        np.add.at(Q, cols - first, b[..., None] * np.asarray(F)[mine][:, None])
        return Q

    def turn(self, points):
        """Points (…, 3) turned as the start turns the fabric (``start``)."""
        R, centre = self.start
        return (points - centre) @ np.asarray(R).T + centre

    def start_points(self):
        """Control points (N, 3) of the start state: ``start_X``, or X,
        turned."""
        return self.turn(self.X if self.start_X is None else self.start_X)

    def started_turned(self, R):
        """The same fabric (same rest) started turned by R about its centroid."""
        return replace(self, start=(np.asarray(R, float),
                                    self.X.mean(axis=0)))

    def rotated(self, R, centre):
        """The same fabric turned rigidly by the rotation R about ``centre``."""
        X, S, C = ((P - centre) @ np.asarray(R).T + centre if P is not None else None
                   for P in (self.X, self.start_X, self.contact_X))
        return replace(self, X=X, start_X=S, contact_X=C,
                       frame=np.asarray(R) @ self.frame)
