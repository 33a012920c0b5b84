"""Implicit integrators and step control: exactness, order, constraints,
error control, checkpoint state."""

import itertools

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import COMM, energies, gather, jersey, models
from knitfem.model.full import FullModel, Material
from knitfem.cli.scenes import make_fabric
from solvers.integrators import (BDF2, BackwardEuler, GeneralizedAlpha,
                                 SimulationError, SymplecticEuler)
from solvers.stepping import PositionHistory, StepControl

SELF = PETSc.COMM_SELF


def pendulum(damping=0.0, EA=0.5, EI=1e-7):
    """A yarn pinned at one end, starting as an arc: it swings under gravity."""
    fab = make_fabric("catenary", length=0.05, span=0.04, segments=8)
    fab.fixed = (np.zeros(1, int), np.zeros(1))
    return FullModel(SELF, fab, Material(EA=EA, EI=EI, gravity=9.81,
                                         damping=damping))


def integrate(integ, system, t_end, t_stops=()):
    """Steps to t_end (landing on t_stops); returns x, v and the step count."""
    x, v = system.rest_state(), system.rest_state()
    v.zeroEntries()
    t, n = 0.0, 0
    for stop in (*t_stops, t_end):
        while t < stop - 1e-12:
            st = integ.step(t, x, v, stop)
            t = stop if abs(t + st["dt"] - stop) < 1e-12 else t + st["dt"]
            n += 1
    return x, v, n


@pytest.mark.parametrize("rho_inf", [1.0, 0.5, 0.0])
def test_generalized_alpha_free_fall_is_exact(rho_inf):
    """ε̈ = −g ŷ is quadratic in t: Newmark with a consistent a₀ is exact."""
    fab = jersey(2, 2)
    g, dt, n = 9.81, 1e-3, 20
    model = FullModel(COMM, fab, Material(EA=5.0, EI=1e-6, gravity=g))
    integ = GeneralizedAlpha(model, dt, rho_inf=rho_inf)
    x, v, _ = integrate(integ, model, n * dt)
    disp = gather(COMM, x).reshape(-1, 3) - fab.X.reshape(-1, 3)
    t = n * dt
    assert np.allclose(disp[:, 1], -0.5 * g * t**2, rtol=5e-14, atol=0)  # measured 7.3e-15
    assert np.abs(disp[:, [0, 2]]).max() < 3e-13 * fab.radius   # measured 5.0e-14 r
    # measured 1.8e-12
    assert np.allclose(gather(COMM, v).reshape(-1, 3)[:, 1], -g * t, rtol=1e-11, atol=0)


@pytest.fixture(scope="module")
def converged():
    """A swinging soft yarn (EA = 1e-2 N, EI = 1e-9 N m², h ω < 1 for its
    modes at the steps below) and its state at 0.02 s by generalized-α at
    7.8e-6 s, 16 times below the finest step of a second-order method."""
    model = pendulum(EA=1e-2, EI=1e-9)
    return model, gather(SELF, integrate(GeneralizedAlpha(model, 6.25e-5 / 8), model,
                                         0.02)[0])


@pytest.mark.parametrize("cls,steps,slope", [
    (GeneralizedAlpha, (1e-3, 5e-4, 2.5e-4, 1.25e-4), 1.48),      # measured 1.48
    (BDF2, (5e-4, 2.5e-4, 1.25e-4, 6.25e-5), 1.18),               # 1.18
    (BackwardEuler, (2e-3, 1e-3, 5e-4, 2.5e-4), 1.01),            # 1.01
    (SymplecticEuler, (1e-4, 5e-5, 2.5e-5, 1.25e-5), 1.00)])      # 1.00
def test_measured_order_against_a_converged_reference(converged, cls, steps, slope):
    """The least-squares slope of log |ε(T) − ε_ref(T)|∞ against log h.

    Backward and symplectic Euler meet their order 1. The second-order
    methods fall below 2: the velocities meet the nonlinear contact and pin
    constraints only to O(h) (position-level drift control), an error that
    enters the next steps' positions, and the yarn's axial modes sit at
    h ω ≈ 0.1–1, where BDF2's damping and α's start are not yet asymptotic.
    """
    model, ref = converged
    errors = [np.abs(gather(SELF, integrate(cls(model, h), model, 0.02)[0]) - ref).max()
              for h in steps]
    # measured within 4.8e-3 of the slopes above
    assert np.polyfit(np.log(steps), np.log(errors), 1)[0] == pytest.approx(slope,
                                                                           abs=0.03)


