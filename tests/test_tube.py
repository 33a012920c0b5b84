"""Knitting in the round: closed (periodic) B-spline yarns, a tube's contacts
across the closing seam, and the bounding volume periodic around it.

A closed yarn of n control points is the open spline of its n + 3 control
points wrapped (p_n, p_{n+1}, p_{n+2} = p_0, p_1, p_2): every identity below
(mass, energy, gradient) is checked against that open twin, folded back.
The model tests run serial and under mpirun (COMM_WORLD)."""

import numpy as np
import pytest

from helpers import COMM, gather, steps_from_start
from knitfem.yarn import bspline
from knitfem.yarn.kernels import KINDS
from knitfem.model.full import FullModel, Material
from knitfem.contact.gaps import YarnGaps
from knitfem.knit.pattern import Jersey, jersey_fabric, min_yarn_distance
from knitfem.lod.reduced import Embedding, ReducedModel
from knitfem.cli.scenes import rotation
from knitfem.lod.volume import BoundingVolume
from knitfem.yarn.elements import YarnElements
from test_yarn import central_differences, dense_hessian, gradient, relative

NCP = 12


def ring(seed=0, n=NCP):
    """Control points (n, 3) of a noisy closed loop (radius 1, wavy in z)."""
    phi = 2 * np.pi * np.arange(n) / n
    X = np.c_[np.cos(phi), np.sin(phi), 0.2 * np.sin(3 * phi)]
    return X + 0.05 * np.random.default_rng(seed).normal(size=X.shape)


def closed_conn(n=NCP):
    return bspline.span(np.arange(n), n, closed=True)


def wrap(n=NCP):
    """F (n + 3, n): the open twin's control points F p of a closed yarn p."""
    return np.eye(n)[np.r_[np.arange(n), 0, 1, 2]]


def test_closed_curve_interpolates_and_is_c2_across_the_seam():
    x = ring(1)
    P = bspline.periodic_interpolant(x)
    # junction s = i − 1 is centred on p_i
    at = bspline.curve_points(P, np.arange(NCP) - 1.0, closed=True)
    assert np.abs(at - x).max() < 5e-15  # measured 4.4e-16
    for nu in (0, 1, 2):
        before = bspline.curve_points(P, NCP - 1e-9, nu, closed=True)
        after = bspline.curve_points(P, 1e-9, nu, closed=True)
        assert np.abs(before - after).max() < 2e-8  # measured 1.3e-9
    # the open twin is the same curve
    s = np.linspace(0, NCP, 97)[:-1]
    assert np.allclose(bspline.curve_points(P, s, closed=True),
                       bspline.curve_points(wrap() @ P, s), rtol=0, atol=1e-15)


def test_closed_mass_and_energy_are_the_open_twins_folded():
    X = ring(2)
    F = wrap()
    closed = YarnElements(X, closed_conn(), 0.3, 10.0, 1e-2)
    twin = YarnElements(F @ X, np.arange(NCP)[:, None] + np.arange(4), 0.3, 10.0, 1e-2)
    m_closed, m_twin = np.zeros((NCP, NCP)), np.zeros((NCP + 3, NCP + 3))
    np.add.at(m_closed, (closed.conn[:, :, None], closed.conn[:, None, :]),
              closed.mass_elements())
    np.add.at(m_twin, (twin.conn[:, :, None], twin.conn[:, None, :]),
              twin.mass_elements())
    # measured 1.7e-16
    assert np.abs(m_closed - F.T @ m_twin @ F).max() < 1e-15 * np.abs(m_closed).max()
    x = X + 0.1 * np.random.default_rng(3).normal(size=X.shape)
    # measured 0
    assert abs(closed.energy(x) - twin.energy(F @ x)) < 2e-15 * twin.energy(F @ x)
    for kind in KINDS:  # measured 5.7e-17 of the largest
        assert np.allclose(gradient(closed, kind)(x), F.T @ gradient(twin, kind)(F @ x),
                           rtol=0, atol=1e-15 * np.abs(gradient(twin)(F @ x)).max())


@pytest.mark.parametrize("kind", KINDS)
def test_closed_gradient_and_hessian_match_finite_differences(kind):
    y = YarnElements(ring(4), closed_conn(), 0.3, 10.0, 1e-2)
    x = y.X + 0.1 * np.random.default_rng(5).normal(size=y.X.shape)
    # measured 6.3e-11
    assert relative(gradient(y, kind)(x).ravel(),
                    central_differences(y.energy, x, 1e-6).ravel()) < 7e-10
    # measured 5.6e-11
    assert relative(dense_hessian(y, x, kind),
                    central_differences(gradient(y, kind), x, 1e-6)) < 6e-10


