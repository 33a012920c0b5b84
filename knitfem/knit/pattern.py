"""Knitted fabrics: yarn control points and contact parameters of a chart
of knit and purl stitches (plain jersey the chart of knits only).

A fabric of r rows (courses) × nc columns (stitches) is r yarns, one per
course. In units where a stitch is 2π wide the centreline of course f of a
jersey is the plain-knit curve

    γ_f(t) = (t + a sin 2t,  h cos t + f w,  d cos 2t),   t ∈ [−π, 2π nc − π],

x along the courses, y along the wales (up), z through the thickness. The
loop heads sit at t = 2πj, j = 0 … nc − 1; a yarn starts and ends at a
sinker loop (t = −π mod 2π).

Face and back. The heads and sinkers lie at +z, the legs at −z: the legs
show as V's on the −z side, the technical face, and the heads and sinkers
as purl bumps on the +z side, the technical back. Stitch j of course f + 1
is a knit, as seen from the face, when its loop is pulled through its
parent (stitch j of course f) towards the face: its legs pass in front of
(−z of) the parent's head, its sinkers behind (+z of) the parent's legs.
A purl is the loop pulled through from the other side: the knit's loop
mirrored through the mid-plane z = 0, its legs behind the parent's head and
its sinkers in front of its legs. A chart (``knit.chart``: rows bottom
first, each read from the face left to right) sets every stitch; the depths
of a course's control points follow its stitches and those above them,
blended across the sinker where a knit meets a purl (``knit.stitches``),
and the template is then opened until no yarn comes within 2r of another,
its crossings as far apart as a jersey's (``knit.clearance``). The
crossings, found per stitch as the closest approach of the two yarns there
(``interlocks``), hold the rest offsets of that geometry: a purl's are the
knit's flipped through the thickness.

Each yarn is a uniform cubic B-spline with 8 segments a stitch, so
n_f = 8 nc + 3 control points. Control point i sits at t_i = −π + (i − 1)Δ,
Δ = 2π/8; each harmonic of γ is divided by the junction symbol
(4 + 2 cos ωΔ)/6 so that the jersey's spline interpolates γ at every segment
junction. Physical lengths are the unit lengths times ``radius / r``.

Knitted in the round (``shape="tube"``) every course closes on itself: the
flat curve is wrapped around the y axis, x onto the angle θ = (x − t₀)/nc and
z onto the radius ρ = nc + d + z, the loops' innermost depth z = −d on a
circle of nc units (a course's 2π nc around),

    γ̃_f(t) = (ρ sin θ,  y,  ρ cos θ),   (x, y, z) = γ_f(t),

so that no arc is shorter than in the flat course: the legs of neighbouring
stitches, innermost, stay as far apart as flat (1.05 × 2r), where a circle
of nc units through z = 0 brought them to 0.97 × 2r at 16 stitches round
(0.90 at 8), closer than touching; the heads and sinkers, outermost, open
by (nc + 2d)/nc. Each yarn is a closed cubic B-spline of n_f = 8 nc
control points, one a junction, interpolating γ̃_f at all of them
(``bspline.periodic_interpolant``; a pattern's depths are those of its
flat course at the junctions). The technical back (+z) faces outwards: a
tube is seen from outside inside out, its chart still read from the face.
We chose closed courses over the single helical yarn of a circular
knitting machine: every course is the same ring, the tube's ends are level,
and whole yarns still spread over the ranks.
"""

import functools
from dataclasses import dataclass

import numpy as np

from knitfem.knit import stitches
from knitfem.knit.chart import Chart
from knitfem.yarn import bspline

__all__ = ["LoopShape", "Jersey", "SHAPES", "min_yarn_distance"]

SEGMENTS_PER_STITCH = 8
DT = 2 * np.pi / SEGMENTS_PER_STITCH
T0 = -np.pi
SHAPES = ("flat", "tube")


@dataclass(frozen=True)
class LoopShape:
    """Plain-knit loop in units where a stitch is 2π wide.

    a: loop bulge, h: loop half height, d: loop depth (z), w: course spacing,
    r: yarn radius. The defaults keep different yarns ≥ 2r apart at rest.
    """

    a: float = 1.5
    h: float = 4.0
    d: float = 1.2
    w: float = 4.5
    r: float = 0.75


