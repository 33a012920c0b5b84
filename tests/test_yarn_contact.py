"""Yarn–yarn contact: the barrier's derivatives, its invariance, its zero at
rest, its place in the full model (any number of ranks) and the step
filter. Runs serial and under mpirun."""

from dataclasses import replace

import numpy as np
import pytest
from petsc4py import PETSc
from scipy.spatial import cKDTree

from knitfem.contact.yarn_contact import YarnContact, segment_distance
from knitfem.knit.fabric import Fabric
from knitfem.cli.scenes import rotation
from knitfem.knit.pattern import Jersey, jersey_fabric
from knitfem.model.full import FullModel, Material
from solvers.integrators import BackwardEuler

from helpers import COMM, gather, jersey, run, to_scipy

R = 5e-4


def crossing(gap=0.5, nseg=8, hold=False):
    """Two straight yarns crossing at right angles, their centrelines
    2r + ``gap`` r apart at the crossing (yarn 0 above, along x; yarn 1
    below, along y); with ``hold`` both ends of each fixed."""
    ncp = nseg + 3
    t = (np.arange(ncp) - (ncp - 1) / 2) * 4 * R
    z = 0.5 * (2 + gap) * R
    X = np.zeros((2, ncp, 3))
    X[0, :, 0], X[0, :, 2] = t, z
    X[1, :, 1], X[1, :, 2] = t, -z
    fab = Fabric(X, R)
    if hold:
        fab.fixed = (np.array([0, 0, 1, 1]), np.array([0.0, nseg, 0.0, nseg]))
    return fab


def pushed(fab, depth):
    """The crossing's control points with the two middles pushed towards
    each other by ``depth`` r each, smoothly along the yarns."""
    P = fab.X.copy().reshape(2, -1, 3)
    bump = depth * R * np.exp(-np.linspace(-2, 2, P.shape[1]) ** 2)
    P[0, :, 2] -= bump
    P[1, :, 2] += bump
    return P.reshape(-1, 3)


def band_state(yc, fab, deepest=1.0):
    """A state whose closest pair sits in the middle of the band (pushed by
    at most ``deepest``)."""
    lo, hi = 0.0, deepest
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        d = yc.min_distance(pushed(fab, mid))
        lo, hi = (mid, hi) if d > yc.dmin + 0.5 * yc.dhat else (lo, mid)
    return pushed(fab, lo)


def test_segment_distance_cases():
    """Crossing, parallel, end-to-end and point–segment distances."""
    p = np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    q = np.array([[1.0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0]])
    a = np.array([[0.5, -1, 1], [0, 1, 0], [2, 0, 0], [3, 0, 2]])
    b = np.array([[0.5, 1, 1], [1, 1, 0], [3, 0, 0], [3, 0, 2 + 1e-9]])
    d = segment_distance(p, q, a, b)
    assert np.allclose(d, [1.0, 1.0, 1.0, np.hypot(2, 2)], rtol=0, atol=2e-15)  # measured 0


@pytest.mark.parametrize("shape", ["flat", "tube"])
def test_compiled_edge_pairs_are_the_numpy_references(shape):
    """The compiled broad phase (``_pairs.pyx``) finds the numpy reference's
    edge pairs, at its distances, on a seed stitch's template shaken by 0.3 r
    (excluded pairs near crossings, patches along a yarn, a tube's seams),
    and its step filter cuts random moves where the reference does."""
    from knitfem.knit.chart import named_chart

    fab = jersey_fabric(Jersey(6, 8, knit=shape, chart=named_chart("seed", 6, 8)))
    compiled = YarnContact(fab, Material().EI)
    numpy = YarnContact(fab, Material().EI, kernels="numpy")
    rng = np.random.default_rng(0)
    V = compiled.samples(fab.X.reshape(-1, 3) + 0.3 * R * rng.standard_normal((fab.npoints, 3)))
    e, f, d = compiled.close_edges(V, 4 * R, distances=True)
    e_ref, f_ref, d_ref = numpy.close_edges(V, 4 * R, distances=True)
    assert len(e) > 1000 and np.array_equal(e, e_ref) and np.array_equal(f, f_ref)
    assert np.array_equal(d, d_ref)                                    # measured 0
    mid = V[compiled.edges].mean(axis=1)                 # every near pair, filtered or not
    g, h = cKDTree(mid).query_pairs(4 * R, output_type="ndarray").T
    may = compiled.edges_may_touch(g, h)
    assert np.array_equal(may, numpy.edges_may_touch(g, h)) and 0.1 < may.mean() < 0.9
    P0 = fab.X.reshape(-1, 3) + 0.05 * R * rng.standard_normal((fab.npoints, 3))
    for scale in (0.3, 1.0, 3.0):                  # the step filter's advancement
        P1 = P0 + scale * R * rng.standard_normal((fab.npoints, 3))
        t = compiled.step_fraction(P0, P1)
        assert t == numpy.step_fraction(P0, P1) and 0.0 < t < 1.0      # measured equal
    V[3] = np.nan                                  # a state blown up: no pairs
    assert all(len(a) == 0 for a in compiled.close_edges(V, 4 * R, distances=True))
    with pytest.raises(ValueError, match="kernels 'fortran'"):
        YarnContact(fab, Material().EI, kernels="fortran")


