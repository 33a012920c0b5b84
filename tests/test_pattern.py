"""Jersey geometry: interpolation of the closed-form curve, contacts, no
penetration at rest."""

import numpy as np
import pytest

from knitfem.yarn import bspline
from knitfem.contact import constraints
from knitfem.knit.pattern import DT, T0, Jersey, jersey_fabric, min_yarn_distance


def test_control_point_count_and_interpolation():
    j = Jersey(3, 5)
    P = j.control_points(1)
    assert P.shape == (8 * 5 + 3, 3)
    s = np.arange(j.nseg + 1.0)
    assert np.allclose(bspline.curve_points(P, s), j.centreline(T0 + s * DT, 1),
                       rtol=0, atol=7e-14 * j.scale)  # measured 3.5e-18


@pytest.mark.parametrize("rows,cols", [(2, 1), (4, 6)])
def test_no_penetration_at_rest(rows, cols):
    j = Jersey(rows, cols, radius=1e-3)
    fab = jersey_fabric(j)
    d, f, g = min_yarn_distance(fab.curves(fab.X), 16)
    assert f != g
    assert d >= 2 * j.radius


def test_contacts_are_closest_approach_between_neighbours():
    j = Jersey(3, 4)
    k, sa, sb = j.contacts()
    assert len(k) == 2 * 4 * 2
    Pa, Pb = j.control_points(0), j.control_points(1)
    D = bspline.curve_points(Pa, sa[:8]) - bspline.curve_points(Pb, sb[:8])
    # stationarity: the offset is normal to both curves
    # measured 1e-14
    assert np.abs(np.sum(D * bspline.curve_points(Pa, sa[:8], 1), -1)).max() < 2e-13 * j.scale**2
    # measured 9.9e-15
    assert np.abs(np.sum(D * bspline.curve_points(Pb, sb[:8], 1), -1)).max() < 1e-13 * j.scale**2
    # and a local minimum: nudging either parameter moves the points apart
    dist = np.linalg.norm(D, axis=-1)
    for da, db in ((0.05, 0), (-0.05, 0), (0, 0.05), (0, -0.05)):
        Dn = bspline.curve_points(Pa, sa[:8] + da) - bspline.curve_points(Pb, sb[:8] + db)
        assert np.all(np.linalg.norm(Dn, axis=-1) > dist)
    assert np.all(dist >= 2 * j.radius)


def test_every_constraint_row_evaluates_its_point():
    """The contacts' factors are the separation and tangents of the paired
    curve points; the holds evaluate the top course's loop heads."""
    j = Jersey(3, 2)
    fab = jersey_fabric(j, hold="top")
    contacts, holds = constraints.build(fab)
    X = fab.X.reshape(-1, 3)
    # measured 8.7e-18 j.scale and 0
    assert np.abs(contacts.values(X[contacts.cols])).max() < 1e-16 * j.scale
    assert np.abs(holds.residual(X)).max() < 5e-16 * j.scale
    ya, sa, yb, sb = fab.contacts
    P = [fab.yarn(f) for f in range(fab.nyarn)]
    r, t_a = contacts.factors(X[contacts.cols])[1][:, :2].transpose(1, 0, 2)
    sep = np.stack([bspline.curve_points(P[a], s) - bspline.curve_points(P[b], t)
                    for a, s, b, t in zip(ya, sa, yb, sb)])
    tan = np.stack([bspline.curve_points(P[a], s, 1) for a, s in zip(ya, sa)])
    assert np.allclose(r, sep, rtol=0, atol=7e-18)  # measured 6.5e-19
    assert np.allclose(t_a, tan, rtol=0, atol=3e-15 * np.abs(tan).max())  # measured 0
    heads = bspline.curve_points(P[2], j.heads(2))
    # measured 0
    assert np.allclose(holds.rhs[holds.kind == "fixed"], heads, rtol=0, atol=5e-16 * j.scale)
    assert np.all(holds.owner == 2)


# --- knit and purl, per stitch ---------------------------------------------

from petsc4py import PETSc  # noqa: E402

from helpers import COMM, gather, models, run  # noqa: E402
from knitfem.contact.gaps import YarnGaps  # noqa: E402
from knitfem.knit.chart import Chart, named_chart  # noqa: E402
from knitfem.model.full import FullModel, Material  # noqa: E402
from knitfem.cli.scenes import rotation  # noqa: E402
from solvers.integrators import SymplecticEuler  # noqa: E402

BORDER = Chart.from_text(["KKKKK", "PPPPP", "KKPPK", "KKPPK", "PPPPP"])
PATTERNS = ["rib1x1", "rib2x2", "garter", "seed", "border"]


def knit(name, rows=4, cols=5, shape="flat"):
    chart = BORDER if name == "border" else named_chart(name, rows, cols)
    return Jersey(chart.rows, chart.cols, knit=shape, chart=chart)