class Jersey:
    """Geometry of an r × nc knit, a jersey unless its chart has purls:
    control points, contacts, fixed points.

    Parameters
    ----------
    rows, cols : int
        Courses r (yarns) and stitches a course nc.
    radius : float
        Yarn radius in metres; sets the scale ``radius / shape.r``.
    shape : LoopShape
    knit : {"flat", "tube"}
        A flat swatch of open courses, or a tube knitted in the round.
    rest : a relaxed knit of these stitches (``run.relax.RelaxedKnit``) its
        fabrics start from, or None for the stress-free template.
    chart : knit.chart.Chart of rows × cols, or None for a jersey
        Knit or purl for every stitch, as seen from the face.
    """

    def __init__(self, rows, cols, radius=5e-4, shape=LoopShape(), knit="flat",
                 rest=None, chart=None):
        if knit not in SHAPES:
            raise ValueError(f"knit shape {knit!r}: use one of {', '.join(SHAPES)}")
        self.rows, self.cols = int(rows), int(cols)
        self.chart = Chart(np.zeros((self.rows, self.cols), bool)) if chart is None \
            else chart
        if self.chart.shape != (self.rows, self.cols):
            raise ValueError(f"a chart of {self.chart.rows}x{self.chart.cols} stitches "
                             f"for a knit of {self.rows}x{self.cols}")
        self.radius, self.shape, self.knit = float(radius), shape, knit
        self.rest = rest
        self.scale = self.radius / shape.r
        self.nseg = SEGMENTS_PER_STITCH * self.cols
        self.ncp = self.nseg if self.closed else self.nseg + 3

    @property
    def closed(self):
        """Every course closed on itself (knitted in the round)."""
        return self.knit == "tube"

    def parameter(self, t):
        """Spline parameter s of the curve parameter t."""
        return (np.asarray(t) - T0) / DT

    def control_points(self, f):
        """Rest control points (n_f, 3) of yarn f: a jersey's interpolate γ_f
        (γ̃_f on a tube) at the junctions; a pattern's are the opened template
        of its knits and purls (``pattern_points``)."""
        if not self.chart.jersey:
            return self.scale * pattern_points(self.chart, self.knit, self.shape)[f]
        if self.closed:
            t = T0 + (np.arange(self.ncp) - 1) * DT
            return bspline.periodic_interpolant(self.centreline(t, f))
        s = self.shape
        t = T0 + (np.arange(self.ncp) - 1) * DT
        sym1 = bspline.junction_symbol(DT)
        sym2 = bspline.junction_symbol(2 * DT)
        P = np.stack(
            [t + s.a * np.sin(2 * t) / sym2,
             s.h * np.cos(t) / sym1 + f * s.w,
             s.d * np.cos(2 * t) / sym2],
            axis=-1,
        )
        return self.scale * P

    def all_control_points(self):
        """Rest control points of all yarns, (r · n_f, 3), yarn after yarn."""
        return np.concatenate([self.control_points(f) for f in range(self.rows)])

    def centreline(self, t, f, z=None):
        """The closed-form jersey curve γ_f(t) (γ̃_f on a tube) in metres,
        (len(t), 3), or the curve with the depths z (units of the shape)."""
        s, t = self.shape, np.asarray(t, dtype=float)
        x, y = t + s.a * np.sin(2 * t), s.h * np.cos(t) + f * s.w
        z = s.d * np.cos(2 * t) if z is None else z
        if self.closed:
            theta = (x - T0) / self.cols
            rho = self.cols + s.d + z        # the legs, z = −d, as far apart as flat
            x, z = rho * np.sin(theta), rho * np.cos(theta)
        return self.scale * np.stack([x, y, z], axis=-1)

    def contacts(self):
        """Interlock contacts, two a stitch: stitch j of course k + 1 passes
        the head of its parent, stitch j of course k, on either side. Each
        contact is the closest approach of the two splines near that stitch:
        the nearest pair of points on a grid of t_a = 2πj ± [0.3, 1.7] (the
        parent's head) and t_b = 2πj ± [1.4, 3.0] (the stitch's leg),
        refined by Newton (the jersey's at t_a = 2πj ± 0.99, t_b = 2πj ±
        2.16; a purl's the knit's mirrored, at the same parameters).

        Returns
        -------
        yarn_a : (nct,) int
            Course k; the contact is P_k(s_a) − P_{k+1}(s_b) = d_ab.
        s_a, s_b : (nct,) float
        """
        return interlocks([self.control_points(f) for f in range(self.rows)],
                          self.cols, self.closed)

    def heads(self, f):
        """Spline parameters of the nc loop heads of yarn f (t = 2πj)."""
        return self.parameter(2 * np.pi * np.arange(self.cols))