def test_zero_at_template_rest():
    """No pair is within the band at the jersey's rest: E_y, its gradient
    and Hessian vanish, and the band sits below the rest clearance."""
    fab = jersey(3, 3)
    yc = YarnContact(fab, Material().EI)
    P = fab.X.reshape(-1, 3)
    assert yc.energy(P) == 0.0
    assert not np.any(yc.gradient(P))
    assert yc.hessian(P).nnz == 0 or not np.any(yc.hessian(P).data)
    assert yc.min_distance(P, 0.5 * R) > yc.dmin + yc.dhat
    assert 0 < yc.dhat <= 0.08 * R


def test_gradient_and_hessian_by_finite_differences():
    """∂E/∂ε and ∂²E/∂ε² (unprojected) against central differences, in the
    band; the projected Hessian is positive semi-definite."""
    fab = crossing()
    yc = YarnContact(fab, Material().EI)
    P = band_state(yc, fab)
    E, g = yc.energy(P), yc.gradient(P)
    assert E > 0
    H = yc.hessian(P, project=False).toarray()
    h = 1e-4 * yc.dhat
    active = np.flatnonzero(np.abs(g) > 1e-6 * np.abs(g).max())
    fd_g, fd_H = [], []
    for i in active:
        e = np.zeros(P.size)
        e[i] = h
        fd_g.append((yc.energy(P + e.reshape(-1, 3)) - yc.energy(P - e.reshape(-1, 3)))
                    / (2 * h))
        fd_H.append((yc.gradient(P + e.reshape(-1, 3))
                     - yc.gradient(P - e.reshape(-1, 3))) / (2 * h))
    # measured: 1.7e-8 and 1.5e-8 of the largest
    assert np.allclose(fd_g, g[active], rtol=0, atol=1e-7 * np.abs(g).max())
    assert np.allclose(np.array(fd_H), H[active], rtol=0,
                       atol=1e-7 * np.abs(H).max())
    Hp = yc.hessian(P).toarray()
    assert np.linalg.eigvalsh(0.5 * (Hp + Hp.T)).min() >= -1e-9 * np.abs(Hp).max()


def test_frame_indifference():
    """A rigid motion changes neither E_y nor the length of its gradient
    (which turns with the fabric)."""
    fab = crossing()
    yc = YarnContact(fab, Material().EI)
    P = band_state(yc, fab)
    c, s = np.cos(0.7), np.sin(0.7)
    Rm = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ \
        np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    Q = P @ Rm.T + np.array([0.01, -0.02, 0.005])
    assert yc.energy(Q) == pytest.approx(yc.energy(P), rel=1.5e-12, abs=0)  # measured 2.0e-13
    gP, gQ = yc.gradient(P).reshape(-1, 3), yc.gradient(Q).reshape(-1, 3)
    # measured 1.2e-13 of the largest
    assert np.allclose(gQ, gP @ Rm.T, rtol=0, atol=1e-12 * np.abs(gP).max())


def test_step_filter_sees_pairs_beyond_its_list():
    """Two yarns 4r of clearance apart (beyond the Verlet list's reach,
    d̂ + margin + skin ≈ 0.6 r) driven 5r each through one another: the
    candidates say nothing, the moving edges' own search cuts the move,
    and no point of the path to the cut comes within dmin."""
    fab = crossing(gap=4.0)
    yc = YarnContact(fab, Material().EI)
    P0 = fab.X.reshape(-1, 3)
    e, _, _ = yc._near(np.asfortranarray(yc.samples(P0)), yc.dmin + yc.dhat + yc.margin)
    assert len(e) == 0                                     # no candidate near
    P1 = pushed(fab, 5.0)
    t = yc.step_fraction(P0, P1)
    assert 0.3 < t < 0.4    # measured 0.379: 3.6r of the 4r closed at ~9.2r (spline samples)
    for tau in np.linspace(0, t, 9)[1:]:
        assert yc.min_distance(P0 + tau * (P1 - P0), reach=8 * R) > yc.dmin


