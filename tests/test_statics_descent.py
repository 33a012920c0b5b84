"""The constrained descent of ``knitfem relax`` (solvers.statics_descent)."""

from petsc4py import PETSc

from knitfem.knit.pattern import Jersey, jersey_fabric
from knitfem.model.full import FullModel, Material
from solvers.statics_descent import ConstrainedDescent

COMM = PETSc.COMM_WORLD


def test_the_shift_is_raised_until_the_step_matrix_is_convex():
    """With K = −M (concave everywhere) K + σM is positive definite on C's
    null space exactly when σ > 1: from σ = 0.1 the inertia of the LDLᵀ
    raises σ twice by 8, to 6.4 (0.8 is still concave), and the step is
    then a descent direction of the quadratic model, dᵀ(K + σM)d > 0."""
    system = FullModel(COMM, jersey_fabric(Jersey(3, 3), hold="top"), Material())
    descent = ConstrainedDescent(system)
    K = descent.A.duplicate(copy=True)
    K.zeroEntries()
    K.axpy(-1.0, system.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
    descent.rhs.setRandom(PETSc.Random().create(comm=COMM).setSeed(3) or None)
    descent.sigma = 0.1
    descent._solve(K)
    assert descent.sigma == 0.1 * 8 * 8
    assert descent.stats["inertia"] == 2 and descent.stats["newton"] == 3
    d = descent.saddle.split(descent.z)[0]
    step = system.M.createVecLeft()
    step.getArray()[:] = d
    Md = step.duplicate()
    system.M.mult(step, Md)
    assert (descent.sigma - 1.0) * step.dot(Md) > 0.0
    for obj in (step, Md, K):
        obj.destroy()
    descent.destroy()
    system.destroy()
