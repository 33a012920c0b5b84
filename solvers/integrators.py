"""Time integrators for a constrained mechanical system.

    M ε̈ = Q(ε, ε̇) + C(ε)ᵀλ,   g(ε) = 0,   C = ∂g/∂ε.

A *system* (``knitfem.model.FullModel``, ``knitfem.lod.reduced.ReducedModel``,
``knitfem.lod.mixed.MixedModel``) supplies M, ``forces(x, v, Q)``,
``stiffness(x, μ, w, xref)`` (K = ∂²E/∂ε² + w Σ μ_i ∇²g_i; with a state
``xref``, its axial force linearised from xref: the MIP matrix), the constraints
``constraint_residual(x, g)`` and ``constraint_jacobian(x)`` (C, a fixed
pattern; ``nonlinear_constraints`` says whether it depends on ε) and
``material.damping`` c_d (Q_d = −c_d M ε̇). The integrators never see a yarn.

Drift control is at the position level: every step asks g(ε_{n+1}) = 0 of
the end point ε_{n+1} = ε̂ + κ ε̇_{n+1} itself, as an equation of its Newton
solve, so constraint drift stays at the Newton tolerance.

Every integrator has ``step(t, ε, ε̇, t_stop)`` (one accepted step, in place;
returns the step ``dt`` taken and iteration counts), ``dt`` (the next step)
and ``state()``/``set_state()`` for checkpoints, and ``like(system)``
(itself, with its step control and settings, for another system). Step
sizes are chosen by a ``solvers.stepping.StepControl``: fixed, or by a
local error estimate.
"""

import numpy as np
from petsc4py import PETSc

from .halting import halt_if_requested, requested
from .libpetsc import line_search, line_search_lambda, set_line_search
from .progress import note
from .reasons import reason_name
from .saddle import (SaddlePoint, SolverFailure, negative_pivots, saddle_ksp,
                     solve_saddle)
from .stepping import PositionHistory, StepControl

__all__ = ["SimulationError", "SymplecticEuler", "NewtonStepper", "BackwardEuler",
           "GeneralizedAlpha", "BDF2", "INTEGRATORS"]

EV_SOLVE = PETSc.Log.Event("knitSaddleSolve")
EV_FACTOR = PETSc.Log.Event("knitFactor")
# a Newton solve of a step from its filtered prediction, failed ones too
# (PETSc's own events of a solve that fails inside MUMPS are never ended, so
# they miss its time)
EV_NEWTON = PETSc.Log.Event("knitNewtonSolve")
EV_INERTIA = PETSc.Log.Event("knitInertia")       # a factorisation for its pivots
EV_CONVEX = PETSc.Log.Event("knitConvexTangent")  # a Newton matrix convexified
EV_CONTROL = PETSc.Log.Event("knitStepControl")
# a step's lagged quantities and, where the yarn contact's pairs moved, its
# tangent pattern made again (``begin_step``, ``relayout``)
EV_BEGIN = PETSc.Log.Event("knitBeginStep")


class SimulationError(RuntimeError):
    """A step failed; the message names the step, the time and the quantity.
    ``curable``: a smaller step may succeed (Newton or a Krylov method that
    did not converge), as opposed to a zero pivot or a PETSc error, which
    stop the run at once."""

    def __init__(self, message, curable=True):
        super().__init__(message)
        self.curable = curable


def _default(prefix, name, value):
    """Set an option default unless the user gave it."""
    opts = PETSc.Options()
    if not opts.hasName(prefix + name):
        opts.setValue(prefix + name, value)


def step_convergence(saddle, step_tol, system, taken=lambda: 1.0):
    """SNES convergence test: PETSc's atol/rtol on |F|, or a Newton step
    that moves no yarn control point by more than ``step_tol()``
    (``system.yarn_move``: the coordinates' update through ε = Γ q, not the
    multipliers'). ``taken()``, called after every iteration, is the
    fraction of Newton's step the update took (the line search's λ), 0
    where the system's step limit cut it: the update over that fraction is
    Newton's step, and a cut one says nothing. The residual of stiff yarns
    carries round-off far above any absolute tolerance on |F|; and volume
    control points that carry almost no yarn (a near-null mode of Γᵀ M Γ)
    may move freely in the last iterations without moving a yarn. A request
    to stop (``halting.requested``) ends the solve at once (reported as
    DIVERGED_FUNCTION_COUNT; the integrator then raises ``Halted``)."""
    R = PETSc.SNES.ConvergedReason

    def test(snes, it, norms):
        if requested():
            return R.DIVERGED_FUNCTION_COUNT
        fnorm = norms[2]
        if it > 0:
            ynorm = system.yarn_move(saddle.split(snes.getSolutionUpdate())[0])
            fraction = taken()
        rtol, atol, _, max_it = snes.getTolerances()
        if not np.isfinite(fnorm):
            return R.DIVERGED_FNORM_NAN
        if fnorm <= atol:
            return R.CONVERGED_FNORM_ABS
        if it == 0:
            test.f0 = fnorm
            return R.ITERATING
        if fnorm <= rtol * test.f0:
            return R.CONVERGED_FNORM_RELATIVE
        if fraction > 0 and ynorm <= fraction * step_tol():
            return R.CONVERGED_SNORM_RELATIVE
        if it >= max_it:
            return R.DIVERGED_MAX_IT
        return R.ITERATING

    return test


def _mpi_op(name):
    """mpi4py's reduction ``name`` (MAX, LAND, …), mpi4py imported on use."""
    from mpi4py import MPI

    return getattr(MPI, name)