def interlocks(P, cols, closed):
    """The contacts (``Jersey.contacts``) of courses with control points P
    (a list of (n_f, 3)) of ``cols`` stitches each: (course k, s_a, s_b).
    The grids are searched a course at a time, and every contact is refined
    at once (``closest_approach``)."""
    side = np.array([-1.0, 1.0])[:, None]
    stitch = 2 * np.pi * np.arange(cols)[:, None, None]
    ga = ((stitch + side * np.linspace(0.3, 1.7, 15) - T0) / DT).reshape(-1, 15)
    gb = ((stitch + side * np.linspace(1.4, 3.0, 17) - T0) / DT).reshape(-1, 17)
    n = np.arange(len(ga))
    sa, sb = [np.zeros(0)], [np.zeros(0)]
    for k in range(len(P) - 1):
        A = bspline.curve_points(P[k], ga, closed=closed)
        B = bspline.curve_points(P[k + 1], gb, closed=closed)
        d = np.linalg.norm(A[:, :, None] - B[:, None], axis=-1).reshape(len(ga), -1)
        ia, ib = np.divmod(np.argmin(d, axis=1), gb.shape[1])
        sa.append(ga[n, ia])
        sb.append(gb[n, ib])
    k = np.repeat(np.arange(max(len(P) - 1, 0)), len(ga))
    a, b = closest_approach(P, k, k + 1, np.concatenate(sa), np.concatenate(sb),
                            closed=closed)
    return k, a, b


@functools.lru_cache(maxsize=16)
def pattern_points(chart, knit, shape):
    """Control points of every course of ``chart`` knitted ``knit`` (flat or
    tube) with loops ``shape``, in the shape's units (a list of (n_f, 3)):
    the jersey's x and y with the depths of its knits and purls
    (``stitches.depths``), opened until no two yarns are within 2.08 r
    (``clearance.open_up``), the yarns of each crossing then as far apart as
    a jersey's (``clearance.hold_crossings``). Computed once for a chart."""
    from knitfem.knit.clearance import hold_crossings, open_up
    from knitfem.knit.fabric import Fabric

    unit = Jersey(chart.rows, chart.cols, shape.r, shape, knit)
    closed = unit.closed
    sym = bspline.junction_symbol(2 * DT)
    X = []
    for f in range(chart.rows):
        P = unit.control_points(f) / unit.scale
        z = stitches.depths(chart.purl, f, len(P), closed, shape.d) / sym
        if closed:      # the flat depths' junction values, wrapped round the tube
            t = T0 + (np.arange(len(P)) - 1) * DT
            z = (np.roll(z, 1) + 4 * z + np.roll(z, -1)) / 6
            P = bspline.periodic_interpolant(unit.centreline(t, f, z) / unit.scale)
        else:
            P[:, 2] = z
        X.append(P)
    fabric = Fabric(X, shape.r, closed=closed)
    fabric.X = open_up(fabric)
    k, sa, sb = interlocks(np.split(fabric.X, fabric.yarn_start[1:-1]), chart.cols,
                           closed)
    fabric.contacts = (k, sa, k + 1, sb)
    two = Jersey(2, 1, shape.r, shape)
    _, sa, sb = two.contacts()
    held = np.linalg.norm(bspline.curve_points(two.control_points(0), sa[:1])
                          - bspline.curve_points(two.control_points(1), sb[:1]))
    opened = hold_crossings(fabric, held, 1e-12 * shape.r)
    return [opened[fabric.yarn_start[f]:fabric.yarn_start[f + 1]]
            for f in range(chart.rows)]