def test_constraints_hold_to_newton_tolerance_under_step_control():
    """g(ε_{n+1}) = 0 is solved with every step (to 1e-9 r); the contacts
    being nonlinear, C(ε)v = 0 holds only to O(h)."""
    fab = jersey(2, 2, hold="top")
    model = FullModel(SELF, fab, Material())
    control = StepControl(1e-4, adaptive=True, rtol=1e-3, atol=1e-6)
    integ = GeneralizedAlpha(model, 1e-4, control)
    x, v, n = integrate(integ, model, 0.02)
    r, rv = model.C.createVecLeft(), model.C.createVecLeft()
    model.constraint_residual(x, r)
    model.constraint_jacobian(x).mult(v, rv)
    speed = v.norm(PETSc.NormType.INFINITY)
    assert n > 5 and r.norm(PETSc.NormType.INFINITY) < 1e-9 * fab.radius
    assert rv.norm(PETSc.NormType.INFINITY) < 2e-3 * speed   # measured 1.9e-4
    assert np.abs(x.getArray() - fab.X.ravel()).max() > 1e-5      # it moved


def test_error_control_lands_on_stops_and_tightens_with_tolerance():
    model = pendulum()
    ref = gather(SELF, integrate(GeneralizedAlpha(model, 1e-5), model, 0.05)[0])
    errors, steps = [], []
    for rtol in (1e-2, 1e-4):
        control = StepControl(1e-4, adaptive=True, rtol=rtol, atol=rtol * 1e-3)
        integ = GeneralizedAlpha(model, 1e-4, control)
        x, _, n = integrate(integ, model, 0.05, t_stops=(0.0123,))
        errors.append(np.abs(gather(SELF, x) - ref).max())
        steps.append(n)
    assert errors[1] < 0.25 * errors[0] and steps[1] > steps[0]


@pytest.mark.parametrize("cls", [GeneralizedAlpha, BDF2, BackwardEuler])
def test_state_continues_bit_exactly(cls):
    model = pendulum()

    def make():
        return cls(model, 1e-4, StepControl(1e-4, adaptive=True, rtol=1e-3, atol=1e-6))

    whole = make()
    x, v, _ = integrate(whole, model, 0.01, t_stops=(0.005,))
    first = make()
    x1, v1, _ = integrate(first, model, 0.005)
    saved = {k: np.array(a, copy=True) for k, a in first.state().items()}
    second = make()
    second.set_state(saved)
    t = 0.005
    while t < 0.01 - 1e-12:
        st = second.step(t, x1, v1, 0.01)
        t = 0.01 if abs(t + st["dt"] - 0.01) < 1e-12 else t + st["dt"]
    # equal up to the last bits of a fresh factorisation: measured 6.9e-18 on
    # one machine, 1.3e-16 (3 ulps of |ε| 4e-2) on another
    assert np.allclose(x1.getArray(), x.getArray(), rtol=0, atol=5e-16)
    assert np.allclose(v1.getArray(), v.getArray(), rtol=0, atol=1e-13)


def test_mass_damping_dissipates_energy():
    model = pendulum(damping=20.0)
    integ = GeneralizedAlpha(model, 1e-3, rho_inf=1.0)
    x, v = model.rest_state(), model.rest_state()
    v.zeroEntries()
    E = [energies(model, x, v)[0]]
    for n in range(100):
        integ.step(n * 1e-3, x, v)
        E.append(energies(model, x, v)[0])
    assert np.all(np.diff(E) < 1e-12 * abs(E[0]))
    assert E[-1] < E[0] - 1e-6


def test_petsc_error_in_newton_becomes_simulation_error():
    model = pendulum()
    opts = PETSc.Options()
    opts["full_ksp_type"] = "cg"
    opts["full_pc_type"] = "none"
    opts["full_ksp_max_it"] = 1
    try:
        integ = BackwardEuler(model, 1e-3)
        integ.max_halvings = 1
        with pytest.raises(SimulationError, match=r"KSP cg with PC none did not "
                                                  r"converge .*-full_ksp_max_it"):
            integrate(integ, model, 1e-3)
    finally:
        for k in ("full_ksp_type", "full_pc_type", "full_ksp_max_it"):
            opts.delValue(k)


