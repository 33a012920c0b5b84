"""Static equilibrium of a constrained mechanical system.

    F_u = −Q(ε, 0) + C(ε)ᵀμ = 0,   F_λ = g(ε) = 0,

by Newton (PETSc SNES, prefix ``-static_``) with pseudo-transient
continuation (Kelley & Keyes, SIAM J. Numer. Anal. 35, 1998): iteration k
solves, with K = ∂²E/∂ε² + Σ_i μ_i ∇²g_i and C at ε,

    [K + σ_k M  Cᵀ] [δε]     [F_u]
    [C          0 ] [δμ] = − [F_λ],     (ε, μ) ← (ε, μ) + (δε, δμ),

a backward Euler step of the gradient flow M ε̇ = Q − Cᵀμ of pseudo-time
step 1/σ_k. The shift σ_k M makes the matrix regular where K alone is
singular (a knit at its stress-free rest state is a mechanism: the courses
hinge about their contacts) and keeps every step on the flow towards a
stable equilibrium. σ_k follows the residual (switched evolution
relaxation on the best residual so far),

    σ_k = σ_0 γ^(−k) min_(j≤k) |F_j| / |F_0|,   σ_0 = max_i |F_i / m_i| / length,

m_i the lumped mass of coordinate i, so the first step moves a free
coordinate by ``length`` (the yarn radius) and σ goes to zero as the
residual falls: the last iterations are Newton's, quadratic. A membrane
residual EA·½|w'|² that jumps after a bending step does not raise σ (plain
SER, σ_k ∝ |F_k|, does, and takes 30, 22, 60 iterations instead of 25, 19,
57 on the hanging 7×7, the catenary and the hanging 15×30).

Steps are taken in full (``-static_snes_linesearch_type basic``): the
shift, not a line search on |F|, controls them. A backtracking line search
on |F| stalls here: after a bending step the membrane residual of a stiff
yarn is far above the gravity load, so it takes λ ~ 1e-2 at every iteration
and |F| falls linearly (the cantilever of q L³/EI = 0.05 did not converge
in 50 iterations at a fifth of its load).

Where there is no equilibrium near the start (a free knit, or one that slides
off a body), the flow runs away and, once σ is small, Newton's steps on a
mechanism grow without bound (|F| reaches 1e38). The solve stops as soon as a
yarn control point has moved farther than twice the knit's size from where
the load step started (``reach``), and says there is no equilibrium.

Why a shifted SNES and not TSPSEUDO: the same schedule through PETSc's
TSPSEUDO (IFunction M ε̇ + F, SNES ksponly, ``-ts_pseudo_increment 1.5``)
takes as many Jacobians (7, 22, 34 on the cantilever, the catenary, the
hanging 7×7) but three residual evaluations a step instead of one (its
time-step rule and its convergence test evaluate F at ε̇ = 0 again), 2 to 3
times the wall time, and stops on |F| / |F_0| (``-ts_pseudo_frtol``), which
the round-off floor of |F| (EA × machine epsilon) makes either loose or
unreachable; the SNES keeps the Newton-update test below.
"""

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .integrators import SimulationError, _default, step_convergence
from .reasons import reason_name
from .saddle import (SaddlePoint, SolverFailure, saddle_ksp,
                     solve_saddle)

__all__ = ["StaticSolver"]