def test_the_verlet_list_follows_the_knits_common_move():
    """The crossing pushed into the band: carried whole by 10 r (50 skins)
    it keeps its Verlet list, and finds the pairs a list made afresh finds;
    pushed further (a relative move of more than half the skin) it makes
    its list again."""
    fab = crossing(gap=0.5)
    yc = YarnContact(fab, Material().EI)
    P = band_state(yc, fab)
    near = yc.segment_pairs(P, yc.margin)
    builds = yc.candidate_builds
    moved = P + np.array([10 * R, -4 * R, 7 * R])
    assert np.array_equal(yc.segment_pairs(moved, yc.margin), near) and len(near)
    assert yc.candidate_builds == builds
    fresh = YarnContact(fab, Material().EI)
    for Q in (moved, pushed(fab, 0.6) + 3 * R):
        assert np.array_equal(yc.segment_pairs(Q, yc.margin),
                              fresh.segment_pairs(Q, fresh.margin))
    assert yc.candidate_builds == builds + 1


def test_step_filter_never_crosses():
    """Random moves of the jersey cut by ``step_fraction``: no point of the
    path comes within dmin; a translation is not cut."""
    fab = jersey(3, 3)
    yc = YarnContact(fab, Material().EI)
    P = fab.X.reshape(-1, 3)
    assert yc.step_fraction(P, P + 3 * R) == 1.0
    rng = np.random.default_rng(3)
    for scale in (0.05, 0.3, 1.0):
        P1 = P + rng.normal(size=P.shape) * scale * R
        t = yc.step_fraction(P, P1)
        assert 0 < t <= 1
        for tau in np.linspace(0, t, 5)[1:]:
            assert yc.min_distance(P + tau * (P1 - P), 2 * R) > yc.dmin


def test_full_model_forces_and_tangent_on_any_ranks():
    """The full model's forces and tangent carry −∂E_y/∂ε and ∂²E_y/∂ε² in
    their rows on every rank (the same as one rank's)."""
    fab = crossing()
    full = FullModel(COMM, fab, Material(gravity=0.0), yarn_contact=True)
    full_off = FullModel(COMM, fab, Material(gravity=0.0))
    yc = full.yarn_contact
    P = band_state(yc, fab)
    x = full.rest_state()
    lo, hi = x.getOwnershipRange()
    x.getArray()[:] = P.ravel()[lo:hi]
    v = x.duplicate()
    v.zeroEntries()
    Q, Q0 = x.duplicate(), x.duplicate()
    full.forces(x, v, Q)
    full_off.forces(x, v, Q0)
    # measured 0 (1 and 2 ranks)
    assert np.allclose(gather(COMM, Q) - gather(COMM, Q0), -yc.gradient(P),
                       rtol=0, atol=1e-15 * np.abs(yc.gradient(P)).max())
    full.begin_step(x)
    # two more states of the same pairs in the band, off the crossing's
    # symmetry (at P the Hessian has 72 nonzeros, off it 324): the second's
    # Hessian goes to the places found for the first
    P2, P3 = (P + 1e-3 * R * f(np.arange(P.size)).reshape(P.shape) for f in (np.sin, np.cos))
    assert np.array_equal(yc.hessian(P2).indices, yc.hessian(P3).indices)
    for Pk in (P, P2, P3):
        x.getArray()[:] = Pk.ravel()[lo:hi]
        K = to_scipy(full.stiffness(x)).toarray()
        K0 = to_scipy(full_off.stiffness(x)).toarray()
        H = yc.hessian(Pk).toarray()[lo:hi]
        diff = np.zeros_like(H)
        diff[:, :K.shape[1]] = K - K0
        assert yc.missed == 0
        assert np.allclose(diff, H, rtol=0, atol=1e-15 * np.abs(H).max())  # measured 3e-32
    x.getArray()[:] = P.ravel()[lo:hi]
    assert full.elastic_energy(x) - full_off.elastic_energy(x) == \
        pytest.approx(yc.energy(P), rel=2e-15, abs=0)  # measured 0 (1 and 2 ranks)
    for m in (full, full_off):
        m.destroy()


