"""Time integrators for a constrained mechanical system.

    M ε̈ = Q(ε, ε̇) + Cᵀλ,   C ε = d.

A *system* (``knitfem.model.FullModel`` or ``knitfem.reduced.ReducedModel``)
supplies M, its scalar factor m (M = m ⊗ I₃), C, c, d, ``forces(x, v, Q)``,
``stiffness(x)`` (K = ∂²E/∂ε²) and ``material.damping`` c_d (Q_d = −c_d M ε̇).
The integrators never see a yarn.

Drift control is by projection at the velocity level: every step asks
C ε_{n+1} = d exactly (C v_{n+1} = (d − C ε_n)/h), so constraint drift stays
at the round-off of the linear solves.
"""

import numpy as np
from petsc4py import PETSc

from .reasons import reason_name
from .saddle import (SaddlePoint, SolverFailure, ksp_failure, saddle_ksp,
                     solve_saddle)

__all__ = ["SimulationError", "SymplecticEuler", "BackwardEuler", "INTEGRATORS"]

EV_SOLVE = PETSc.Log.Event("knitSaddleSolve")
EV_FACTOR = PETSc.Log.Event("knitFactor")


class SimulationError(RuntimeError):
    """A step failed; the message names the step, the time and the quantity."""


def _default(prefix, name, value):
    """Set an option default unless the user gave it."""
    opts = PETSc.Options()
    if not opts.hasName(prefix + name):
        opts.setValue(prefix + name, value)


def step_convergence(saddle, step_tol):
    """SNES convergence test: PETSc's atol/rtol on |F|, or a Newton update of
    the coordinates (not the multipliers) below ``step_tol()`` in max norm
    (the residual of stiff yarns carries round-off far above any absolute
    tolerance on |F|)."""
    R = PETSc.SNES.ConvergedReason

    def test(snes, it, norms):
        fnorm = norms[2]
        if it > 0:
            du = saddle.split(snes.getSolutionUpdate())[0]
            local = np.abs(du).max() if du.size else 0.0
            ynorm = saddle.K.getComm().tompi4py().allreduce(local, op=_MPI_MAX())
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
        if ynorm <= step_tol():
            return R.CONVERGED_SNORM_RELATIVE
        if it >= max_it:
            return R.DIVERGED_MAX_IT
        return R.ITERATING

    return test


def _MPI_MAX():
    from mpi4py import MPI

    return MPI.MAX


class SymplecticEuler:
    """Explicit symplectic Euler on the constant saddle point.

        [m cᵀ] [v_{n+1}^k]   [(M v_n + h Q(ε_n, v_n))^k]
        [c 0 ] [  μ^k    ] = [ (d^k − (c ε_n)^k) / h    ],   ε_{n+1} = ε_n + h v_{n+1},

    for each component k = x, y, z: the scalar saddle point [m cᵀ; c 0] is a
    third of the 3-D size, factorised once (``-<kind>_explicit_`` KSP) and
    solved for three right-hand sides a step.
    """

    name = "symplectic"

    def __init__(self, system, dt):
        self.system, self.dt = system, dt
        self.saddle = SaddlePoint(system.m, system.c)
        self.ksp = saddle_ksp(self.saddle, f"{system.kind}_explicit_")
        with EV_FACTOR:
            self.ksp.setUp()
        self.rhs, self.sol = self.saddle.createVec(), self.saddle.createVec()
        self.Q, self.Mv = system.M.createVecLeft(), system.M.createVecLeft()
        self.Cx = system.C.createVecLeft()

    def step(self, t, x, v):
        s, h = self.system, self.dt
        s.forces(x, v, self.Q)
        s.M.mult(v, self.Mv)
        self.Mv.axpy(h, self.Q)
        s.C.mult(x, self.Cx)
        g = (s.d.getArray(readonly=True) - self.Cx.getArray(readonly=True)) / h
        rhs_u, rhs_l = self.saddle.split(self.rhs)
        mv = self.Mv.getArray(readonly=True)
        vv = v.getArray()
        its = 0
        for k in range(3):
            rhs_u[:] = mv[k::3]
            rhs_l[:] = g[k::3]
            with EV_SOLVE:
                self.ksp.solve(self.rhs, self.sol)
            its += self.ksp.getIterationNumber()
            vv[k::3] = self.saddle.split(self.sol)[0]
        x.axpy(h, v)
        return {"newton": 0, "ksp": its}