def closest_approach(P, ka, kb, sa, sb, iterations=30, closed=False):
    """Local minimisers of ½|P_ka(s_a) − P_kb(s_b)|² by Newton, vectorised
    over the pairs of curves (ka, kb) of the list of control points P,
    steps capped at a quarter segment (s read modulo the segments on closed
    curves, else kept in them), until the steps are at the round-off of
    the parameters (64 ulps of the largest: Newton's steps then wander at
    1e-13 on a long course, and quadratic convergence gets there in 5 or 6
    iterations)."""
    count = np.array([len(p) for p in P])
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    flat = np.concatenate(P) if len(P) else np.zeros((0, 3))
    nseg = bspline.segments(count, closed)
    na, nb = nseg[ka], nseg[kb]
    tol = 64 * np.finfo(float).eps * max(nseg.max(initial=1), 1)

    def at(k, s, nu):
        j, u = bspline.locate(s, nseg[k], closed)
        idx = start[k][:, None] + bspline.span(j, count[k][:, None], closed)
        return np.einsum("qa,qai->qi", bspline.basis(u, nu), flat[idx])

    for _ in range(iterations):
        D = at(ka, sa, 0) - at(kb, sb, 0)
        A1, A2 = at(ka, sa, 1), at(ka, sa, 2)
        B1, B2 = at(kb, sb, 1), at(kb, sb, 2)
        g = np.stack([np.sum(D * A1, -1), -np.sum(D * B1, -1)], -1)
        H = np.empty(g.shape + (2,))
        H[:, 0, 0] = np.sum(A1 * A1 + D * A2, -1)
        H[:, 1, 1] = np.sum(B1 * B1 - D * B2, -1)
        H[:, 0, 1] = H[:, 1, 0] = -np.sum(A1 * B1, -1)
        step = np.clip(np.linalg.solve(H, g[..., None])[..., 0], -0.25, 0.25)
        sa, sb = sa - step[:, 0], sb - step[:, 1]
        sa, sb = (np.mod(sa, na), np.mod(sb, nb)) if closed else \
            (np.clip(sa, 0, na), np.clip(sb, 0, nb))
        if np.abs(step).max(initial=0.0) < tol:
            break
    return sa, sb


def min_yarn_distance(curves, samples_per_segment=8):
    """Smallest centreline distance between two different yarns.

    ``curves`` are the yarns as open splines (``curves.Curves``), each
    sampled ``samples_per_segment`` times a segment; the samples of every
    later yarn are matched to a k-d tree of yarn f. Returns (distance, f, g).
    """
    from scipy.spatial import cKDTree          # on first use: 40 ms of import

    sampled = curves.samples(samples_per_segment)
    pts, start = sampled.points, sampled.start
    best = (np.inf, -1, -1)
    for f in range(curves.nyarn - 1):
        d, _ = cKDTree(pts[start[f]:start[f + 1]]).query(pts[start[f + 1]:], k=1)
        i = np.argmin(d)
        if d[i] < best[0]:
            best = (d[i], f, sampled.yarn[start[f + 1] + i])
    return best


HOLDS = ("top", "side", "corner")


def jersey_fabric(jersey, hold=None):
    """The ``Fabric`` of a jersey, held (fixed points) by ``hold``: "top" the
    loop heads of the top course, "side" the heads of the first stitch of
    every course, "corner" the head of the top course's first stitch, or
    None (free)."""
    from knitfem.knit.fabric import Fabric

    X = np.stack([jersey.control_points(f) for f in range(jersey.rows)])
    k, sa, sb = jersey.contacts()
    fab = Fabric(X, jersey.radius, contacts=(k, sa, k + 1, sb), closed=jersey.closed)
    if jersey.rest is not None:
        fab = jersey.rest.apply(fab)
    top = jersey.rows - 1
    heads = jersey.heads(top)
    if hold == "top":
        fab.fixed = (np.full(len(heads), top), heads)
    elif hold == "side":
        fab.fixed = (np.arange(jersey.rows), np.full(jersey.rows, heads[0]))
    elif hold == "corner":
        fab.fixed = (np.array([top]), heads[:1])
    elif hold is not None:
        raise ValueError(f"hold {hold!r}: use one of {', '.join(HOLDS)}")
    return fab