def test_step_control_shrinks_to_dt_min_and_no_further():
    """A rejected step proposes h·fac but never below dt_min; a step
    rejected at dt_min (or a shorter one landing on t_stop) returns None (the
    run stops); an accepted one never proposes below dt_min either."""
    c = StepControl(1e-3, adaptive=True, dt_min=3e-4)
    assert c.judge(1e6, 1e-3, 2, False) is False and c.dt == 3e-4   # h fac = 2e-4
    assert c.judge(1e6, 3e-4, 2, False) is None
    assert c.judge(1e6, 1e-4, 2, True) is None
    assert c.judge(0.99, 3e-4, 2, False) is True and c.dt == 3e-4
    c = StepControl(1e-3, adaptive=True, dt_min=1e-5)
    assert c.judge(1e6, 1e-3, 2, False) is False and c.dt == pytest.approx(2e-4)


def test_position_history_estimate_is_exact_for_a_cubic():
    """For ε = t³ the extrapolation error is Π ε⃛/3! and e = c h³ ε⃛."""
    hist = PositionHistory(2, 0.1)
    times = [0.0, 0.3, 0.5, 0.9]
    for t0, t1 in zip(times, times[1:]):
        if t0 == 0.0:
            hist.start(np.array([t0**3]))
        hist.push(np.array([t1**3]), t1 - t0)
    h = 0.25
    exact_next = (0.9 + h) ** 3
    e = np.zeros(1)
    # a method with local error c h³ ε⃛ = 0.1 h³ · 6 lands here:
    assert hist.estimate(np.array([exact_next + 0.6 * h**3]), h, e)
    assert e[0] == pytest.approx(0.6 * h**3, rel=2e-14, abs=0)    # measured 3.5e-15


@pytest.mark.parametrize("method", [BackwardEuler, BDF2, GeneralizedAlpha])
def test_newton_matrix_is_the_derivative_of_the_residual(method):
    """The saddle-point matrix each method gives Newton (σκK + (1 + σc_d)M,
    the frame-indifferent contacts' curvature, C(ε) and its transpose)
    equals central differences of the method's residual in (ε̇_{n+1}, μ),
    at a generic state of a hanging jersey after two steps."""
    from knitfem.knit.pattern import Jersey

    model = FullModel(SELF, make_fabric("hanging", Jersey(3, 3), tilt=0.0), Material(damping=2.0))
    integ = method(model, 1e-2)
    x, v = model.start_state(), model.start_state()
    v.zeroEntries()
    integ.step(0.0, x, v)
    integ.step(0.01, x, v)
    integ.xn, integ.vn = x.copy(), v.copy()
    integ.coefficients(1e-2)
    rng = np.random.default_rng(7)
    z = integ.saddle.createVec()
    zu, zl = integ.saddle.split(z)
    zu[:] = v.getArray() + 1e-3 * rng.standard_normal(len(zu))
    zl[:] = 1e-6 * rng.standard_normal(len(zl))
    integ._jacobian(None, z, None, None)
    d, Jd = z.duplicate(), z.duplicate()
    d.getArray()[:] = rng.standard_normal(z.getLocalSize())
    integ.saddle.K.mult(d, Jd)
    h = 1e-6
    F = [z.duplicate() for _ in range(2)]
    for sign, out in zip((1, -1), F):
        zs = z.copy()
        zs.axpy(sign * h, d)
        integ._residual(None, zs, out)
    fd = (F[0].getArray() - F[1].getArray()) / (2 * h)
    assert np.linalg.norm(Jd.getArray() - fd) <= 8e-10 * np.linalg.norm(fd)  # 7.6e-11
    model.destroy()


def test_mip_newton_takes_the_first_step_from_rest_in_fewer_iterations():
    """The mixed integration point Newton matrix (``-knit_tangent mip``)
    reaches the state of the exact one, in under half its iterations, on a
    jersey released from rest at a large step."""
    out = {}
    for tangent in ("exact", "mip", "auto"):
        model = FullModel(COMM, jersey(6, 12, hold="top"), Material())
        integ = BackwardEuler(model, 1e-2, tangent=tangent)
        x, v = model.rest_state(), model.rest_state()
        v.zeroEntries()
        first = integ.step(0.0, x, v)["newton"]
        out[tangent] = first, gather(COMM, x), integ.step(1e-2, x, v)["newton"]
    (n_exact, x_exact, then_exact), (n_mip, x_mip, _) = out["exact"], out["mip"]
    assert np.abs(x_mip - x_exact).max() < 5e-11 * model.fabric.radius   # 4.4e-12
    assert 2 * n_mip < n_exact
    # auto: MIP on the first step (no velocity history), exact after
    n_auto, x_auto, then_auto = out["auto"]
    assert n_auto == n_mip and np.array_equal(x_auto, x_mip)
    assert then_auto == then_exact


