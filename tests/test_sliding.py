"""Sliding crossings: g at the closest approach s*(ε), its exact gradient and
Hessian (s* re-solved at every finite-difference point), frame
indifference, and a yarn that slides through a crossing without friction.
The model tests run serial and under mpirun (COMM_WORLD)."""

import numpy as np
import pytest
import scipy.sparse as sp
from petsc4py import PETSc

from helpers import (COMM, central, constraints_off_rest, curvature_and_force, gather,
                     jersey, run, state)
from knitfem.cli.scenes import rotation
from knitfem.contact import sliding
from knitfem.knit.fabric import Fabric
from knitfem.model.full import FullModel, Material
from knitfem.yarn import bspline
from solvers.integrators import BackwardEuler


@pytest.fixture(scope="module")
def model():
    m = FullModel(COMM, jersey(4, 3, hold="top"), Material(), contacts="sliding")
    yield m
    m.destroy()


def perturbed(model, seed, amplitude):
    rng = np.random.default_rng(seed)
    return model.fabric.X + amplitude * rng.standard_normal(model.fabric.X.shape)


def residual(model, x):
    g = model.C.createVecLeft()
    model.constraint_residual(x, g)
    return gather(COMM, g)


def crossing_residual(crossings, P):
    """max |r·T_a|, |r·T_b| over the crossings at their last s*, in m²."""
    r = crossings._geometry(P, crossings.s_star)[0]
    return np.abs(np.einsum("nd,njd->nj", r, crossings._chords(P))).max(initial=0.0)


def test_one_row_a_crossing_that_holds_at_rest_and_under_rigid_motions(model):
    contact = np.repeat(model.constraint_kind, model.constraints.nrows) == "contact"
    assert model.constraints.rows == 1
    assert contact.sum() == 2 * 3 * (4 - 1)            # one row a crossing
    assert np.abs(residual(model, model.rest_state())).max() < 1e-18
    X = perturbed(model, 1, 2e-5)
    g0 = residual(model, state(model, X))
    centre = X.reshape(-1, 3).mean(axis=0)
    for turn in [(90, 0, 0), (0, 45, 0), (30, -60, 120)]:
        Y = (X - centre) @ rotation(turn).T + centre + np.array([0.3, -0.1, 0.2])
        g = residual(model, state(model, Y))
        # a distance: rigid motions change it by round-off (measured 1e-16 m
        # of g ≈ 4e-5 m)
        assert np.abs(g[contact] - g0[contact]).max() < 1e-15
        assert np.abs(g[~contact]).max() > 1e-3        # world holds do care


def test_crossing_conditions_hold_after_every_evaluation(model):
    asm = model.constraints
    for seed in (2, 3):
        x = state(model, perturbed(model, seed, 2e-5))
        for evaluate in (lambda: residual(model, x),
                         lambda: model.constraint_jacobian(x),
                         lambda: model.stiffness(x, model.C.createVecLeft(), 1.0)):
            evaluate()
            P = asm._points(x)
            # |r| |t| ≈ 1e-3 · 2e-3 m² (measured 9.6e-21 m², 1 and 2 ranks)
            assert crossing_residual(asm.local, P[asm.ghost_c]) < 8e-20
        # the crossings reaching the tangent's rows: evaluated by the tangent
        assert crossing_residual(asm.reaching, P[asm.ghost_r]) < 8e-20  # measured 9.6e-21


def finite_difference_errors(model, x, seed):
    """Relative errors of C dx and Σ μ_i ∇²g_i dx against central
    differences whose states re-solve s*, at h = 1e-2 and 1e-3."""
    dx = state(model, perturbed(model, seed, 1e-5))
    dx.axpy(-1.0, model.rest_state())
    Cdx = model.C.createVecLeft()
    model.constraint_jacobian(x).mult(dx, Cdx)
    exact = gather(COMM, Cdx)
    hess, force = curvature_and_force(model, x, dx, seed + 1)
    errors = []
    for h in (1e-2, 1e-3):
        fd = central(lambda y: residual(model, y), x, dx, h)
        fdH = central(force, x, dx, h)
        errors.append((np.abs(fd - exact).max() / np.abs(exact).max(),
                       np.abs(fdH - hess).max() / np.abs(hess).max()))
    return errors