def unwrapped(j, P):
    """(u, y, depth) of points P (..., 3): x, y, z on a flat knit; on a
    tube the arclength round the mid-circle, y and the radius past it."""
    if not j.closed:
        return P
    R = j.cols * j.scale
    theta = np.arctan2(P[..., 0], P[..., 2])
    return np.stack([R * theta, P[..., 1], np.hypot(P[..., 0], P[..., 2]) - R], -1)


def projected_crossing(j, Pa, Pb, sa, sb):
    """Where the two curves cross seen through the thickness (u, y equal), by
    Newton with central differences from (sa, sb): (sa, sb, depth_a − depth_b)."""
    period = 2 * np.pi * j.cols * j.scale

    def uy(P, s):
        return unwrapped(j, bspline.curve_points(P, s, closed=j.closed))[:, :2]

    def gap(sa, sb):
        d = uy(Pa, sa) - uy(Pb, sb)
        if j.closed:
            d[:, 0] = np.mod(d[:, 0] + period / 2, period) - period / 2
        return d

    h = 1e-6
    for _ in range(30):
        F = gap(sa, sb)
        J = np.stack([(gap(sa + h, sb) - gap(sa - h, sb)) / (2 * h),
                      (gap(sa, sb + h) - gap(sa, sb - h)) / (2 * h)], -1)
        step = np.linalg.solve(J, F[..., None])[..., 0]
        sa, sb = sa - step[:, 0], sb - step[:, 1]
    assert np.abs(gap(sa, sb)).max() < 1e-13 * j.scale  # measured 1.6e-14 j.scale
    depth = [unwrapped(j, bspline.curve_points(P, s, closed=j.closed))[:, 2]
             for P, s in ((Pa, sa), (Pb, sb))]
    return sa, sb, depth[0] - depth[1]


@pytest.mark.parametrize("shape", ["flat", "tube"])
@pytest.mark.parametrize("name", PATTERNS)
def test_every_stitch_crosses_its_parent_as_the_chart_asks(name, shape):
    """Seen through the thickness, stitch j of course k + 1 crosses its
    parent four times: its legs pass its parent's head (A, at t ≈ 2πj ±
    0.32 on the parent, ±1.75 on the stitch) and its sinkers its parent's
    legs (B, ±1.39 and ±2.82). A knit's legs lie in front of (−z of) the
    head and its sinkers behind the legs; a purl's the other way round."""
    j = knit(name, shape=shape)
    P = [j.control_points(f) for f in range(j.rows)]
    sigma = 1 - 2 * j.chart.purl.astype(int)
    stitch = 2 * np.pi * np.arange(j.cols)
    for k in range(j.rows - 1):
        for side in (-1, 1):
            for kind, (ta, tb) in (("A", (0.32, 1.75)), ("B", (1.39, 2.82))):
                *_, dz = projected_crossing(j, P[k], P[k + 1],
                                            j.parameter(stitch + side * ta),
                                            j.parameter(stitch + side * tb))
                behind = sigma[k + 1] if kind == "A" else -sigma[k + 1]
                assert np.all(np.sign(dz) == behind), (k, side, kind)


@pytest.mark.parametrize("shape", ["flat", "tube"])
@pytest.mark.parametrize("name", PATTERNS)
def test_no_yarn_through_another_at_rest(name, shape):
    """Different yarns, and parts of one yarn more than 8 r apart along it,
    keep at least 2r apart (16 samples a segment), and the two yarns of a
    crossing are its closest approach there, as far apart as a jersey's."""
    held_apart(knit(name, shape=shape))


def test_a_large_seed_keeps_its_interlocks():
    """The 10×10 seed's template moves farthest when it is opened (3.5 r):
    its courses keep every interlock (opened without a bound on a round's
    moves they slipped out of 62 of 180)."""
    held_apart(knit("seed", 10, 10))


def held_apart(j):
    """The template of ``j`` keeps its yarns 2r apart and its crossings as
    far apart as a jersey's, at their stitches."""
    fab = jersey_fabric(j)
    S = fab.curves(fab.X).samples(16)
    assert YarnGaps(S, j.radius).frame(S) == 1.0
    ya, sa, yb, sb = fab.contacts
    assert len(ya) == 2 * j.cols * (j.rows - 1)
    A = np.stack([bspline.curve_points(fab.yarn(a), s, closed=j.closed)
                  for a, s in zip(ya, sa)])
    B = np.stack([bspline.curve_points(fab.yarn(b), s, closed=j.closed)
                  for b, s in zip(yb, sb)])
    dist = np.linalg.norm(A - B, axis=-1) / (2 * j.radius)
    # a jersey's 1.0431 × 2r; measured 1.039 to 1.0431
    assert np.all(np.abs(dist - 1.0431) < 0.02)
    # each crossing lies at its stitch: s_a within 3 of 8 segments of its head
    head = j.parameter(2 * np.pi * np.repeat(np.tile(np.arange(j.cols), j.rows - 1), 2))
    assert np.abs(sa - head).max() < 3