def test_unknown_tangent_is_refused():
    with pytest.raises(ValueError, match="use one of auto, mip, exact"):
        BackwardEuler(FullModel(COMM, jersey(), Material()), 1e-2, tangent="secant")


def test_mip_newton_reaches_the_reduced_models_step():
    """MIP through Γ: the reduced model's step with the MIP matrix (its
    reference state embedded as Γ q_ref) is the exact matrix's step."""
    out = {}
    for tangent in ("exact", "mip"):
        _, red = models(COMM, jersey(4, 8, hold="top"))
        integ = BackwardEuler(red, 1e-2, tangent=tangent)
        q, v = red.rest_state(), red.rest_state()
        v.zeroEntries()
        integ.step(0.0, q, v)
        out[tangent] = gather(COMM, red.full_state(q))
    assert np.abs(out["mip"] - out["exact"]).max() < 8e-16    # measured 8e-17


@pytest.mark.parametrize("cls,kw", [(BackwardEuler, dict(tangent="mip")),
                                    (BackwardEuler, dict(guess="start")), (BDF2, {}),
                                    (GeneralizedAlpha, dict(rho_inf=0.8, tangent="mip"))])
def test_an_integrator_like_another_keeps_its_control_and_settings(cls, kw):
    """What an adaptive run's switch gives its new model: the same step
    control (error-controlled stays error-controlled) and settings."""
    fab = jersey(2, 2, hold="top")
    control = StepControl(1e-3, adaptive=True, rtol=1e-4, atol=1e-6)
    integ = cls(FullModel(COMM, fab, Material()), 1e-3, control, **kw)
    other = FullModel(COMM, fab, Material())
    new = integ.like(other)
    assert type(new) is cls and new.system is other and new.control is control
    assert new.settings() == integ.settings()
    assert new.tangent == kw.get("tangent", "exact")
    assert getattr(new, "rho_inf", None) == kw.get("rho_inf", getattr(integ, "rho_inf", None))


def test_backward_euler_from_the_start_reaches_the_extrapolated_guess_state():
    """Newton's first guess (the step's start, or the extrapolated motion)
    changes the iterations, not the steps' solutions (a swinging yarn), to
    Newton's tolerance (|F| reduced by 1e-7 or ε moving by < 1e-9 r)."""
    ends = {}
    for guess in ("extrapolated", "start"):
        model = pendulum(EI=1e-9)
        x, _, _ = integrate(BackwardEuler(model, 2e-3, guess=guess), model, 0.02)
        ends[guess] = gather(SELF, x)
    # measured 4.1e-9 r
    assert np.abs(ends["start"] - ends["extrapolated"]).max() < 5e-8 * model.fabric.radius


def falling_reduced(bodies=()):
    """The reduced model of a free 2 x 2 jersey (no constraint rows: each
    backward Euler step is the minimum of its Φ) over ``bodies``."""
    fab = jersey(2, 2)
    fab.bodies = tuple(bodies)
    return models(SELF, fab)[1]


def test_backtracking_is_the_line_search_where_a_body_moves():
    """Backward Euler on a model without constraint rows backtracks on Φ
    when a body moves (and lets Newton run to 60 iterations), takes full
    steps otherwise (25), and a user's -<kind>_snes_linesearch_type has the
    last word."""
    from knitfem.contact.colliders import Sphere
    from knitfem.contact.motion import Kinematic, Motion
    from solvers.libpetsc import line_search_type

    ball = Sphere(np.array([0.0, -0.02, 0.0]), 0.005)
    turning = Kinematic(ball, Motion([0.0, 1.0], [[0, 0, 0], [0, 0.001, 0]]))
    snes = [BackwardEuler(falling_reduced(b), 1e-3).snes for b in ((), (ball,), (turning,))]
    assert [line_search_type(s) for s in snes] == ["basic", "basic", "bt"]
    assert [s.getTolerances()[3] for s in snes] == [25, 25, 60]   # Newton's iterations
    opts = PETSc.Options()
    opts.setValue("reduced_snes_linesearch_type", "l2")
    try:
        assert line_search_type(BackwardEuler(falling_reduced((turning,)), 1e-3).snes) == "l2"
    finally:
        opts.delValue("reduced_snes_linesearch_type")