class SymplecticEuler:
    """Explicit symplectic Euler, the constraints held by SHAKE:

        [M     C_nᵀ] [v_{n+1}]   [M v_n + h Q(ε_n, v_n)]
        [C_n   0   ] [  μ    ] = [ −g(ε_n + h v_{n+1})/h ],   ε_{n+1} = ε_n + h v_{n+1},

    C_n = C(ε_n): the constraint force acts along the constraint normals at
    the start of the step and the end point satisfies g = 0, solved by
    iterations with the matrix at ε_n (a chord method, linear convergence by
    the change of C over a step) until |g(ε_{n+1})| ≤ 1e-9 r. Linear
    constraints need one solve, and the matrix (``-<kind>_explicit_`` KSP) is
    factorised once a run; nonlinear ones, once a step.
    """

    name = "symplectic"
    max_iterations = 50

    def __init__(self, system, dt, control=None):
        self.system, self.control = system, control or StepControl(dt)
        system.constraint_jacobian(system.start_state())
        self.saddle = SaddlePoint(system.M, system.C)
        self.ksp = saddle_ksp(self.saddle, f"{system.kind}_explicit_",
                              getattr(system, "null_space", False))
        with EV_FACTOR:
            self._solve(self.ksp.setUp)
        self.rhs, self.sol = self.saddle.createVec(), self.saddle.createVec()
        self.Q, self.Mv = system.M.createVecLeft(), system.M.createVecLeft()
        self.xe, self.g = system.M.createVecLeft(), system.C.createVecLeft()
        self.tol = 1e-9 * system.fabric.radius

    @property
    def dt(self):
        return self.control.dt

    def like(self, system):
        """This integrator, its step control and its settings, for another
        system (an adaptive run's new mixed model)."""
        return type(self)(system, self.dt, self.control)

    def state(self):
        return self.control.state()

    def set_state(self, st):
        self.control.set_state(st)

    def _solve(self, solve=None):
        """The saddle solve (or ``solve``, e.g. the set-up), a solver failure
        as a SimulationError; returns the KSP iterations."""
        with EV_SOLVE:
            try:
                solve_saddle(solve or (lambda: self.ksp.solve(self.rhs, self.sol)),
                             self.ksp)
            except SolverFailure as err:
                raise SimulationError(str(err), curable=False) from None
        return self.ksp.getIterationNumber()

    def step(self, t, x, v, t_stop=None):
        s, h = self.system, self.control.propose(t, t_stop)[0]
        s.move_bodies(t, t)                     # forces where the bodies are now
        s.forces(x, v, self.Q)
        s.M.mult(v, self.Mv)
        self.Mv.axpy(h, self.Q)
        if s.nonlinear_constraints:
            s.constraint_jacobian(x)
            self.saddle.update(constraints=True)
        rhs_u, rhs_l = self.saddle.split(self.rhs)
        rhs_u[:] = self.Mv.getArray(readonly=True)
        s.constraint_residual(x, self.g)
        rhs_l[:] = -self.g.getArray(readonly=True) / h
        its = self._solve()
        vv = self.saddle.split(self.sol)[0]
        for _ in range(self.max_iterations if s.nonlinear_constraints else 0):
            self.xe.getArray()[:] = x.getArray(readonly=True) + h * vv
            s.constraint_residual(self.xe, self.g)
            g = self.g.getArray(readonly=True)
            worst = s.comm.tompi4py().allreduce(np.abs(g).max() if g.size else 0.0,
                                                op=_mpi_op("MAX"))
            if worst <= self.tol:
                break
            if not np.isfinite(worst):
                raise SimulationError(f"constraint residual g not finite in SHAKE "
                                      f"(h = {h:.3g} s)")
            rhs_l -= g / h              # the chord step for the end point
            its += self._solve()
            vv = self.saddle.split(self.sol)[0]
        else:
            if s.nonlinear_constraints:
                raise SimulationError(f"SHAKE did not hold the constraints in "
                                      f"{self.max_iterations} iterations (|g| = "
                                      f"{worst:.3e} m, h = {h:.3g} s)")
        v.getArray()[:] = vv
        x.axpy(h, v)
        return {"newton": 0, "ksp": its, "rejected": 0, "linear_failures": 0, "dt": h}


