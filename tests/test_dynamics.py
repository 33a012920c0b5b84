"""Constrained dynamics of the full model against analytic mechanics."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import COMM, energies, gather, hanging_simulation, jersey, run
from knitfem.model.full import FullModel, Material
from knitfem.cli.scenes import make_fabric
from solvers.integrators import BackwardEuler, SymplecticEuler
from solvers.statics import StaticSolver

SELF = PETSc.COMM_SELF


def test_assembled_forces_and_stiffness_match_finite_differences():
    fab = jersey(2, 1)
    model = FullModel(SELF, fab, Material(EA=5.0, EI=1e-6, gravity=9.81))
    rng = np.random.default_rng(1)
    x = model.rest_state()
    x.getArray()[:] += 2e-5 * rng.normal(size=x.getLocalSize())
    v = x.duplicate()
    v.zeroEntries()
    Q0, Qp, Qm = x.duplicate(), x.duplicate(), x.duplicate()
    model.forces(x, v, Q0)
    K = model.stiffness(x)
    dx = x.duplicate()
    dx.getArray()[:] = rng.normal(size=x.getLocalSize())
    h = 1e-9
    xp, xm = x.copy(), x.copy()
    xp.axpy(h, dx)
    xm.axpy(-h, dx)
    model.forces(xp, v, Qp)
    model.forces(xm, v, Qm)
    fd = -(Qp.getArray() - Qm.getArray()) / (2 * h)
    Kdx = K.createVecLeft()
    K.mult(dx, Kdx)
    # measured 1.4e-10
    assert np.linalg.norm(Kdx.getArray() - fd) < 2e-9 * np.linalg.norm(fd)
    # Q is minus the gradient of E plus gravity: directional derivative of E
    dE = (model.elastic_energy(xp) - model.elastic_energy(xm)) / (2 * h)
    Qel = Q0.getArray() - model.Qg.getArray()
    assert np.isclose(dE, -Qel @ dx.getArray(), rtol=6e-9, atol=0)  # measured 5.5e-10
    assert K.isSymmetric(1e-10 * K.norm())


# xtol in yarn radii, vtol relative: measured 6.1e-15 r, 1.8e-8 (symplectic)
# and 5.9e-13 r, 1.2e-13 (backward Euler)
@pytest.mark.parametrize("integrator,dt,xtol,vtol", [
    (SymplecticEuler, 5e-7, 4e-14, 1e-7), (BackwardEuler, 1e-3, 4e-12, 1e-12)])
def test_free_fall_follows_half_g_t_squared_and_keeps_shape(integrator, dt, xtol, vtol):
    fab = jersey(2, 2)
    g, n = 9.81, 20
    model = FullModel(COMM, fab, Material(EA=5.0, EI=1e-6, gravity=g))
    _, x, v = run(model, integrator, dt, n)
    X = fab.X.reshape(-1, 3)
    disp = gather(COMM, x).reshape(-1, 3) - X
    # both schemes: v_n = −g n h, y_n = −g h² n(n + 1)/2 for a rigid fall
    drop = -g * dt**2 * n * (n + 1) / 2
    assert np.allclose(disp[:, 1], drop, rtol=0, atol=xtol * fab.radius)
    assert np.abs(disp[:, [0, 2]]).max() < xtol * fab.radius
    assert np.isclose(drop, -0.5 * g * (n * dt) ** 2, rtol=0.06)   # O(h) scheme
    assert np.allclose(gather(COMM, v).reshape(-1, 3)[:, 1], -g * n * dt, rtol=vtol, atol=0)


# ptol relative to Σ|m v|: measured 1.5e-11 (symplectic), 3.4e-14 (backward)
@pytest.mark.parametrize("integrator,dt,ptol", [(SymplecticEuler, 5e-7, 1e-10),
                                                (BackwardEuler, 1e-4, 3e-13)])
def test_linear_momentum_conserved_without_gravity(integrator, dt, ptol):
    fab = jersey(2, 1)
    model = FullModel(COMM, fab, Material(EA=2.0, EI=1e-6, gravity=0.0))
    rng = np.random.default_rng(3)
    v0 = 1e-2 * rng.normal(size=3 * fab.npoints)
    _, x, v = run(model, integrator, dt, 40, v0)
    m = model.M.createVecLeft()
    model.M.mult(v, m)
    p = gather(COMM, m).reshape(-1, 3).sum(0)
    # the first step projects v0 onto C v = 0; momentum is kept through it
    x0, vv = model.rest_state(), model.rest_state()
    lo, hi = vv.getOwnershipRange()
    vv.getArray()[:] = v0[lo:hi]
    model.M.mult(vv, m)
    p0 = gather(COMM, m).reshape(-1, 3).sum(0)
    scale = np.abs(gather(COMM, m)).sum()
    # the constraint rows sum to zero up to the round-off of the spline
    # weights (Σ N_i(s) = 1 in floating point), times the contact forces
    assert np.allclose(p, p0, rtol=0, atol=ptol * scale)
    assert np.abs(gather(COMM, x) - gather(COMM, x0)).max() > 1e-9   # it moved


def catenary_sag(length, span):
    from scipy.optimize import brentq

    a = brentq(lambda a: 2 * a * np.sinh(span / (2 * a)) - length, span / 50, 1e3)
    return a * (np.cosh(span / (2 * a)) - 1)


def test_catenary_settles_to_analytic_sag():
    L, S = 0.1, 0.08
    fab = make_fabric("catenary", length=L, span=S, segments=40)
    model = FullModel(SELF, fab, Material(EA=1e3, EI=1e-10, damping=20.0))
    # a string (EI ≈ 0): at 1e-2 s steps Newton wanders between the hinge
    # mechanism's equilibria and lands on another one, depending on round-off;
    # at 4e-3 to 8e-3 s every run settles on the catenary
    _, x, v = run(model, BackwardEuler, 5e-3, 200)
    P = x.getArray().reshape(-1, 3)
    from knitfem.yarn import bspline
    s = np.linspace(0, 40, 801)
    sag = -bspline.curve_points(P, s)[:, 1].min()
    assert sag == pytest.approx(catenary_sag(L, S), rel=0.02)
    arc_sag = -bspline.curve_points(fab.X, s)[:, 1].min()
    assert abs(arc_sag - sag) > 0.02 * sag              # the arc did move
    assert v.norm() < 1e-7                              # and settled: measured 1.3e-8 m/s


def test_cantilever_small_deflection_tip():
    L, EI, rho, g = 0.1, 1e-4, 3e-5, 9.81
    fab = make_fabric("cantilever", length=L, segments=20)
    model = FullModel(SELF, fab, Material(rho=rho, EA=1e3, EI=EI, gravity=g))
    x = model.rest_state()
    StaticSolver(model, steps=1).solve(x)
    P = x.getArray().reshape(-1, 3)
    from knitfem.yarn import bspline
    tip = bspline.curve_points(P, np.array([20.0]))[0]
    # measured 1.1e-7
    assert -tip[1] == pytest.approx(rho * g * L**4 / (8 * EI), rel=1e-6)


def test_symplectic_energy_drift_bounded():
    fab = make_fabric("catenary", length=0.05, span=0.04, segments=8)
    fab.fixed = (np.zeros(1, int), np.zeros(1))        # a pendulum: one end pinned
    mat = Material(EA=0.5, EI=1e-7, gravity=9.81)
    model = FullModel(SELF, fab, mat)
    dt = 5e-6
    integ = SymplecticEuler(model, dt)
    x, v = model.rest_state(), model.rest_state()
    v.zeroEntries()
    E0, totals, kinetic = energies(model, x, v)[0], [], []
    for n in range(10000):
        integ.step(n * dt, x, v)
        if n % 100 == 99:
            E, T = energies(model, x, v)
            totals.append(E)
            kinetic.append(T)
    drift = np.abs(np.array(totals) - E0)
    assert max(kinetic) > 1e-8                       # the yarn swings
    assert drift.max() < 9e-4 * max(kinetic)  # bounded: measured 8.1e-5
    # no secular growth: the last tenth drifts no more than the worst before it
    assert drift[-10:].max() <= 1.5 * drift[:-10].max()


@pytest.mark.parametrize("contacts", ["fixed", "sliding"])
def test_restart_equals_uninterrupted(tmp_path, contacts):
    """A restart continues exactly (sliding crossings from where the
    checkpoint had them, not from rest)."""
    fab = jersey(3, 2, hold="top")

    def simulation(out):
        return hanging_simulation(fab, out, contacts=contacts, output_every=5,
                                  checkpoint_every=10)

    whole = simulation(tmp_path / "a")
    whole.run(0.02)
    first = simulation(tmp_path / "b")
    first.run(0.01)
    second = simulation(tmp_path / "c")
    second.restart(str(tmp_path / "b" / "checkpoint.h5"))
    assert second.step_count == 10
    if contacts == "sliding":
        slid = second.full.constraints.local
        assert np.abs(slid.s - slid.s0).max() > 1e-3
    second.run(0.02)
    assert np.abs(whole.x.getArray() - fab.X.ravel()).max() > 1e-7
    # measured 1.8e-16
    assert np.allclose(second.x.getArray(), whole.x.getArray(), rtol=0, atol=2e-15)
    assert np.allclose(second.v.getArray(), whole.v.getArray(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("growth,quantity", [
    (0.5, "the total energy grew"),
    (0.0, ".*(not finite|drift|SHAKE did not hold)")])
def test_blow_up_stops_with_step_time_and_quantity(tmp_path, growth, quantity):
    """An explicit step above its stable one: the energy guard stops it at
    its first growth; without the guard, the state's blow-up does."""
    from knitfem.run.simulation import Simulation, SimulationError

    fab = jersey(2, 1)
    model = FullModel(SELF, fab, Material(EA=5.0, EI=1e-6))
    sim = Simulation(model, SymplecticEuler(model, 1e-4), out=str(tmp_path),
                     scene="freefall", output_every=1, verbose=False,
                     energy_growth=growth)
    with pytest.raises(SimulationError, match=rf"step \d+, t = .* s: {quantity}"):
        sim.run(0.05)
    assert (tmp_path / "yarns.xdmf").exists() and (tmp_path / "yarns" / "mesh.h5").exists()