def test_gradient_and_hessian_against_finite_differences(model):
    """C = ∂g/∂ε and Σ μ_i ∇²g_i = ∂(Cᵀμ)/∂ε by central differences whose
    states re-solve s*: errors fall as h² (measured 4.1e-8 and 3.5e-8
    relative at h = 1e-2, 100 × less at 1e-3)."""
    x = state(model, perturbed(model, 4, 2e-5))
    (g1, h1), (g2, h2) = finite_difference_errors(model, x, 5)
    assert g1 < 5e-7 and h1 < 5e-7
    assert g2 < 3e-2 * g1 + 1e-9 and h2 < 3e-2 * h1 + 1e-9       # O(h²)


def test_crossings_numpy_hessian_matches_gradient_differences():
    """The vectorised kernels alone: ∇²g dP = (∇g(P + h dP) − ∇g(P − h dP))/2h."""
    c = sliding.crossings(jersey(3, 3))
    rng = np.random.default_rng(7)
    P = c.X + 2e-5 * rng.standard_normal(c.X.shape)
    dP = 1e-5 * rng.standard_normal(P.shape)
    H = c.hessians(P)
    h = 1e-3
    fd = (c.gradients(P + h * dP) - c.gradients(P - h * dP))[:, 0] / (2 * h)
    exact = np.einsum("nab,nb->na", H, dP.reshape(c.count, -1))
    # measured 5.5e-10 relative (O(h²)); H symmetric to round-off (4.4e-16)
    assert np.abs(fd.reshape(c.count, -1) - exact).max() < 4e-9 * np.abs(exact).max()
    assert np.abs(H - H.transpose(0, 2, 1)).max() < 4e-15 * np.abs(H).max()


def test_a_crossing_held_at_its_window_end_has_the_derivatives_of_its_g():
    """Where s* is held at an end of its window (yarn b slid along itself
    past the window, its side clamped) g is that of a fixed s_b and a free
    s_a: C and ∇²g by central differences of g and C, whose states solve s*
    again (measured 1.1e-11 and 7.6e-11 relative at h = 1e-3, O(h²); 0.84
    and 1.1 with the interior's η and S kept there)."""
    c = sliding.crossings(two_straight_yarns())
    P = c.X.copy()
    P[:, c.width:, 1] += 2.5e-3                  # yarn b 2.5 segments along y
    rng = np.random.default_rng(5)
    P += 2e-5 * rng.standard_normal(P.shape)
    dP = 1e-5 * rng.standard_normal(P.shape)
    assert c.held(c.solve(P)).tolist() == [[False, True]]
    gradient, hessian = derivative_errors(c, P, dP)
    assert gradient < 1e-10 and hessian < 5e-10


def derivative_errors(c, P, dP, h=1e-3):
    """Relative errors of crossings c's ∇g·dP and ∇²g dP at the points P
    against central differences of g and ∇g (each state solving s* again)."""
    grad, H = c.gradients(P)[:, 0].reshape(c.count, -1), c.hessians(P)
    dg = (c.values(P + h * dP) - c.values(P - h * dP))[:, 0] / (2 * h)
    exact = np.einsum("na,na->n", grad, dP.reshape(c.count, -1))
    gradient = abs(dg - exact).max() / abs(exact).max()
    fd = (c.gradients(P + h * dP) - c.gradients(P - h * dP))[:, 0] / (2 * h)
    exact = np.einsum("nab,nb->na", H, dP.reshape(c.count, -1))
    return gradient, np.abs(fd.reshape(c.count, -1) - exact).max() / np.abs(exact).max()


def two_straight_yarns(delta=1e-3, spacing=1e-3, ncp=16, angle=90.0):
    """Yarn 0 along x, yarn 1 at ``angle`` degrees to it (along y by
    default) at height delta, crossing at their middles."""
    t = (np.arange(ncp) - (ncp - 1) / 2) * spacing
    X = np.zeros((2, ncp, 3))
    X[0, :, 0] = t
    X[1, :, :2] = np.outer(t, [np.cos(np.radians(angle)), np.sin(np.radians(angle))])
    X[1, :, 2] = delta
    mid = np.array([(ncp - 3) / 2])
    return Fabric(X, 2.5e-4, contacts=(np.array([0]), mid, np.array([1]), mid))


def turned_about_z(P, c, angle):
    """The points P of c's windows with yarn b's turned by ``angle``
    degrees about the z axis through the origin."""
    Q = P.copy()
    Q[:, c.width:] = Q[:, c.width:] @ rotation((0, 0, angle)).T
    return Q