class NewtonStepper:
    """One implicit step on the constrained saddle point, solved by Newton
    (PETSc SNES, prefix ``-<kind>_``); the integrators are small subclasses.

    The unknowns are z = (v, μ), v = ε̇_{n+1} and μ = −σλ. A method gives,
    for a step h, the end point ε_{n+1} = ε̂ + κ v, the point where forces
    are evaluated, ε_f = (1 − w) ε_n + w ε_{n+1} (and ε̇_f alike), and

        F_u = M (v − v̂) − σ Q(ε_f, ε̇_f) + C(ε_{n+1})ᵀ μ,
        F_λ = g(ε_{n+1}) / κ,

    so g(ε_{n+1}) = 0 holds to the Newton tolerance at every step. With
    K = ∂²E/∂ε² and Q_d = −c_d M ε̇ the Jacobian is [A Cᵀ; C 0], C at ε_{n+1},

        A = σ w κ K(ε_f) + (1 + σ w c_d) M + κ Σ_i μ_i ∇²g_i,

    assembled as one AIJ matrix (or dense for the reduced model on one rank)
    and solved by ``-<kind>_ksp_type``, ``-<kind>_pc_type`` … (MUMPS LDLᵀ by
    default). ``-<kind>_snes_type ksponly`` makes the step linearly implicit
    (one Newton iteration).

    The Newton matrix (``tangent``). With "mip" K's axial force is the one
    linearised from the last Newton iterate (the mixed integration point
    Newton of Magisano, Leonetti & Garcea, CMAME 313, 2017;
    ``yarn.stretch_terms``): the Newton iteration of the stretch with its
    axial force an unknown of its own at each Gauss point, condensed, so the
    pattern, the residual and the solution are those of the displacement
    form, but an update that turns a stiff yarn no longer gives the next
    matrix the axial force of the linearised turn's stretch. The first
    iteration of a step linearises from ε_n; a MIP solve that fails is solved
    again with the exact matrix. "exact" (the default here) is A = ∂F/∂z
    itself. "auto" (the command line's default) is MIP on a first step, where
    the predictor knows no velocity, and exact after: MIP pays on a large
    step from rest (hanging 20×40, 1e-2 s: 18 Newton iterations exact, 6 MIP,
    the same state) but not once the knit moves (hanging 7×7, 0.3 s, BDF2:
    2 567 exact, 4 257 MIP, 2 533 auto).

    Why not PETSc's TS: TSALPHA2 and TSBDF integrate every component of
    their state, so the multipliers λ of the index-3 rows C ε = d would be
    carried as differential unknowns (TSALPHA2 gives them Newmark
    "velocities" and "accelerations", and both put them into the local
    error estimate), and PETSc 3.18 has no hook for the consistent start
    (projected ε̇₀ and ε̈₀) the constrained α-method needs. Differentiating
    the constraints to index 1 would let C ε = d drift. So the step is
    written here, on the same SNES, and the step control is ``StepControl``.

    Steps are fixed (``dt``) unless ``control`` is adaptive. A failed Newton
    solve at a fixed step is retried as two half steps, down to
    dt / 2^max_halvings; under step control it is a rejected step.

    The step as a minimum. Without constraint rows, a method whose forces
    are taken at the end point (w = 1: backward Euler, BDF2) solves F_u = 0
    as the minimum of

        Φ(v) = ½ (v − v̂)ᵀ M (v − v̂) + (σ/κ) Π(ε̂ + κ v) + ½ σ c_d vᵀ M v,

    ∂Φ/∂v = F_u, Π = E + D − Q_gᵀ ε the system's ``potential`` (its
    barriers and lagged friction D included). SNES gets Φ as its objective,
    which the line searches that take one use
    (``-<kind>_snes_linesearch_type bt``: Armijo backtracking on Φ, as in
    IPC's incremental potential), and ``basic`` (full steps) ignores.

    The line search. Full steps by default; backtracking on Φ where a body
    moves. A body that moves drags its contacts along it near the friction
    cone's edge, where the slip's direction turns within an update and full
    steps cycle (the reduced 16×10 sleeve on a bending arm: 1 710 Newton
    iterations for 0.5 s in full steps, 563 backtracking); where bodies
    rest, a knit landing on them does better in full steps, which backtracking
    cuts to a tenth as the barrier rises (the reduced 12×12 drape: 884
    against 2 707). A backtracking search that finds no decrease (Φ at its
    round-off near the minimum) hands the solve to full steps from where it
    stopped (``_in_full_steps``). ``-<kind>_snes_linesearch_type`` chooses.

    Convergence. |F| to 1e-7 of its start (``-<kind>_snes_rtol``), or a
    Newton step that moves no yarn point by more than 1e-9 r: the step,
    not the update the line search took, which is λ times it
    (``step_convergence``; a search cut to λ ~ 1e-10 once ended steps of the
    60×120 sleeve at |F| 4e-3 of their start). Where Newton backtracks on
    a moving body, |F| to the system's ``moving_body_rtol`` of its start
    (1e-6 unless it says otherwise; the reduced model's is 1e-4).

    A convex Newton matrix where it backtracks. Backtracking needs a descent
    direction, which an indefinite matrix does not give. A system whose
    tangent can turn indefinite offers a convex one (``convex_tangent``,
    ``stiffness(..., convex=True)``: the reduced model's shell stretch
    without its compressed stitches' negative stiffness). At each iteration
    of a step until the first whose exact matrix is positive definite, that
    matrix is factorised and, where MUMPS's LDLᵀ finds negative pivots,
    replaced by the convex one (``-log_view``'s events knitInertia and
    knitConvexTangent count them); from then on it is the exact one, so
    Newton converges as fast as before near the solution, unless a line
    search finds next to no decrease of Φ along its direction (λ < 1e-6:
    the exact matrix turned indefinite again), after which the next one is
    checked again. On a sleeve whose
    forearm turns, the step's start carried with the arm compresses the
    stitches at the elbow and the exact matrix has generalised eigenvalues
    down to −3e5 M: its first updates moved the yarns by several radii,
    against the filter, for about five iterations a step. The 60×120
    sleeve's bend takes 492 Newton iterations where it took 1 035. Where
    full steps are taken the exact matrix is kept (the 12×12 drape took
    1 315 iterations with this, 777 without).
    """

    order = 1
    newton_ctol = 0.0
    minimises = False                   # w = 1: a step is the minimum of Φ
    TANGENTS = ("auto", "mip", "exact")

    def __init__(self, system, dt, control=None, tangent="exact"):
        if tangent not in self.TANGENTS:
            raise ValueError(f"tangent {tangent!r}: use one of {', '.join(self.TANGENTS)}")
        self.tangent = tangent
        self.mip = False                    # the solve now running is MIP
        self.steps = 0                      # accepted steps (0: no history yet)
        self.system = system
        self.control = control or StepControl(dt)
        self.prefix = prefix = f"{system.kind}_"
        x0 = system.start_state()
        self._layout(x0)
        x0.destroy()
        self.snes = PETSc.SNES().create(comm=system.comm)
        self.snes.setOptionsPrefix(prefix)
        self.F, self.z = self.saddle.createVec(), self.saddle.createVec()
        self.snes.setFunction(self._residual, self.F)
        barrier = getattr(getattr(system, "full", system), "barrier", None)
        self.bodies = barrier is not None
        self.yarn_contact = getattr(system, "yarn_contact", None) is not None
        self.snes.setJacobian(self._jacobian, self.saddle.K, self.saddle.P)
        self.snes.setType("newtonls")
        # converged when the update moves ε by < newton_tol: 1e-9 yarn radii at
        # fixed steps, 1e-2 of the local error tolerance under step control
        self.limited = False                # the last update was shortened
                                            # (a body's step limit, the yarn
                                            # contact's filter)
        self.snes.setConvergenceTest(self._missing_entries(step_convergence(
            self.saddle, lambda: self.newton_tol / self.kappa, system,
            self._taken)))
        # the step as a minimum of Φ (class docstring): backtracking on Φ where
        # a body moves; Φ then falls at every iteration, and a solve is let
        # run to 60 (the landing of a sleeve on an arm takes 25 to 60 and
        # converges: a halved step would throw them away), else 25; there
        # |F| to the system's moving_body_rtol of its start, else 1e-7
        # (class docstring)
        self.descent = self.minimises and not self.saddle.constrained and \
            getattr(system, "potential", None) is not None
        backtracks = self.descent and self.bodies and barrier.moves
        set_line_search(self.snes, "bt" if backtracks else "basic")
        # where it backtracks, Newton's matrices are the system's convex
        # tangent until the first definite one of a step (class docstring)
        self.convexify = backtracks and getattr(system, "convex_tangent", False)
        self.definite = False               # a definite Newton matrix this step
        rtol = getattr(system, "moving_body_rtol", 1e-6) if backtracks else 1e-7
        self.snes.setTolerances(rtol=rtol, atol=1e-50,
                                max_it=60 if backtracks else 25)
        self.null_space = getattr(system, "null_space", False)
        self.ksp = saddle_ksp(self.saddle, prefix, self.null_space)
        self.snes.setKSP(self.ksp)
        self.snes.setFromOptions()
        if self.bodies or self.yarn_contact:
            self.snes.setLineSearchPreCheck(self._limit)
        if self.descent:
            self.snes.setObjective(self._objective)
        self.missing = None                 # tangent entries missed before a solve
        self.phi_kept = None                # (z, Φ) of the last objective
        self.user_atol = PETSc.Options().hasName(prefix + "snes_atol")
        new = system.M.createVecLeft
        self.v, self.xe, self.xf, self.vf = new(), new(), new(), new()
        self.vhat, self.xhat, self.e = new(), new(), new()
        self.xref = new()                   # where the last tangent was formed
        self.dxe = new()                    # a Newton update's move of ε_{n+1}
        self.Q, self.Mv, self.tmp = new(), new(), new()
        self.mu, self.Cx = system.C.createVecLeft(), system.C.createVecLeft()
        self.lam = system.C.createVecLeft()          # −λ of the last step
        self.xn = self.vn = None
        self.h = self.sigma = self.kappa = dt
        self.newton_tol = 1e-9 * system.fabric.radius
        self.w = 1.0
        self.max_halvings = 6

    @property
    def dt(self):
        """The fixed step, or the next trial step under step control."""
        return self.control.dt

    def _layout(self, x):
        """The Newton matrix A on the tangent's pattern at x, M in A's
        pattern (MA), the saddle point (MUMPS analyses it on first use)."""
        system = self.system
        K = system.stiffness(x)
        self.A = K.duplicate(copy=True)
        self.A.axpy(1.0, system.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        # M in A's pattern: A = a K + b M is then one axpy of equal patterns
        self.MA = self.A.duplicate()
        self.MA.axpy(1.0, system.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        self.saddle = SaddlePoint(self.A, system.constraint_jacobian(x),
                                  dense=getattr(system, "dense_saddle", False),
                                  prefix=self.prefix,
                                  blocks=getattr(system, "yarn_blocks", None))

    def relayout(self, x):
        """A, MA, the saddle point and its KSP made again on the system's new
        tangent pattern (the yarn contact's pairs moved; ``begin_step``)."""
        for obj in (self.ksp, self.saddle, self.A, self.MA):
            obj.destroy()
        self._layout(x)
        self.snes.setJacobian(self._jacobian, self.saddle.K, self.saddle.P)
        self.ksp = saddle_ksp(self.saddle, self.prefix, self.null_space)
        self.snes.setKSP(self.ksp)

    def _missing_entries(self, test):
        """``test``, but a Newton whose matrix lacked entries of the tangent
        (``system.tangent_missed``: the yarn contact's pairs left its
        pattern) stops at once, to be solved again on a new pattern
        (``_solve``)."""
        R = PETSc.SNES.ConvergedReason

        def stop_or_test(snes, it, norms):
            if self.missing is not None and it > 0 and \
                    self.system.tangent_missed() > self.missing:
                return R.DIVERGED_MAX_IT
            return test(snes, it, norms)

        return stop_or_test

    def _step_fraction(self, z, y):
        """Newton's update z ← z − y moves ε from ε̂ + κ v by −κ y_v: the
        fraction of it the yarn contact allows (``step_fraction``; local
        arrays, collective)."""
        nu = self.saddle.nu
        x0 = self.xhat.getArray(readonly=True) + self.kappa * z[:nu]
        return self.system.step_fraction(x0, x0 - self.kappa * y[:nu])

    def like(self, system):
        """This integrator, its step control and its settings (the Newton
        matrix, ρ∞), for another system (an adaptive run's new mixed model);
        it starts as from a first step."""
        return type(self)(system, self.dt, self.control, **self.settings())

    def settings(self):
        """The constructor's keyword arguments this integrator was made with."""
        return dict(tangent=self.tangent)

    # -- the method: subclasses ----------------------------------------------
    def coefficients(self, h):
        """Set σ, κ, w, v̂ and ε̂ for a step h from (self.xn, self.vn)."""
        raise NotImplementedError

    def predict(self, h, v):
        """Explicit predictor of ε̇_{n+1} (the first Newton guess), into v."""
        raise NotImplementedError

    def one_step_error(self, h):
        """Local error estimate of ε_{n+1} into self.e from this step alone
        (until ``history`` knows enough positions)."""
        raise NotImplementedError

    def error(self, h):
        """Local error estimate of ε_{n+1} into self.e (adaptive steps): from
        the position history (``PositionHistory``), else ``one_step_error``."""
        if not self.history.estimate(self.xe.getArray(readonly=True), h,
                                     self.e.getArray()):
            self.one_step_error(h)

    def accepted(self, h):
        """Update the method's own history after an accepted step."""

    def start(self, x, v):
        """Prepare the first step from (x, v)."""

    # -- Newton ----------------------------------------------------------------
    def _unpack(self, z):
        u, lam = self.saddle.split(z)
        self.v.getArray()[:] = u
        self.mu.getArray()[:] = lam
        self.xe.waxpy(self.kappa, self.v, self.xhat)
        if self.w == 1.0:
            self.xe.copy(self.xf)
            self.v.copy(self.vf)
        else:
            self.xf.waxpy(-1.0, self.xn, self.xe)      # ε_n + w (ε_{n+1} − ε_n)
            self.xf.aypx(self.w, self.xn)
            self.vf.waxpy(-1.0, self.vn, self.v)
            self.vf.aypx(self.w, self.vn)

    def _residual(self, snes, z, F):
        s = self.system
        self._unpack(z)
        s.forces(self.xf, self.vf, self.Q)
        self.tmp.waxpy(-1.0, self.vhat, self.v)
        s.M.mult(self.tmp, self.Mv)
        self.Mv.axpy(-self.sigma, self.Q)
        fu, fl = self.saddle.split(F)
        fu[:] = self.Mv.getArray(readonly=True)
        if self.saddle.constrained:
            s.constraint_jacobian(self.xe).multTranspose(self.mu, self.tmp)
            fu += self.tmp.getArray(readonly=True)
            s.constraint_residual(self.xe, self.Cx)
            fl[:] = self.Cx.getArray(readonly=True) / self.kappa

    def _objective(self, snes, z):
        """Φ at z = (v, μ) (class docstring; collective), kept for the last z
        of a solve: a line search starts from the iterate its last one
        accepted, whose Φ it has just computed."""
        zz = z.getArray(readonly=True)
        same = self.phi_kept is not None and np.array_equal(self.phi_kept[0], zz)
        if z.getComm().tompi4py().allreduce(same, op=_mpi_op("LAND")):
            return self.phi_kept[1]
        phi = self._phi(z)
        self.phi_kept = (zz.copy(), phi)
        return phi

    def _phi(self, z):
        s = self.system
        self._unpack(z)
        self.tmp.waxpy(-1.0, self.vhat, self.v)
        s.M.mult(self.tmp, self.Mv)
        phi = 0.5 * self.tmp.dot(self.Mv) + self.sigma / self.kappa * s.potential(self.xe)
        c_d = s.material.damping
        if c_d:
            s.M.mult(self.v, self.Mv)
            phi += 0.5 * self.sigma * c_d * self.v.dot(self.Mv)
        return phi

    def _limit(self, z, y):
        """Newton's update −y of z (Vecs) shortened to the largest fraction
        τ that stops every yarn at a body's surface (the system's
        ``step_limit`` on the end point's move −κ y_u) and keeps the yarns
        apart (``_step_fraction``). An update so cut is ``limited``: a
        short update there is not convergence."""
        tau = 1.0
        if self.bodies:
            self._unpack(z)
            self.dxe.getArray()[:] = -self.kappa * self.saddle.split(y)[0]
            tau = self.system.step_limit(self.xe, self.dxe)
        if self.yarn_contact:
            tau = min(tau, self._step_fraction(z.getArray(readonly=True),
                                               y.getArray(readonly=True)))
        self.limited = tau < 1.0
        if tau < 1.0:
            y.scale(tau)

    def _taken(self):
        """The fraction of Newton's step its last update took, for the
        convergence test: the line search's λ, 0 where the step filter cut
        it (``limited``). A line search that found next to no decrease of Φ
        (λ < 1e-6; where it backtracks, a Newton matrix that turned
        indefinite after the step's first definite one gives a direction
        along which Φ rises) has the next Newton matrix checked again, and
        made convex if it is not definite."""
        lam = line_search_lambda(self.snes)
        if lam < 1e-6 and self.convexify:
            self.definite = False
        return 0.0 if self.limited else lam

    def _jacobian(self, snes, z, J, P):
        self._unpack(z)
        self._newton_matrix()
        if self.convexify and not self.definite:
            with EV_INERTIA:
                negative = negative_pivots(self.ksp)
            self.definite = not negative
            if negative:
                with EV_CONVEX:
                    self._newton_matrix(convex=True)
        if self.mip:
            self.xf.copy(self.xref)

    def _newton_matrix(self, **convex):
        """A (class docstring) at the unpacked state, the system's tangent
        ``convex`` where asked (``convexify``)."""
        s = self.system
        sw = self.sigma * self.w
        K = s.stiffness(self.xf, self.mu if self.saddle.constrained else None,
                        1.0 / sw, xref=self.xref if self.mip else None, **convex)
        K.copy(self.A, PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        self.A.scale(sw * self.kappa)
        self.A.axpy(1.0 + sw * s.material.damping, self.MA,
                    PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        s.constraint_jacobian(self.xe)
        self.saddle.update(constraints=s.nonlinear_constraints)

    def _solve(self, h, stats):
        """Newton for the step h from (self.xn, self.vn): leaves ε_{n+1} in
        self.xe and ε̇_{n+1} in self.v; raises SimulationError on failure."""
        s = self.system
        self.h = h
        s.move_bodies(self.t_n, self.t_n + h, self.xn)  # bodies where they are at its end
        self.coefficients(h)
        c = self.control
        if c.adaptive:
            # the update of ε small against the local error tolerance
            scale = c.atol + c.rtol * self.xn.norm(PETSc.NormType.INFINITY)
            self.newton_tol = max(self.newton_ctol * scale,
                                  1e-9 * s.fabric.radius)
        if not self.user_atol:
            s.M.mult(self.vn, self.Mv)
            scale = self.Mv.norm() + self.sigma * s.Qg.norm()
            floor = 1e-14 * s.total_mass * s.fabric.radius / self.kappa
            self.snes.setTolerances(atol=max(1e-12 * scale, floor))
        # a MIP Newton that fails is tried again with the exact matrix
        mip = self.tangent == "mip" or (self.tangent == "auto" and not self.steps)
        for self.mip in (True, False) if mip else (False,):
            self._newton(h, stats)
            if self.snes.getConvergedReason() > 0 or self._in_full_steps(stats):
                break
            if self._pattern_left():
                self._newton(h, stats)
                if self.snes.getConvergedReason() > 0:
                    break
        else:
            raise SimulationError(f"Newton did not converge ({reason_name(self.snes)}, "
                                  f"|F| = {self.snes.getFunctionNorm():.3e}, "
                                  f"h = {h:.3g} s)")
        self._unpack(self.z)
        crossed = s.tunnelled(self.xn, self.xe)       # a step through a body
        if crossed:
            raise SimulationError(f"{crossed}, h = {h:.3g} s")

    def _newton(self, h, stats):
        """One Newton solve of the step h from the predictor."""
        self.phi_kept = None                   # Φ changes with the step
        self.definite = False                  # no definite Newton matrix yet
        with EV_NEWTON:
            self.predict(h, self.tmp)
            if self.yarn_contact:
                self._filter_prediction()
                self.missing = self.system.tangent_missed()
            self.xn.copy(self.xref)
            zu, zl = self.saddle.split(self.z)
            zu[:] = self.tmp.getArray(readonly=True)
            zl[:] = self.lam.getArray(readonly=True) * self.sigma
            self._snes_solve(stats)
        halt_if_requested()

    def _snes_solve(self, stats):
        """SNES from the iterate in self.z, its iterations counted; a linear
        solver's failure raised as a SimulationError."""
        try:
            solve_saddle(lambda: self.snes.solve(None, self.z), self.snes.getKSP())
        except SolverFailure as err:
            stats["linear_failures"] += 1
            raise SimulationError(f"{err}, h = {self.h:.3g} s", err.curable) from None
        finally:
            stats["newton"] += self.snes.getIterationNumber()
            stats["ksp"] += self.snes.getLinearSolveIterations()

    def _in_full_steps(self, stats):
        """After a line search that found no decrease of Φ (a backtracking
        one; at round-off of Φ near the minimum, or where the Newton
        direction is poor): Newton goes on from its last iterate in full
        steps (the ``basic`` line search), its first matrix checked for
        definiteness again where it convexifies; whether it converged. (PETSc
        reports a failed search as DIVERGED_LOCAL_MIN where |F|² looks
        minimal.)"""
        R = PETSc.SNES.ConvergedReason
        if self.snes.getConvergedReason() not in (R.DIVERGED_LINE_SEARCH, R.DIVERGED_LOCAL_MIN):
            return False
        self.definite = False           # a direction that did not descend: checked
        with line_search(self.snes, "basic"):
            self._snes_solve(stats)
        return self.snes.getConvergedReason() > 0

    def _pattern_left(self):
        """After a failed Newton: if its matrix lacked tangent entries, the
        system's pattern laid out again at the last iterate and the Newton
        matrix with it; whether it was."""
        if self.missing is None or self.system.tangent_missed() <= self.missing:
            return False
        self._unpack(self.z)
        self.system.drop_tangent()
        self.relayout(self.xe)
        return True

    def _filter_prediction(self):
        """The predicted ε_{n+1} = ε̂ + κ v (v in self.tmp) brought back
        along the straight path from ε_n as far as the system allows."""
        v = self.tmp.getArray()
        xn, xhat = self.xn.getArray(readonly=True), self.xhat.getArray(readonly=True)
        x1 = xhat + self.kappa * v
        t = self.system.step_fraction(xn, x1)
        if t < 1.0:
            v[:] = (xn + t * (x1 - xn) - xhat) / self.kappa

    def _commit(self, x, v, h):
        self.steps += 1
        self.t_n += h
        self.accepted(h)
        if self.control.adaptive:
            self.history.push(self.xe.getArray(readonly=True), h)
        self.lam.getArray()[:] = self.mu.getArray(readonly=True) / self.sigma
        self.xe.copy(x)
        self.v.copy(v)

    # -- the step ------------------------------------------------------------
    def step(self, t, x, v, t_stop=None):
        """Advance (ε, ε̇) in place by one accepted step, landing on t_stop
        when it is within reach. Returns the step taken ``dt``, the Newton
        and KSP iterations and the rejected trial steps."""
        if self.xn is None:
            self.xn, self.vn = x.duplicate(), v.duplicate()
            x.copy(self.xn)
            v.copy(self.vn)
            self.start(x, v)
            self.history.start(x.getArray(readonly=True))
        stats = {"newton": 0, "ksp": 0, "rejected": 0, "linear_failures": 0}
        with EV_BEGIN:
            if self.system.begin_step(x, t):    # lagged quantities (friction)
                self.relayout(x)                # a new tangent pattern
        self.t_n = t                            # where the next (part) step starts
        c = self.control
        while True:
            h, landed = c.propose(t, t_stop)
            x.copy(self.xn)
            v.copy(self.vn)
            if not c.adaptive:
                self._advance(x, v, h, 0, stats)
                stats["dt"] = h
                return stats
            try:
                self._solve(h, stats)
            except SimulationError as err:
                stats["rejected"] += 1
                self.cure_or_stop(err, stats)
                if not c.newton_failed(h):
                    raise SimulationError(f"{err}; the step fell below "
                                          f"-knit_dt_min {c.dt_min:g} s") from None
                note(f"retried with dt {c.dt:.2e} s ({err})")
                continue
            with EV_CONTROL:
                self.error(h)
                err = c.norm(self.system.comm, self.e.getArray(readonly=True),
                             self.xn.getArray(readonly=True),
                             self.xe.getArray(readonly=True))
                good = c.judge(err, h, self.order, landed)
            if good is None:
                raise SimulationError(f"local error {err:.3g} times the tolerance at "
                                      f"dt {h:.2e} s; the step fell below "
                                      f"-knit_dt_min {c.dt_min:g} s")
            if good:
                self._commit(x, v, h)
                stats["dt"] = h
                return stats
            stats["rejected"] += 1
            note(f"retried with dt {c.dt:.2e} s (local error {err:.3g} times the "
                 f"tolerance at dt {h:.2e} s)")

    def _advance(self, x, v, h, depth, stats):
        """A fixed step h, retried as two half steps when Newton fails."""
        try:
            x.copy(self.xn)
            v.copy(self.vn)
            self._solve(h, stats)
            self._commit(x, v, h)
        except SimulationError as err:
            self.cure_or_stop(err, stats)
            if depth >= self.max_halvings:
                raise
            note(f"retried as two steps of {h / 2:.2e} s ({err})")
            for _ in range(2):
                self._advance(x, v, h / 2, depth + 1, stats)

    linear_retries = 4

    def cure_or_stop(self, err, stats):
        """Re-raise a failure that a smaller step cannot cure: a zero pivot or
        a PETSc error, or a linear solver that failed ``linear_retries``
        times in one step, the step halved each time."""
        if not err.curable:
            raise err
        if stats["linear_failures"] >= self.linear_retries:
            raise SimulationError(f"{err}; {stats['linear_failures']} linear solves "
                                  f"failed as the step was halved", False) from None

    # -- checkpoints -----------------------------------------------------------
    def state(self):
        """Everything beyond (t, ε, ε̇) the next step needs to continue
        bit-exactly: local arrays and floats (collective only in the sense
        that every rank holds its own part)."""
        st = self.control.state()
        if self.history.x:
            st.update(self.history.state())
        st["lam"] = self.lam.getArray(readonly=True).copy()
        return st

    def set_state(self, st):
        self.control.set_state(st)
        if "history_t" in st:
            self.history.set_state(st)
        self.lam.getArray()[:] = st["lam"]
        self.steps = max(self.steps, 1)      # a checkpoint follows a step


class BackwardEuler(NewtonStepper):
    """Implicit (backward) Euler, order 1:

        ε_{n+1} = ε_n + h ε̇_{n+1},
        M (ε̇_{n+1} − ε̇_n) = h Q(ε_{n+1}, ε̇_{n+1}) + h Cᵀλ,

    (σ = κ = h, w = 1, v̂ = ε̇_n, ε̂ = ε_n), so A = h² K + (1 + h c_d) M.
    Predictor ε̇_n + h a_n with a_n = (ε̇_n − ε̇_{n−1}) / h_{n−1}, or, with
    ``guess="start"``, ε̇ = 0: Newton from the step's start ε_n, which a
    knit on a body can always reach (an extrapolation drives a falling knit
    into the body's barrier: the 12×12 reduced drape takes 1 214 Newton
    iterations from it, 884 from the start), carried with the moving bodies
    near it (the system's ``carry``, when it has one): a sleeve goes with
    the arm that turns inside it, sticking where it was. Local error e = ½ h² ε̈
    (``PositionHistory`` with c = ½; on the first step ½ h (ε̇_{n+1} − ε̇_n)).
    """

    name = "implicit"
    order = 1
    minimises = True

    def __init__(self, system, dt, control=None, guess="extrapolated", **kw):
        super().__init__(system, dt, control, **kw)
        if guess not in ("extrapolated", "start"):
            raise ValueError(f"guess {guess!r}: expected extrapolated or start")
        self.guess = guess
        self.a = system.M.createVecLeft()      # backward-difference ε̈_n
        self.history = PositionHistory(1, 0.5)

    def settings(self):
        return dict(super().settings(), guess=self.guess)

    def coefficients(self, h):
        self.sigma = self.kappa = h
        self.w = 1.0
        self.vn.copy(self.vhat)
        self.xn.copy(self.xhat)

    def predict(self, h, v):
        if self.guess == "start":
            v.zeroEntries()
            carry = getattr(self.system, "carry", None)
            if carry is not None:
                carry(self.xn, self.t_n, self.t_n + h, v, 1.0 / self.kappa)
        else:
            v.waxpy(h, self.a, self.vn)

    def one_step_error(self, h):
        self.e.waxpy(-1.0, self.vn, self.v)
        self.e.scale(0.5 * h)

    def accepted(self, h):
        self.a.waxpy(-1.0, self.vn, self.v)
        self.a.scale(1.0 / h)

    def state(self):
        return dict(super().state(), a=self.a.getArray(readonly=True).copy())

    def set_state(self, st):
        super().set_state(st)
        self.a.getArray()[:] = st["a"]


class GeneralizedAlpha(NewtonStepper):
    """Generalized-α for constrained mechanical systems (Arnold & Brüls,
    Multibody Syst. Dyn. 18, 2007): the equations of motion hold at t_{n+1},

        M ε̈_{n+1} = Q(ε_{n+1}, ε̇_{n+1}) + C(ε_{n+1})ᵀλ,   g(ε_{n+1}) = 0,
        ε_{n+1} = ε_n + h ε̇_n + h² ((½ − β) a_n + β a_{n+1}),
        ε̇_{n+1} = ε̇_n + h ((1 − γ) a_n + γ a_{n+1}),
        (1 − αm) a_{n+1} + αm a_n = (1 − αf) ε̈_{n+1} + αf ε̈_n,

    with the pseudo-acceleration a, and from the spectral radius ρ∞ at
    infinite frequency (1: no numerical dissipation, 0: annihilation)

        αm = (2ρ∞ − 1)/(ρ∞ + 1),  αf = ρ∞/(ρ∞ + 1),
        γ = ½ − αm + αf,           β = ¼ (1 − αm + αf)².

    Forces and constraint forces at the same state keep the Newton matrix
    symmetric, and the method is second order for the index-3 system
    (Chung & Hulbert's form, forces at an α-interpolated state and
    constraints at t_{n+1}, fed the stiff axial modes energy with the
    nonlinear contacts). In the Newton unknown v = ε̇_{n+1}:
    a_{n+1} = (v − ε̇_n − h(1 − γ)a_n)/(γh), κ = hβ/γ, w = 1,
    σ = γh(1 − αf)/(1 − αm),
    v̂ = ε̇_n + h(1 − γ)a_n − σ (αm a_n − αf ε̈_n)/(1 − αf) and
    ε̂ = ε_n + h ε̇_n + h²(½ − β)a_n − κ(ε̇_n + h(1 − γ)a_n).

    The start projects ε̇₀ onto C ε̇ = 0 and solves M ε̈₀ = Q₀ + Cᵀλ,
    C ε̈₀ = −ε̇₀ᵀ∇²g ε̇₀ (the same saddle point with A = M, C at ε₀), and
    a₀ = ε̈₀, so the start is consistent with g = 0 to second order.
    The local error of ε_{n+1} is c h³ ε⃛, c = β − ⅙ + (αm − αf)/2,
    estimated from the last three positions (``PositionHistory``; with
    h ε⃛ ≈ a_{n+1} − a_n on the first two steps). Predictor: a_{n+1} ≈ a_n.
    """

    name = "alpha"
    order = 2

    def __init__(self, system, dt, control=None, rho_inf=0.5, **kw):
        super().__init__(system, dt, control, **kw)
        r = rho_inf
        self.rho_inf = r
        self.alpha_m, self.alpha_f = (2 * r - 1) / (r + 1), r / (r + 1)
        self.gamma = 0.5 - self.alpha_m + self.alpha_f
        self.beta = 0.25 * (1 - self.alpha_m + self.alpha_f) ** 2
        self.a, self.a1 = system.M.createVecLeft(), system.M.createVecLeft()
        self.acc = system.M.createVecLeft()        # ε̈_n
        self.started = False
        self.c_error = self.beta - 1.0 / 6.0 + 0.5 * (self.alpha_m - self.alpha_f)
        self.history = PositionHistory(2, self.c_error)

    def settings(self):
        return dict(super().settings(), rho_inf=self.rho_inf)

    def coefficients(self, h):
        am, af, g, b = self.alpha_m, self.alpha_f, self.gamma, self.beta
        self.kappa = h * b / g
        self.w = 1.0
        self.sigma = g * h * (1.0 - af) / (1.0 - am)
        self.vhat.waxpy(h * (1.0 - g) - self.sigma * am / (1.0 - af), self.a, self.vn)
        self.vhat.axpy(self.sigma * af / (1.0 - af), self.acc)
        self.xhat.waxpy(h, self.vn, self.xn)
        self.xhat.axpy(h * h * (0.5 - b) - self.kappa * h * (1.0 - g), self.a)
        self.xhat.axpy(-self.kappa, self.vn)

    def predict(self, h, v):
        v.waxpy(h, self.a, self.vn)

    def _acceleration(self, h, out):
        """a_{n+1} = (v − ε̇_n − h(1 − γ)a_n)/(γh) into out."""
        out.waxpy(-1.0, self.vn, self.v)
        out.axpy(-h * (1.0 - self.gamma), self.a)
        out.scale(1.0 / (self.gamma * h))

    def one_step_error(self, h):
        self._acceleration(h, self.a1)
        self.e.waxpy(-1.0, self.a, self.a1)
        self.e.scale(self.c_error * h * h)

    def accepted(self, h):
        self.acc.waxpy(-1.0, self.vhat, self.v)     # ε̈_{n+1} = (v − v̂)/σ
        self.acc.scale(1.0 / self.sigma)
        self._acceleration(h, self.a1)
        self.a1.copy(self.a)

    def start(self, x, v):
        """Consistent start unless a checkpoint gave a₀: ε̇₀ ← the M-orthogonal
        projection onto C ε̇ = 0, then a₀ with C a₀ = 0."""
        if self.started:
            return
        s = self.system
        self.MA.copy(self.A, PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        s.constraint_jacobian(x)
        self.saddle.update(constraints=True)
        rhs, sol = self.saddle.createVec(), self.saddle.createVec()
        s.M.mult(v, self.Mv)
        self.mu.set(0.0)
        self._start_solve(rhs, sol, self.Mv, v)
        # g quadratic and C ε̇₀ = 0: ε̇₀ᵀ∇²g ε̇₀ = 2 (g(ε₀ + ε̇₀) − g(ε₀))
        self.xe.waxpy(1.0, v, x)
        s.constraint_residual(self.xe, self.mu)
        s.constraint_residual(x, self.Cx)
        self.mu.axpy(-1.0, self.Cx)
        self.mu.scale(-2.0)
        s.forces(x, v, self.Q)
        self._start_solve(rhs, sol, self.Q, self.a)
        self.a.copy(self.acc)
        self.lam.getArray()[:] = self.saddle.split(sol)[1]
        v.copy(self.vn)
        rhs.destroy()
        sol.destroy()
        self.started = True

    def _start_solve(self, rhs, sol, b, out):
        """[M Cᵀ; C 0] [out; ·] = [b; self.mu]."""
        ru, rl = self.saddle.split(rhs)
        ru[:] = b.getArray(readonly=True)
        rl[:] = self.mu.getArray(readonly=True)
        try:
            solve_saddle(lambda: self.ksp.solve(rhs, sol), self.ksp)
        except SolverFailure as err:
            raise SimulationError(f"the start solve failed: {err}") from None
        out.getArray()[:] = self.saddle.split(sol)[0]

    def state(self):
        return dict(super().state(), a=self.a.getArray(readonly=True).copy(),
                    acc=self.acc.getArray(readonly=True).copy())

    def set_state(self, st):
        super().set_state(st)
        self.a.getArray()[:] = st["a"]
        self.acc.getArray()[:] = st["acc"]
        self.started = True


class BDF2(NewtonStepper):
    """Variable-step BDF2 on (ε, ε̇), order 2, L-stable: with ω = h/h_{n−1},

        y_{n+1} − (1 + ω)²/(1 + 2ω) y_n + ω²/(1 + 2ω) y_{n−1} = h (1 + ω)/(1 + 2ω) ẏ_{n+1}

    for y = ε and, times M, for y = ε̇ (ẏ = ε̈, M ε̈ = Q + Cᵀλ): σ = κ =
    h(1 + ω)/(1 + 2ω), w = 1, ε̂ and v̂ the history terms. Unresolved stiff
    modes (the yarns' axial vibration) are damped out in a step, where the
    generalized-α method keeps ρ∞ of them and its nonlinear energy balance
    can feed them. The first step is backward Euler. Local error
    −(2/9) h³ ε⃛ (``PositionHistory``); predictor
    ε̇_n + h (ε̇_n − ε̇_{n−1})/h_{n−1}.
    """

    name = "bdf2"
    order = 2
    minimises = True

    def __init__(self, system, dt, control=None, **kw):
        super().__init__(system, dt, control, **kw)
        self.x1, self.v1 = system.M.createVecLeft(), system.M.createVecLeft()
        self.h1 = 0.0                       # 0: no previous step yet
        self.history = PositionHistory(2, -2.0 / 9.0)

    def coefficients(self, h):
        if self.h1 == 0.0:                  # backward Euler
            self.sigma = self.kappa = h
            self.vn.copy(self.vhat)
            self.xn.copy(self.xhat)
            return
        om = h / self.h1
        c0, c1 = (1 + om) ** 2 / (1 + 2 * om), om ** 2 / (1 + 2 * om)
        self.sigma = self.kappa = h * (1 + om) / (1 + 2 * om)
        for hat, y, y1 in ((self.vhat, self.vn, self.v1),
                           (self.xhat, self.xn, self.x1)):
            y.copy(hat)
            hat.scale(c0)
            hat.axpy(-c1, y1)

    def predict(self, h, v):
        self.vn.copy(v)
        if self.h1:
            v.scale(1 + h / self.h1)
            v.axpy(-h / self.h1, self.v1)

    def one_step_error(self, h):
        self.e.waxpy(-1.0, self.vn, self.v)
        self.e.scale(0.5 * h)

    def accepted(self, h):
        self.xn.copy(self.x1)
        self.vn.copy(self.v1)
        self.h1 = h

    def state(self):
        return dict(super().state(), x1=self.x1.getArray(readonly=True).copy(),
                    v1=self.v1.getArray(readonly=True).copy(), h1=self.h1)

    def set_state(self, st):
        super().set_state(st)
        self.x1.getArray()[:] = st["x1"]
        self.v1.getArray()[:] = st["v1"]
        self.h1 = float(st["h1"])


INTEGRATORS = {"alpha": GeneralizedAlpha, "bdf2": BDF2, "implicit": BackwardEuler,
               "symplectic": SymplecticEuler}