@pytest.mark.parametrize("cols", [3, 7, 16])
def test_tube_courses_keep_apart_and_interlock_all_round(cols):
    """At rest different courses are >= 2r apart, and so are the parts of
    one course more than 8 r apart along it (the legs of neighbouring
    stitches as far apart as flat, where wrapped through their mid-depth
    they were 0.97 x 2r apart at 16 stitches round); every stitch around,
    the one across the seam too, interlocks with the course above."""
    jersey = Jersey(4, cols, knit="tube")
    fab = jersey_fabric(jersey)
    assert fab.closed.all() and np.all(fab.yarn_ncp == 8 * cols)
    assert np.all(fab.yarn_nseg == 8 * cols)
    dist = min_yarn_distance(fab.curves(fab.X), 16)[0]
    assert dist >= 2 * fab.radius
    flat = jersey_fabric(Jersey(4, cols))
    legs = [YarnGaps(c, f.radius).pairs(c.points, 3 * f.radius)[2].min()
            for f in (fab, flat) for c in [f.curves(f.X).samples(16)]]
    # measured 0.963, 1.002, 1.009 of the flat jersey's 2.086 r at 3, 7, 16 round
    assert legs[0] >= 0.95 * legs[1] and legs[0] > 2 * fab.radius
    ya, sa, yb, sb = fab.contacts
    assert len(ya) == 3 * 2 * cols and np.all(yb == ya + 1)
    a = bspline.curve_points(fab.yarn(0), sa[:2 * cols], closed=True)
    b = bspline.curve_points(fab.yarn(1), sb[:2 * cols], closed=True)
    gap = np.linalg.norm(a - b, axis=1)
    assert np.ptp(gap) < 1e-12 and 2 * fab.radius <= gap[0] < 2.5 * fab.radius
    # the stitch at the seam reaches control points on both sides of it
    k = bspline.locate(sb, 8 * cols, closed=True)[0]
    assert np.any(bspline.span(k, 8 * cols, closed=True).min(axis=1) == 0)


@pytest.fixture(scope="module")
def tube():
    fab = jersey_fabric(Jersey(4, 5, knit="tube"), hold="top")
    full = FullModel(COMM, fab, Material())
    volume = BoundingVolume.tube(fab.X.reshape(-1, 3), 6, 5, margin=fab.radius)
    red = ReducedModel(full, Embedding(COMM, full.layout, fab, volume))
    yield full, red
    red.destroy()
    full.destroy()


def test_tube_contacts_hold_under_rigid_motions(tube):
    full, _ = tube
    fab = full.fabric
    lo, hi = full.rest_state().getOwnershipRange()
    contact = full.constraint_kind == "contact"
    g = full.C.createVecLeft()
    centre = fab.X.reshape(-1, 3).mean(axis=0)
    for turn in [(0, 0, 0), (90, 0, 0), (0, 45, 0), (30, -60, 120)]:
        X = (fab.X - centre) @ rotation(turn).T + centre + [0.3, -0.1, 0.2]
        x = full.rest_state()
        x.getArray()[:] = X.ravel()[lo:hi]
        full.constraint_residual(x, g)
        assert np.abs(gather(COMM, g).reshape(-1, 3)[contact]).max() < 1e-15


def test_tube_volume_embeds_the_yarns_exactly_across_the_seam(tube):
    full, red = tube
    fab, emb = full.fabric, red.embedding
    vol = emb.volume
    assert vol.periodic and vol.domain[0] == vol.n1
    s1 = emb.params[0]
    assert s1.min() < 0.5 and s1.max() > vol.n1 - 0.5       # points all round
    assert np.all(emb.vals >= 0)
    assert np.allclose(emb.vals.sum(axis=1), 1, atol=0, rtol=2e-15)  # measured 2.2e-16
    eps = gather(COMM, red.full_state(red.rest_state()))
    assert np.abs(eps - fab.X.ravel()).max() < 2e-13 * fab.radius  # measured 1.4e-14


def test_periodic_volume_saves_and_loads(tmp_path):
    fab = jersey_fabric(Jersey(2, 4, knit="tube"))
    vol = BoundingVolume.tube(fab.X.reshape(-1, 3), 5, 4, margin=fab.radius)
    vol.save(tmp_path / "v.vtu")
    back = BoundingVolume.load(tmp_path / "v.vtu")
    assert back.periodic and np.array_equal(back.flat, vol.flat)
    assert back.deformed("shear", 10.0).periodic


@pytest.mark.parametrize("kind", ["full", "reduced"])
def test_tube_started_turned_falls_rigidly(kind):
    """A free tube started turned strains nothing and falls as a rigid body
    (backward Euler: y_n = −g h² n(n + 1)/2), in both models."""
    fab = jersey_fabric(Jersey(3, 4, knit="tube")).started_turned(rotation((30, 0, 50)))
    full = FullModel(COMM, fab, Material())
    system = full
    if kind == "reduced":
        volume = BoundingVolume.tube(fab.X.reshape(-1, 3), 6, 4, margin=fab.radius)
        system = ReducedModel(full, Embedding(COMM, full.layout, fab, volume))
    x, energy, worst = steps_from_start(system)
    assert energy < 6e-29 and worst < 1e-12 * fab.radius  # measured 5.6e-30
    moved = gather(COMM, system.full_state(x)).reshape(-1, 3) - \
        fab.start_points().reshape(-1, 3)
    drop = -9.81 * 1e-6 * 15
    # measured 4.6e-11 of the drop (2 ranks 1.2e-12)
    assert np.allclose(moved, [0, drop, 0], rtol=0, atol=4e-10 * abs(drop))