def test_a_crossing_of_nearly_parallel_yarns_locks_and_slides_again_when_they_part():
    """Yarns 5° apart: the crossing locks at commit (its point along them
    ill-defined) and g is that of a fixed s, its derivatives by central
    differences (measured 4.5e-12 and 7.1e-12 relative at h = 1e-3, O(h²)).
    Turned 30° apart it slides again, re-anchored so that s* stays where
    it was locked and the crossing conditions hold there."""
    fab = two_straight_yarns(angle=5.0)
    c = sliding.crossings(fab)
    rng = np.random.default_rng(3)
    P = c.X + 2e-5 * rng.standard_normal(c.X.shape)
    c.commit(P)
    assert c.locked.tolist() == [True]
    s = c.s.copy()
    dP = 1e-5 * rng.standard_normal(P.shape)
    Q = P + 10 * dP
    assert np.array_equal(c.solve(Q), s)                    # held at s
    r = c._geometry(Q, s, False)[0]
    assert c.values(Q)[0, 0] == pytest.approx(
        (r @ r[0] - c.delta[0]**2) / (2 * c.delta[0]), rel=1e-15, abs=0)
    gradient, hessian = derivative_errors(c, P, dP)
    assert gradient < 3e-11 and hessian < 5e-11
    R = turned_about_z(P, c, 25.0)
    c.commit(R)
    assert c.locked.tolist() == [False]
    assert np.array_equal(c.s, s)
    # s* where it was locked, to round-off (measured 8.9e-16 segments)
    assert np.abs(c.solve(R) - s).max() < 8e-15
    assert crossing_residual(c, R) < 5e-22                # m², measured 5.3e-23
    c.commit(turned_about_z(P, c, -0.5))                   # 4.5° apart: locks again
    again = sliding.crossings(fab)                          # a checkpoint keeps it
    again.set_state(c.state(), fab.X)
    assert again.locked.tolist() == [True]


@pytest.mark.parametrize("v,n,ncp", [(0.05, 20, 16), (0.5, 30, 40)])
def test_yarn_pulled_lengthwise_slides_through_a_crossing(v, n, ncp):
    """Yarn 0, straight, set moving along itself glides through the crossing
    untouched: no force, uniform motion, kinetic energy kept, the crossing
    held, slid by v t. Over 15 segments (five windows of 3) the windows
    move to follow it and C's pattern is laid out again."""
    fab = two_straight_yarns(ncp=ncp)
    m = FullModel(PETSc.COMM_SELF, fab, Material(gravity=0.0), contacts="sliding")
    rest = m.sliding.first.copy()
    dt = 1e-3                                        # 1 mm segments
    shape = (2, -1, 3)                               # two yarns of one length
    v0 = np.zeros(fab.X.shape).reshape(shape)
    v0[0, :, 0] = v
    _, x, vel = run(m, BackwardEuler, dt, n, v0.ravel())
    moved = (x.getArray().reshape(fab.X.shape) - fab.X).reshape(shape)
    # uniform motion and kinetic energy kept to round-off (measured 1.4e-17 m;
    # 3.6e-18 and 1.1e-17 m; 4.6e-15 m/s; 8.9e-16 relative)
    assert np.abs(moved[0, :, 0] - v * n * dt).max() < 1e-16
    assert np.abs(moved[0, :, 1:]).max() < 3e-17 and np.abs(moved[1]).max() < 1e-16
    assert np.abs(vel.getArray().reshape(shape) - v0).max() < 4e-14
    kinetic = 0.5 * vel.dot(m.M * vel)
    assert abs(kinetic / (0.25 * m.total_mass * v * v) - 1) < 8e-15
    g = m.C.createVecLeft()
    m.constraint_residual(x, g)
    assert np.abs(g.getArray()).max() < 2e-18             # measured 2.1e-19 m
    report = m.slide_report(x)
    assert abs(report["max_slide_m"] - v * n * dt) < 1.5e-17  # measured 1.7e-18 m
    # a move for every segment slid, yarn 1's window kept, yarn 0's centred
    # on s before the last step (a margin of 1: s in the middle segment)
    segments = v * n * dt / 1e-3
    assert report["slide_window_moves"] >= int(segments) - 1
    c = m.constraints.local
    assert c.first[0, 1] == rest[0, 1]
    assert abs(c.s[0, 0] - c.first[0, 0] - 1.5) <= 0.5 + v * dt / 1e-3 + 1e-9
    m.destroy()