def test_two_crossing_yarns_pushed_together_stop_at_thickness():
    """Two straight yarns held at their ends and pushed through each other
    at the crossing by opposite forces (damped, backward Euler) come to rest
    with their centrelines between 2r and 2r + d̂ apart, where the barrier
    holds the load; without contact they pass through."""
    fab = crossing(gap=0.5, hold=True)
    F = 2e-3
    fab.loads = (np.array([0, 1]), np.array([4.0, 4.0]),
                 np.array([[0, 0, -F], [0, 0, F]]))
    gaps = {}
    for contact in (True, False):
        full = FullModel(COMM, fab, Material(gravity=0.0, damping=200.0),
                         yarn_contact=contact)
        integ, x, _ = run(full, BackwardEuler, 2e-3, 40)
        yc = YarnContact(fab, Material().EI)
        gaps[contact] = yc.min_distance(full.all_points(x), 4 * R)
        full.destroy()
    assert gaps[False] < 2 * R
    assert 2 * R < gaps[True] < 2 * R + yc.dhat


def test_tangent_pattern_follows_the_pairs():
    """A state whose near pairs left the pattern makes ``begin_step`` lay it
    out again (counted), and the new pattern holds the whole Hessian."""
    fab = crossing(gap=3.0)
    full = FullModel(COMM, fab, Material(gravity=0.0), yarn_contact=True)
    x = full.rest_state()
    full.stiffness(x)
    assert len(full.yarn_contact.pairs) == 0
    P = band_state(YarnContact(fab, Material().EI), fab, 3.0)
    lo, hi = x.getOwnershipRange()
    x.getArray()[:] = P.ravel()[lo:hi]
    assert full.begin_step(x) and full.pattern_rebuilds == 1
    assert not full.begin_step(x)
    full.stiffness(x)
    assert full.yarn_contact.missed == 0
    full.destroy()


def test_a_restart_takes_the_pairs_and_the_list_it_had():
    """``contact_state`` / ``set_contact_state`` (a checkpoint's): a model
    continued at a state lays its tangent out on the pairs it had, not on
    those of that state, asks for a new Newton matrix, and makes its Verlet
    list where the first one was made, so that its step filter, which looks
    beyond the list by the moves since then, cuts as the first one's."""
    fab = crossing(gap=3.0)
    first, again = (FullModel(COMM, fab, Material(gravity=0.0), yarn_contact=True)
                    for _ in range(2))
    rest, x = first.rest_state(), first.rest_state()
    P = band_state(YarnContact(fab, Material().EI), fab, 3.0)
    lo, hi = x.getOwnershipRange()
    x.getArray()[:] = P.ravel()[lo:hi]
    first.begin_step(x)
    first.stiffness(x)                     # pairs and list around x
    again.stiffness(rest)                  # none at rest
    assert len(again.yarn_contact.pairs) == 0 < len(first.yarn_contact.pairs)
    again.set_contact_state(first.contact_state())
    assert again.begin_step(rest)          # a new Newton matrix
    assert np.array_equal(again.stiffness(rest).getValuesCSR()[1],
                          first.stiffness(rest).getValuesCSR()[1])
    A, B = first.yarn_contact, again.yarn_contact
    assert np.array_equal(A.candidates_at, B.candidates_at)
    X, move = fab.X.reshape(-1, 3), np.zeros_like(P)
    move[:, 2] = np.linspace(-4 * R, 4 * R, len(P))
    assert A.step_fraction(X, X + move) == B.step_fraction(X, X + move) < 1
    for m in (first, again):
        m.destroy()


def test_option_turns_it_off():
    """-knit_yarn_contact on|off (on by default)."""
    from knitfem.cli.commands import model_options
    from knitfem.cli.options import KnitOptions

    opts = PETSc.Options()
    opts.setValue("-knit_yarn_contact", "off")
    try:
        assert model_options(KnitOptions()).yarn_contact is False
        opts.setValue("-knit_yarn_contact", "on")
        assert model_options(KnitOptions()).yarn_contact is True
    finally:
        opts.delValue("-knit_yarn_contact")
    assert model_options(KnitOptions()).yarn_contact is True           # on by default


def test_an_update_cut_by_the_filter_is_not_convergence():
    """Newton's update cut short by the yarn contact's filter is ``limited``,
    so that its small length is not taken for convergence (the convergence
    test's step criterion); an update the filter lets through is not."""
    fab = crossing(gap=0.5, hold=True)
    full = FullModel(COMM, fab, Material(gravity=0.0), yarn_contact=True)
    integ, _, _ = run(full, BackwardEuler, 1e-3, 1)
    lo, hi = full.rest_state().getOwnershipRange()
    through = (pushed(fab, 3.0) - fab.X.reshape(-1, 3)).ravel()[lo:hi]
    z, y = integ.z.duplicate(), integ.z.duplicate()
    z.zeroEntries()
    for scale, cut in ((1.0, True), (0.01, False)):
        y.zeroEntries()
        y.getArray()[:hi - lo] = -scale * through / integ.kappa   # ε moves by −κ y
        asked = y.norm()
        integ._limit(z, y)
        assert integ.limited is cut
        assert (y.norm() < asked) is cut
    z.destroy()
    y.destroy()
    full.destroy()