def test_a_purl_is_the_knit_mirrored_through_the_mid_plane():
    """A chart of purls only (reverse jersey) is the jersey with z → −z, its
    crossings at the same parameters, their rest offsets flipped in z."""
    jersey, reverse = Jersey(3, 4), Jersey(3, 4, chart=Chart(np.ones((3, 4), bool)))
    X, Y = jersey_fabric(jersey), jersey_fabric(reverse)
    # the jersey's depths d cos 2t_i / J are computed, the purl's set: measured 4.1e-18
    assert np.allclose(Y.X, X.X * [1, 1, -1], rtol=0, atol=3e-17)
    for a, b in zip(X.contacts, Y.contacts):
        assert np.allclose(a, b, rtol=0, atol=1e-13)  # measured 1.4e-14
    ca, _ = constraints.build(X)
    cb, _ = constraints.build(Y)
    ra, rb = (c.factors(F.X[c.cols])[0][:, 0] for c, F in ((ca, X), (cb, Y)))
    # the jersey's offsets lie in its plane (z 1.8e-17 m of 1.0e-3): measured 2.6e-17
    assert np.allclose(rb, ra * [1, 1, -1], rtol=0, atol=2e-16)


@pytest.mark.parametrize("name", ["rib1x1", "seed"])
def test_crossings_hold_at_rest_and_under_rigid_motions(name):
    """|Cx − d| at round-off at the rest of a pattern, and with the pattern
    started turned; a free one turned strains nothing (E_el at round-off)."""
    fab = jersey_fabric(knit(name)).started_turned(rotation((30, -60, 120)))
    model = FullModel(COMM, fab, Material())
    try:
        for x in (model.rest_state(), model.start_state()):
            g = model.C.createVecLeft()
            model.constraint_residual(x, g)
            # measured 3.4e-18 m (turned), 9.7e-20 m (rest)
            assert g.norm(PETSc.NormType.INFINITY) < 5e-14 * fab.radius
            assert model.elastic_energy(x) < 1e-28  # measured 8.6e-30 J
    finally:
        model.destroy()


@pytest.mark.parametrize("name", ["rib1x1", "seed"])
def test_reduced_model_is_exact_in_the_range_of_gamma(name):
    """The reduced model of a pattern reproduces affine maps of its rest, and
    a rigid translation runs the same as the full model's (round-off)."""
    fab = jersey_fabric(knit(name, 3, 3))
    full, red = models(COMM, fab, Material(EA=5.0, EI=1e-6), lod=(4, 4))
    try:
        alpha = red.rest_state()
        q = alpha.getArray().reshape(-1, 3)
        eps0 = gather(COMM, red.full_state(alpha)).reshape(-1, 3)
        assert np.allclose(eps0, fab.X, rtol=0, atol=5e-17)  # measured 5.2e-18
        A = np.array([[1.1, 0.2, -0.1], [0.05, 0.9, 0.3], [0.0, -0.2, 1.2]])
        q[:] = q @ A.T + [1e-3, -2e-3, 5e-4]
        eps = gather(COMM, red.full_state(alpha)).reshape(-1, 3)
        # measured 6.9e-18
        assert np.allclose(eps, eps0 @ A.T + [1e-3, -2e-3, 5e-4], rtol=0, atol=5e-17)
        v = [0.01, 0.02, -0.005]
        _, xf, _ = run(full, SymplecticEuler, 5e-7, 15, np.tile(v, fab.npoints))
        _, xr, _ = run(red, SymplecticEuler, 5e-7, 15,
                       np.tile(v, red.embedding.volume.size))
        ef, er = gather(COMM, xf), gather(COMM, red.full_state(xr))
        # measured 1.6e-13 r on one rank, 2.1e-10 to 2.7e-10 r on two
        assert np.allclose(ef, er, rtol=0, atol=2e-9 * fab.radius)
        assert np.abs(ef - fab.X.ravel()).max() > 1e-7  # it moved: 1.5e-7 m
    finally:
        red.destroy()
        full.destroy()


def test_a_pattern_on_two_ranks_equals_one():
    """Mass, constraint Jacobian, and the forces off the rest of a seed
    pattern: every rank's rows equal one rank's."""
    fab = jersey_fabric(knit("seed", 5, 3), hold="top")
    par = FullModel(COMM, fab, Material())
    ser = FullModel(PETSc.COMM_SELF, fab, Material())
    try:
        shift = 1e-2 * fab.radius * np.random.default_rng(2).standard_normal(fab.X.size)
        out = []
        for m in (par, ser):
            x = m.rest_state()
            lo, hi = x.getOwnershipRange()
            x.getArray()[:] += shift[lo:hi]
            v, f = x.duplicate(), x.duplicate()
            v.zeroEntries()
            m.forces(x, v, f)
            g = m.C.createVecLeft()
            m.constraint_residual(x, g)
            out.append((gather(m.comm, f), gather(m.comm, g), m.M.getRowSum().sum()))
        (f, g, mass), (fs, gs, ms) = out
        assert np.array_equal(g, gs) and np.array_equal(f, fs)  # measured: equal
        assert abs(mass - ms) <= 2e-15 * ms  # measured 2.6e-16 (6.4e-16 before)
    finally:
        par.destroy()
        ser.destroy()