def ring_and_line(n=16, radius=5e-3, delta=1e-3):
    """Yarn 0 a closed ring of n control points about z, yarn 1 straight
    along z, crossing it at δ outside the middle of the ring's segment 0
    (yarns of their own lengths)."""
    angle = 2 * np.pi * np.arange(n) / n
    ring = radius * np.stack([np.cos(angle), np.sin(angle), 0 * angle], axis=1)
    p = bspline.curve_points(ring, 0.5, closed=True)
    out = np.array([p[0], p[1], 0.0]) / np.hypot(p[0], p[1])
    line = p + delta * out + np.outer(np.arange(-4, 5) * 2e-3, [0, 0, 1])
    contacts = (np.array([0]), np.array([0.5]), np.array([1]), np.array([3.0]))
    return Fabric([ring, line], 2.5e-4, contacts=contacts,
                  closed=np.array([True, False]))


def test_a_ring_turned_slides_round_its_crossing():
    """The ring turned about its axis a quarter segment at a time, past its
    seam and round more than once: the crossing stays where it is in space
    while s_a goes round the ring (the reference tangents turned with the
    ring lag by up to half a segment), its window following it through the
    seam on the ring's own control points; the slide is the arc turned."""
    fab = ring_and_line()
    m = FullModel(PETSc.COMM_SELF, fab, Material(gravity=0.0), contacts="sliding")
    n, quarters = 16, 80                                 # 20 segments
    ring = fab.X[:n]
    error = 0.0
    for k in range(1, quarters + 1):
        a = 2 * np.pi / n * k / 4
        turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0],
                         [0, 0, 1]])
        P = fab.X.copy()
        P[:n] = ring @ turn.T
        x = state(m, P)
        m.begin_step(x)
        c = m.constraints.local
        error = max(error, abs(np.mod(c.s[0, 0] - 0.5 + k / 4 + n / 2, n) - n / 2))
        assert abs(c.s[0, 1] - 3.0) < 4e-15            # the line's middle: measured 0
    # s_a within the reference tangents' lag (measured 0.26 segments); a
    # move for every segment turned (20), the window now across the seam
    assert error < 0.5 and m.window_moves >= quarters // 4 - 1
    window = c.cols[0, :6]
    assert window.max() < n and (np.diff(window) < 0).any()
    x8, w8 = bspline.gauss(8)
    segment = w8 @ np.linalg.norm(bspline.basis(x8, 1) @ ring[:4], axis=-1)
    turned = quarters / 4 - np.mod(c.s[0, 0] - 0.5 + quarters / 4 + n / 2, n) + n / 2
    # the arc turned, segments of one length by symmetry (measured 7e-7
    # relative: 8-point Gauss over pieces across segment ends)
    assert m.slide_report(x)["max_slide_m"] == pytest.approx(turned * segment,
                                                               rel=5e-6)
    m.destroy()


def shifted_windows(m, by):
    """Window starts moved by ``by`` segments where the crossing's segment
    stays inside (and an open yarn's window on the yarn)."""
    c = m.sliding
    k = np.floor(c.s).astype(int)
    first = c.first + by
    ok = (k - first >= 0) & (k - first <= c.width - 4) & (first >= 0) \
        & (first <= c.nseg - c.width + 3)
    return np.where(ok, first, c.first)


def test_moved_windows_keep_g_and_stay_exact():
    """Windows moved at a state keep g there, rigid motions still keep it,
    and C and Σμ∇²g pass the finite-difference check on the new pattern."""
    m = FullModel(COMM, jersey(4, 3, hold="top"), Material(), contacts="sliding")
    x = state(m, perturbed(m, 11, 2e-5))
    g0 = residual(m, x)
    m.constraints.commit(x)
    before = m.sliding.cols.copy()
    assert m.move_windows(x, shifted_windows(m, -1)) > 0 and m.window_moves == 1
    assert (m.sliding.cols != before).any()
    assert m.begin_step(x)                           # a new Newton matrix
    # s* and g unchanged (measured 0 m)
    assert np.abs(residual(m, x) - g0).max() < 1e-19
    contact = np.repeat(m.constraint_kind, m.constraints.nrows) == "contact"
    X = perturbed(m, 11, 2e-5)
    centre = X.mean(axis=0)
    Y = (X - centre) @ rotation((30, -60, 120)).T + centre + 0.1
    # measured 2.3e-17 m
    assert np.abs(residual(m, state(m, Y))[contact] - g0[contact]).max() < 2e-16
    (g1, h1), (g2, h2) = finite_difference_errors(m, x, 12)
    # measured 4.6e-8 and 8.1e-8 at h = 1e-2, O(h²)
    assert g1 < 5e-7 and h1 < 1e-6
    assert g2 < 3e-2 * g1 + 1e-9 and h2 < 3e-2 * h1 + 1e-9
    m.destroy()