def test_a_line_search_that_finds_no_decrease_leaves_newton_to_full_steps():
    """Where backtracking finds no decrease of Φ (Φ at its round-off near the
    minimum; here an objective that rises at every call), the step does not
    fail:
    Newton goes on from its last iterate in full steps, to the states of
    the full-step line search, bit for bit."""
    from solvers.libpetsc import set_line_search

    ends = []
    for stuck in (False, True):
        red = falling_reduced()
        integ = BackwardEuler(red, 1e-3)
        if stuck:
            set_line_search(integ.snes, "bt")
            calls = itertools.count()
            integ.snes.setObjective(lambda snes, z: float(next(calls)))
        x, _, _ = integrate(integ, red, 5e-3)
        ends.append(x.getArray().copy())
        assert not stuck or next(calls) > 5               # it was tried
    assert np.array_equal(ends[0], ends[1]) and np.abs(ends[0]).max() > 0


def test_the_step_criterion_measures_newtons_step_not_the_update():
    """The convergence test's step criterion measures Newton's step, the
    update over the fraction of it taken (the line search's λ): an update
    a thousand times below the step tolerance, taken as 1e-6 of Newton's
    step, is not convergence; taken in full, or as half of a step within
    the tolerance, it is; cut by the step filter (0) it never is."""
    from solvers.integrators import step_convergence

    class Saddle:
        split = staticmethod(lambda y: (y, None))

    class System:
        yarn_move = staticmethod(lambda dy: 1e-15)

    class Snes:
        getSolutionUpdate = staticmethod(lambda: None)
        getTolerances = staticmethod(lambda: (1e-7, 1e-50, 0.0, 60))

    R = PETSc.SNES.ConvergedReason
    for fraction, converged in ((1e-6, False), (1.0, True), (0.5, True), (0.0, False)):
        test = step_convergence(Saddle(), lambda: 1e-12, System(), lambda: fraction)
        assert test(Snes(), 0, (0.0, 0.0, 1.0)) == R.ITERATING
        assert test(Snes(), 1, (0.0, 0.0, 0.5)) == (
            R.CONVERGED_SNORM_RELATIVE if converged else R.ITERATING)


def test_a_line_search_that_barely_moves_has_the_next_matrix_checked():
    """Where Newton convexifies, a backtracking search that took λ < 1e-6
    (Φ rose along the direction: a matrix indefinite after the step's first
    definite one) has the next Newton matrix checked for definiteness
    again; λ = 1 or 0.5 does not; the fraction taken is λ, 0 where the
    step filter cut the update."""
    import ctypes

    from knitfem.contact.colliders import Sphere
    from knitfem.contact.motion import Kinematic, Motion
    from solvers.libpetsc import _line_search, check, library

    turning = Kinematic(Sphere(np.array([0.0, -0.02, 0.0]), 0.005),
                        Motion([0.0, 1.0], [[0, 0, 0], [0, 0.001, 0]]))
    integ = BackwardEuler(falling_reduced((turning,)), 1e-3)
    integ.convexify = True                  # as a shell-stretched model's
    for lam, limited, checked in ((1.0, False, False), (0.5, False, False),
                                  (0.5, True, False), (1e-9, False, True)):
        check(library().SNESLineSearchSetLambda(_line_search(integ.snes),
                                                ctypes.c_double(lam)),
              "SNESLineSearchSetLambda")
        integ.definite, integ.limited = True, limited
        assert integ._taken() == (0.0 if limited else lam)
        assert integ.definite is not checked


def test_backtracking_reuses_the_objective_of_the_iterate_it_accepted():
    """A line search starts from the iterate the last one accepted, whose Φ
    is kept (a knit falling on a rising ball): the potential is evaluated
    once less an iteration, and the states are those of a Φ computed at
    every call, bit for bit."""
    from knitfem.contact.colliders import Sphere
    from knitfem.contact.motion import Kinematic, Motion

    ball = Kinematic(Sphere(np.array([0.002, -0.009, 0.0]), 0.005),
                     Motion([0.0, 1.0], [[0, 0, 0], [0, 0.05, 0]]))
    ends, calls, its = [], [], []
    for kept in (True, False):
        red = falling_reduced((ball,))
        integ = BackwardEuler(red, 2e-3)
        count = itertools.count()
        potential = red.potential
        red.potential = lambda q: (next(count), potential(q))[1]
        if not kept:
            objective = integ._objective
            integ.snes.setObjective(
                lambda snes, z: (setattr(integ, "phi_kept", None), objective(snes, z))[1])
        x, _, _ = integrate(integ, red, 3e-2)
        ends.append(x.getArray().copy())
        calls.append(next(count))
        its.append(integ.snes.getIterationNumber())
    assert np.array_equal(ends[0], ends[1]) and min(its) > 2
    # measured 635 against 886 (15 steps)
    assert calls[0] < 0.75 * calls[1]