def test_a_tube_at_rest_has_a_band_and_no_barrier():
    """On closed yarns (a tube knitted in the round) samples next to each
    other across a yarn's seam never count as touching, and no pair of the
    template is tight (its legs are as far apart as flat; wrapped through
    their mid-depth they were 0.90 x 2r apart at 8 stitches round, and left
    out): the band is the flat jersey's d̂ = 0.072 r (it was -1.19 r: the
    seam's neighbours, 0.34 x 2r apart, counted as a pair), E_y = 0 at rest
    and after a rigid motion, and a small move is not cut."""
    fab = jersey_fabric(Jersey(4, 8, knit="tube"), hold="top")
    yc = YarnContact(fab, Material().EI)
    P = fab.X.reshape(-1, 3)
    assert yc.dhat == pytest.approx(0.072 * fab.radius, rel=2e-15, abs=0)  # measured 0
    assert yc.tight_at_rest == 0 and yc.min_distance(P) >= yc.dmin + yc.dhat
    R = rotation((30, 40, 50))
    assert yc.energy(P) == 0.0 and yc.energy(P @ R.T + 0.01) == 0.0
    move = 1e-3 * fab.radius * np.random.default_rng(1).standard_normal(P.shape)
    assert yc.step_fraction(P, P + move) == 1.0
    seam = yc.edges[yc.edges[:, 1] < yc.edges[:, 0]]     # each closed yarn's last edge
    first = yc.edges[np.searchsorted(yc.edges[:, 0], seam[:, 1]) + 1]
    e = np.searchsorted(yc.edges[:, 0], seam[:, 0])
    f = np.searchsorted(yc.edges[:, 0], first[:, 0])
    assert not yc._apart(e, f).any() and not yc.edges_may_touch(e, f).any()


@pytest.mark.parametrize("shape", ["flat", "tube"])
def test_one_yarn_is_excluded_by_arc_not_by_samples(shape):
    """On a seed, whose rest edges differ by 2.6× in length, two samples of
    one yarn are never kept apart closer than L / 2 = self_reach · r along it
    (the short way round a tube's course) and always kept apart from L on,
    unless the crossings or the template's tight pairs exclude them."""
    from knitfem.knit.chart import named_chart

    j = Jersey(4, 6, knit=shape, chart=named_chart("seed", 4, 6))
    fab = jersey_fabric(j)
    yc = YarnContact(fab, 1.0)
    edge = yc.edge_lengths(yc.samples(fab.X))
    assert edge.max() / edge.min() > 2          # measured 2.6
    i, j_ = np.triu_indices(len(yc.sample_yarn), 1)
    same = yc.sample_yarn[i] == yc.sample_yarn[j_]
    i, j_ = i[same], j_[same]
    along = np.abs(yc.arc[i] - yc.arc[j_])
    along = np.minimum(along, yc.perimeter[i] - along)
    key = i * len(yc.sample_yarn) + j_
    free = ~np.isin(key, yc.excluded)
    may = yc.samples_may_touch(i, j_)
    L = 2 * 8.0 * R
    assert not may[along < L / 2].any()
    assert may[(along >= L) & free].all()
    assert ((along >= L) & free).sum() > 1000    # the pairs the old runs cut off


def test_a_natural_knit_of_a_shorter_loop_keeps_its_templates_gaps():
    """A natural knit whose rest X is its template scaled to a loop 10 %
    shorter leaves out the pairs and takes the band of its template at its
    own size (``Fabric.contact_X``), not those of X, whose gaps close 10 %."""
    from knitfem.run.relax import natural_fabric, stitch_length

    j = Jersey(4, 4)
    template = jersey_fabric(j)
    own = YarnContact(natural_fabric(j, template), 1.0)
    short = natural_fabric(j, template, 0.9 * stitch_length(j, template))
    shorter = YarnContact(short, 1.0)
    assert own.tight_at_rest == shorter.tight_at_rest == 0
    assert shorter.dhat == own.dhat
    read_on_X = YarnContact(replace(short, contact_X=None), 1.0)
    assert read_on_X.tight_at_rest > 100          # measured 724
