"""The stable step of the explicit (symplectic Euler) integrator.

Symplectic Euler on M ε̈ = −K ε is stable for h ω_max ≤ 2, ω_max² the
largest eigenvalue of K v = ω² M v. Constraints only lower the frequencies
(Cauchy interlacing on null(C)), so h ≤ 2 / ω_max of the unconstrained
pencil is safe. ω_max² comes from power iteration on M⁻¹K with Rayleigh
quotients (M solved by CG, ``-stable_`` KSP).
"""

import numpy as np
from petsc4py import PETSc

__all__ = ["largest_eigenvalue", "stable_step"]


def largest_eigenvalue(K, M, rtol=1e-3, max_it=200):
    """ω_max² = max v·Kv / v·Mv by power iteration v ← M⁻¹K v. Collective.

    Stops when the Rayleigh quotient changes by less than ``rtol``; the
    quotient approaches ω_max² from below.
    """
    ksp = PETSc.KSP().create(comm=M.getComm())
    ksp.setOptionsPrefix("stable_")
    ksp.setOperators(M)
    ksp.setType("cg")
    ksp.getPC().setType("jacobi")
    ksp.setTolerances(rtol=1e-10)
    ksp.setFromOptions()
    v, Kv, Mv = M.createVecRight(), M.createVecLeft(), M.createVecLeft()
    rng = np.random.default_rng(7)
    lo, hi = v.getOwnershipRange()
    v.getArray()[:] = rng.standard_normal(v.getSize())[lo:hi]
    lam = 0.0
    for _ in range(max_it):
        K.mult(v, Kv)
        M.mult(v, Mv)
        new = Kv.dot(v) / Mv.dot(v)
        ksp.solve(Kv, v)
        v.scale(1.0 / v.norm())
        if abs(new - lam) <= rtol * new:
            lam = new
            break
        lam = new
    for obj in (ksp, v, Kv, Mv):
        obj.destroy()
    return lam


def stable_step(system, x=None):
    """h_max = 2 / ω_max of the system's pencil (K at x, default the rest
    state; M). Collective."""
    x = system.rest_state() if x is None else x
    lam = largest_eigenvalue(system.stiffness(x), system.M)
    return 2.0 / np.sqrt(lam) if lam > 0 else np.inf