class StaticSolver:
    """Static equilibrium by Newton with pseudo-transient continuation.

    Collective. ``steps`` equal load increments of gravity (1 is enough for
    the continuation; more follow the loading path); ``length`` the largest
    move of the first iteration (default: the yarn radius); ``growth`` γ,
    the factor by which the pseudo-time step 1/σ grows each iteration
    beyond what the residual gives.
    """

    name, dt = "static", 0.0

    def __init__(self, system, steps=1, length=None, growth=1.5):
        self.system, self.steps, self.growth = system, steps, growth
        self.length = length or system.fabric.radius
        x0 = system.start_state()
        self.reach = 2.0 * _size(system, x0)
        K = system.stiffness(x0)
        self.A = K.duplicate(copy=True)
        self.A.axpy(1.0, system.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        self.saddle = SaddlePoint(self.A, system.constraint_jacobian(x0),
                                  dense=getattr(system, "dense_saddle", False),
                                  blocks=getattr(system, "yarn_blocks", None))
        x0.destroy()
        self.snes = PETSc.SNES().create(comm=system.comm)
        self.snes.setOptionsPrefix("static_")
        self.F, self.z = self.saddle.createVec(), self.saddle.createVec()
        self.snes.setFunction(self._residual, self.F)
        self.snes.setJacobian(self._jacobian, self.saddle.K, self.saddle.K)
        self.snes.setType("newtonls")
        self.snes.setConvergenceTest(self._converged(system))
        _default("static_", "snes_linesearch_type", "basic")
        self.snes.setTolerances(rtol=1e-12, atol=1e-50, max_it=500)
        self.snes.setKSP(saddle_ksp(self.saddle, "static_",
                                    getattr(system, "null_space", False)))
        self.snes.setFromOptions()
        if getattr(system, "yarn_contact", None) is not None:
            self.snes.setLineSearchPreCheck(self._filter)
        self.x, self.zero = system.M.createVecLeft(), system.M.createVecLeft()
        self.Q, self.mu = system.M.createVecLeft(), system.C.createVecLeft()
        self.Cx, self.tmp = system.C.createVecLeft(), system.M.createVecLeft()
        self.lumped = system.M.getRowSum()
        self.start, self.moved = system.M.createVecLeft(), 0.0
        self.load, self.sigma, self.sigma0 = 1.0, 0.0, 0.0
        self.f0 = self.fmin = 0.0
        self.ksp_iterations = 0

    def _converged(self, system):
        """PETSc's |F| tests, or a Newton update below 1e-9 yarn radii once the
        shift is negligible (σ ≤ 1e-6 σ_0): a shifted step is small because
        σM is large, not because F is; DIVERGED_DTOL when a yarn control point
        has moved beyond ``reach`` (collective)."""
        base = step_convergence(self.saddle, lambda: 1e-9 * system.fabric.radius,
                                system)
        R = PETSc.SNES.ConvergedReason

        def test(snes, it, norms):
            if it > 0:
                self.tmp.getArray()[:] = self.saddle.split(snes.getSolution())[0]
                self.tmp.axpy(-1.0, self.start)
                self.moved = system.yarn_move(self.tmp.getArray(readonly=True))
                if self.moved > self.reach:
                    return R.DIVERGED_DTOL
            reason = base(snes, it, norms)
            if reason == R.CONVERGED_SNORM_RELATIVE and \
                    self.sigma > 1e-6 * self.sigma0:
                return R.DIVERGED_MAX_IT if it >= snes.getTolerances()[3] \
                    else R.ITERATING
            return reason

        return test

    def _unpack(self, z):
        u, lam = self.saddle.split(z)
        self.x.getArray()[:] = u
        self.mu.getArray()[:] = lam

    def _filter(self, z, y):
        """Newton's update z ← z − y shortened to the fraction of its move of
        ε the yarn contact allows (``step_fraction``: no two yarn surfaces
        touch on the way)."""
        nu = self.saddle.nu
        x0 = z.getArray(readonly=True)[:nu]
        t = self.system.step_fraction(x0, x0 - y.getArray(readonly=True)[:nu])
        if t < 1.0:
            y.scale(t)

    def _residual(self, snes, z, F):
        s = self.system
        self._unpack(z)
        s.forces(self.x, self.zero, self.Q)
        self.Q.axpy(self.load - 1.0, s.Qg)
        fu, fl = self.saddle.split(F)
        fu[:] = -self.Q.getArray(readonly=True)
        if self.saddle.constrained:
            s.constraint_jacobian(self.x).multTranspose(self.mu, self.tmp)
            fu += self.tmp.getArray(readonly=True)
            s.constraint_residual(self.x, self.Cx)
            fl[:] = self.Cx.getArray(readonly=True)

    def _shift(self, snes):
        """σ_k = σ_0 γ^(−k) min_(j≤k) |F_j| / |F_0|; σ_0 = max_i |F_i/m_i| / length."""
        fnorm, k = snes.getFunctionNorm(), snes.getIterationNumber()
        if k == 0:
            self.tmp.getArray()[:] = self.saddle.split(self.F)[0]
            self.tmp.pointwiseDivide(self.tmp, self.lumped)
            self.sigma0 = self.tmp.norm(PETSc.NormType.INFINITY) / self.length
            self.f0 = self.fmin = fnorm
        self.fmin = min(self.fmin, fnorm)
        self.sigma = self.sigma0 * self.fmin / self.f0 / self.growth**k \
            if self.f0 > 0 else 0.0
        return self.sigma

    def _jacobian(self, snes, z, J, P):
        s = self.system
        self._unpack(z)
        sigma = self._shift(snes)
        mu = self.mu if self.saddle.constrained else None
        s.stiffness(self.x, mu).copy(self.A, PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        if sigma:
            self.A.axpy(sigma, s.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        s.constraint_jacobian(self.x)
        self.saddle.update(constraints=s.nonlinear_constraints)

    def solve(self, x, monitor=None):
        """Equilibrium from the initial guess x (overwritten). Returns Newton its."""
        self.saddle.split(self.z)[0][:] = x.getArray(readonly=True)
        its = 0
        for i in range(1, self.steps + 1):
            self.load = i / self.steps
            self.start.getArray()[:] = self.saddle.split(self.z)[0]
            try:
                solve_saddle(lambda: self.snes.solve(None, self.z), self.snes.getKSP())
            except SolverFailure as err:
                raise SimulationError(f"static Newton failed at load {self.load:.3g}: "
                                      f"{err}", curable=False) from None
            finally:
                its += self.snes.getIterationNumber()
                self.ksp_iterations += self.snes.getLinearSolveIterations()
            reason = self.snes.getConvergedReason()
            if monitor:
                monitor(i, self.load, self.snes)
            if reason == PETSc.SNES.ConvergedReason.DIVERGED_DTOL:
                raise SimulationError(
                    f"static Newton left the start at load {self.load:.3g}: a yarn "
                    f"control point moved {self.moved:.3g} m, more than twice the "
                    f"knit's size: there is no equilibrium near this state (a free "
                    "knit, or one that can slide off a body, has none; hold it, or "
                    "run the dynamics)")
            if reason < 0:
                raise SimulationError(
                    f"static Newton did not converge at load {self.load:.3g} "
                    f"({reason_name(self.snes)} after "
                    f"{self.snes.getIterationNumber()} iterations, |F| = "
                    f"{self.snes.getFunctionNorm():.3e}, shift σ = {self.sigma:.3g})")
            fnorm, load = self.snes.getFunctionNorm(), self.load * self.system.Qg.norm()
            floor = _round_off_floor(self.system, self.x)
            if fnorm > max(1e-6 * load, floor):   # small updates far from equilibrium
                raise SimulationError(
                    f"static Newton stopped at load {self.load:.3g} with |F| = "
                    f"{fnorm:.3e} N, above 1e-6 of the load's {load:.3e} N and "
                    f"round-off's {floor:.1e} N: there is no equilibrium near this "
                    "state (a free knit, or one that can slide off a body, has none; "
                    "hold it, or run the dynamics)")
        self._unpack(self.z)
        self.x.copy(x)
        return its


def _round_off_floor(system, x):
    """The round-off floor of |F| at the yarn coordinates of x (collective):

        ε EA (max |ε_i| / h) √n,

    h the mean control point spacing and n the yarn coordinates: the axial
    strain ½(|ε'|² − 1) of a segment carries ε max|ε_i| / h of round-off
    (positions of size max|ε_i| differenced over h), the axial force EA
    times that on each coordinate, and the n of them add as noise. The
    converged cantilever of 80 segments (EA 1e4) has |F| 1.9e-10 N against
    this 2.8e-9 N, 1e-6 of its load 1.1e-10 N; 160 segments 4.8e-10 N."""
    fab = system.fabric
    X, first = fab.X, fab.yarn_start
    legs = np.linalg.norm(np.diff(X, axis=0), axis=1)
    legs[first[1:-1] - 1] = np.nan              # no leg from one yarn to the next
    h = np.nanmean(legs) if np.isfinite(legs).any() else 1.0
    p = x.getArray(readonly=True)
    reach = system.comm.tompi4py().allreduce(float(np.abs(p).max()) if p.size else 0.0,
                                             op=MPI.MAX)
    return (np.finfo(float).eps * system.material.EA * reach / h
            * np.sqrt(X.size))


def _size(system, x):
    """The diagonal of the bounding box of the coordinates x (collective):
    the knit's size, or its volume's for a reduced model."""
    p = x.getArray(readonly=True).reshape(-1, 3)
    lo = p.min(axis=0) if len(p) else np.full(3, np.inf)
    hi = p.max(axis=0) if len(p) else np.full(3, -np.inf)
    span = np.concatenate([-lo, hi])
    system.comm.tompi4py().Allreduce(MPI.IN_PLACE, span, op=MPI.MAX)
    return float(np.linalg.norm(span[3:] + span[:3]))