class BackwardEuler:
    """Implicit (backward) Euler with Newton (PETSc SNES, prefix ``-<kind>_``).

    Unknowns z = (v_{n+1}, μ) with μ = −hλ; residual

        F_u = M (v − v_n) − h Q(ε_n + h v, v) + Cᵀ μ,
        F_λ = C v − (d − C ε_n) / h,

    and Jacobian [A Cᵀ; C 0] with A = h² K + (1 + h c_d) M, assembled as one
    AIJ matrix; its KSP/PC is chosen by ``-<kind>_ksp_type``,
    ``-<kind>_pc_type`` … (MUMPS LU by default).
    """

    name = "implicit"

    def __init__(self, system, dt):
        self.system, self.dt = system, dt
        prefix = f"{system.kind}_"
        K = system.stiffness(system.rest_state())
        self.A = K.duplicate(copy=True)
        self.A.axpy(1.0, system.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        self.saddle = SaddlePoint(self.A, system.C,
                                  dense=getattr(system, "dense_saddle", False),
                                  prefix=prefix)
        self.snes = PETSc.SNES().create(comm=system.comm)
        self.snes.setOptionsPrefix(prefix)
        self.F, self.z = self.saddle.createVec(), self.saddle.createVec()
        self.snes.setFunction(self._residual, self.F)
        self.snes.setJacobian(self._jacobian, self.saddle.K, self.saddle.P)
        self.snes.setType("newtonls")
        # converged when the update moves ε by < 1e-9 yarn radii
        self.snes.setConvergenceTest(step_convergence(
            self.saddle, lambda: 1e-9 * system.fabric.radius / self.h))
        _default(prefix, "snes_linesearch_type", "basic")
        self.snes.setTolerances(rtol=1e-7, atol=1e-50, max_it=25)
        ksp = saddle_ksp(self.saddle, prefix)
        self.snes.setKSP(ksp)
        self.snes.setFromOptions()
        self.user_atol = PETSc.Options().hasName(prefix + "snes_atol")
        self.v, self.xt = system.M.createVecLeft(), system.M.createVecLeft()
        self.Q, self.Mv = system.M.createVecLeft(), system.M.createVecLeft()
        self.mu, self.Cx = system.C.createVecLeft(), system.C.createVecLeft()
        self.tmp = system.M.createVecLeft()
        self.xn = self.vn = None
        self.h = dt
        self.max_halvings = 6

    def _unpack(self, z):
        u, lam = self.saddle.split(z)
        self.v.getArray()[:] = u
        self.mu.getArray()[:] = lam
        self.xn.copy(self.xt)
        self.xt.axpy(self.h, self.v)

    def _residual(self, snes, z, F):
        s, h = self.system, self.h
        self._unpack(z)
        s.forces(self.xt, self.v, self.Q)
        self.v.copy(self.tmp)
        self.tmp.axpy(-1.0, self.vn)
        s.M.mult(self.tmp, self.Mv)
        self.Mv.axpy(-h, self.Q)
        fu, fl = self.saddle.split(F)
        fu[:] = self.Mv.getArray(readonly=True)
        if self.saddle.constrained:
            s.C.multTranspose(self.mu, self.tmp)
            fu += self.tmp.getArray(readonly=True)
            s.C.mult(self.v, self.Cx)
            fl[:] = self.Cx.getArray(readonly=True) - self.g

    def _jacobian(self, snes, z, J, P):
        s, h = self.system, self.h
        self._unpack(z)
        K = s.stiffness(self.xt)
        K.copy(self.A, PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        self.A.scale(h * h)
        self.A.axpy(1.0 + h * s.material.damping, s.M,
                    PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        self.saddle.update()

    def step(self, t, x, v):
        """Advance (ε, ε̇) by dt; a failed Newton solve is retried as two half
        steps, down to dt / 2^max_halvings, before the step fails."""
        stats = {"newton": 0, "ksp": 0}
        try:
            self._advance(x, v, self.dt, 0, stats)
        except SolverFailure as err:          # a smaller step would not help
            raise SimulationError(str(err)) from None
        return stats

    def _advance(self, x, v, h, depth, stats):
        try:
            self._solve(x, v, h, stats)
        except SimulationError:
            if depth >= self.max_halvings:
                raise
            for _ in range(2):
                self._advance(x, v, h / 2, depth + 1, stats)

    def _solve(self, x, v, h, stats):
        s = self.system
        self.h, self.xn, self.vn = h, x, v
        s.C.mult(x, self.Cx)
        self.g = (s.d.getArray(readonly=True) - self.Cx.getArray(readonly=True)) / h
        zu, zl = self.saddle.split(self.z)
        zu[:] = v.getArray(readonly=True)
        zl[:] = 0.0
        if not self.user_atol:
            s.M.mult(v, self.Mv)
            scale = self.Mv.norm() + h * s.Qg.norm()
            floor = 1e-14 * s.total_mass * s.fabric.radius / h
            self.snes.setTolerances(atol=max(1e-12 * scale, floor))
        try:
            solve_saddle(lambda: self.snes.solve(None, self.z), self.snes.getKSP())
        except SolverFailure as err:
            raise SimulationError(f"{err}, h = {h:.3g} s") from None
        reason = self.snes.getConvergedReason()
        stats["newton"] += self.snes.getIterationNumber()
        stats["ksp"] += self.snes.getLinearSolveIterations()
        if reason == PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE:
            raise SimulationError(f"{ksp_failure(self.snes.getKSP())}, h = {h:.3g} s")
        if reason < 0:
            raise SimulationError(f"Newton did not converge ({reason_name(self.snes)}, "
                                  f"|F| = {self.snes.getFunctionNorm():.3e}, "
                                  f"h = {h:.3g} s)")
        self._unpack(self.z)
        self.v.copy(v)
        x.axpy(h, v)


INTEGRATORS = {"symplectic": SymplecticEuler, "implicit": BackwardEuler}