def test_fixed_crossing_drags_the_other_yarn():
    fab = two_straight_yarns()
    m = FullModel(PETSc.COMM_SELF, fab, Material(gravity=0.0))
    v0 = np.zeros(fab.X.shape).reshape(2, -1, 3)
    v0[0, :, 0] = 0.05
    _, x, _ = run(m, BackwardEuler, 1e-3, 20, v0.ravel())
    moved = (x.getArray().reshape(fab.X.shape) - fab.X).reshape(2, -1, 3)
    assert np.abs(moved[1]).max() > 1e-2 * 0.05 * 20 * 1e-3
    m.destroy()


@pytest.mark.parametrize("moved", [False, True])
def test_parallel_equals_serial(moved):
    """g, C and K + Σμ∇²g off the rest under mpirun equal one rank's, with
    the windows where they started or moved."""
    fab = jersey(5, 3, hold="top")
    par, ser = (FullModel(comm, fab, Material(), contacts="sliding")
                for comm in (PETSc.COMM_WORLD, PETSc.COMM_SELF))
    for m in (par, ser) if moved else ():
        x = m.start_state()
        m.constraints.commit(x)
        assert m.move_windows(x, shifted_windows(m, -1)) > 0
    rng = np.random.default_rng(8)
    full = 4e-2 * fab.radius * rng.standard_normal(3 * par.layout.ncp)
    nrow = par.C.getSize()[0]
    mu_full = rng.standard_normal(nrow)
    out = []
    for m in (par, ser):
        g, K = constraints_off_rest(m, full, mu_full)
        out.append((g.getArray().copy(), K.getValuesCSR(), m.C.getValuesCSR(),
                    K.getOwnershipRange()))
    (g, K, C, (lo, hi)), (gs, Ks, Cs, _) = out
    a, b = par.C.getOwnershipRange()
    # the same Newton iterations for s* on either side: equal to round-off
    # (measured 0, 1 and 2 ranks; allowed: round-off of the ~1e-2 m positions)
    assert np.allclose(g, gs[a:b], rtol=0, atol=1e-15 * np.abs(fab.X).max())
    for (ip, ix, vals), (sip, six, svals), rows, n in (
            (K, Ks, (lo, hi), par.K.getSize()), (C, Cs, (a, b), par.C.getSize())):
        mine = sp.csr_matrix((vals, ix, ip), shape=(rows[1] - rows[0], n[1]))
        ref = sp.csr_matrix((svals, six, sip), shape=n)[rows[0]:rows[1]]
        assert abs(mine - ref).max() <= 1e-14 * abs(ref).max()     # measured 0
    par.destroy()
    ser.destroy()



def test_crossings_hold_the_fabric_separation():
    """A natural fabric's crossings hold its separation (2r: touching), not
    the template's."""
    fab = jersey(3, 3)
    rest = sliding.crossings(fab).delta
    fab.separation = 2 * fab.radius
    held = sliding.crossings(fab).delta
    assert np.all(rest > 1.04 * held) and np.all(held == 2 * fab.radius)


def test_slide_margin_sets_the_windows():
    """-knit_slide_margin m: windows of 4 + 2m control points a side."""
    from knitfem.cli.commands import build_system
    from knitfem.cli.options import KnitOptions

    opts = PETSc.Options()
    opts.setValue("-knit_contacts", "sliding")
    opts.setValue("-knit_slide_margin", "3")
    try:
        m = build_system(PETSc.COMM_WORLD, KnitOptions(), jersey(3, 4), Material())
    finally:
        opts.delValue("-knit_contacts")
        opts.delValue("-knit_slide_margin")
    assert m.constraints.local.width == 4 + 2 * 3
    m.destroy()
