"""Saddle-point systems [A Cᵀ; C 0] as one AIJ matrix, and their KSP.

The blocks are wrapped in a MATNEST and converted to AIJ once (MUMPS cannot
factor a nest); the constraint block carries an explicit zero diagonal so
that factorisations and fieldsplit find its entries. When A's values change
(same pattern) ``update`` writes them into their places in K, so K keeps
its nonzero state and factorisations keep their symbolic phase. Small serial
systems (the reduced model's) can be held dense instead and factorised by
LAPACK's pivoting LU. Each rank's
rows are [its A rows, its C rows], so a saddle vector's local array is the
concatenation of the two local parts.
"""

import numpy as np
from petsc4py import PETSc

__all__ = ["SaddlePoint", "saddle_ksp"]


def zero_diagonal(comm, n_local, n_global):
    """An AIJ matrix holding explicit zeros on its diagonal."""
    start = comm.tompi4py().exscan(n_local) or 0
    ptr = np.arange(n_local + 1, dtype=PETSc.IntType)
    idx = np.arange(start, start + n_local, dtype=PETSc.IntType)
    Z = PETSc.Mat().createAIJ(((n_local, n_global), (n_local, n_global)),
                              csr=(ptr, idx, np.zeros(n_local)), comm=comm)
    Z.assemble()
    return Z


class SaddlePoint:
    """K = [A Cᵀ; C 0] for A (n×n) and C (k×n); K = A when C has no rows.

    Collective. ``nu`` and ``nl`` are the local sizes of the two parts;
    ``dense`` holds K as a dense matrix (one rank only).
    """

    def __init__(self, A, C, dense=False):
        self.A, self.C, self.aij = A, C, None
        self.nu = A.getLocalSize()[0]
        self.nl = C.getLocalSize()[0] if C is not None else 0
        self.constrained = C is not None and C.getSize()[0] > 0
        if not self.constrained:
            self.nl, self.nest, self.K = 0, None, A
            return
        comm = A.getComm()
        self.Ct = C.transpose(PETSc.Mat())
        self.Z = zero_diagonal(comm, *C.getSizes()[0])
        self.nest = PETSc.Mat().createNest([[A, self.Ct], [C, self.Z]], comm=comm)
        self.K = self.nest.convert("aij", PETSc.Mat())
        self.K.setBlockSize(1)
        if dense:
            self.aij, self.K = self.K, self.K.convert("dense", PETSc.Mat())
        self.fields = self.nest.getNestISs()[0]
        # A's global column j, owned by rank r, is column j − a_r + k_r of K
        a = np.asarray(A.getOwnershipRanges())
        k = np.asarray(self.K.getOwnershipRanges()) if not dense else a * 0
        indptr, cols, _ = A.getValuesCSR()
        owner = np.searchsorted(a, cols, side="right") - 1
        indptr = np.append(indptr, np.full(self.nl, indptr[-1]))   # C rows: none
        self.csr = (indptr.astype(PETSc.IntType),
                    (cols - a[owner] + k[owner]).astype(PETSc.IntType))

    def update(self):
        """Refresh K after A's values changed (same nonzero pattern)."""
        if self.aij is not None:
            self.nest.convert("aij", self.aij)
            self.aij.convert("dense", self.K)
        elif self.constrained:
            self.K.setValuesCSR(*self.csr, self.A.getValuesCSR()[2])
            self.K.assemble()

    def createVec(self):
        return self.K.createVecRight()

    def split(self, z):
        """Local arrays (u part, λ part) of a saddle vector, as views."""
        a = z.getArray()
        return a[: self.nu], a[self.nu:]

    def destroy(self):
        if self.constrained:
            for obj in (self.Ct, self.Z, self.nest, self.K, self.aij):
                if obj is not None:
                    obj.destroy()


def saddle_ksp(saddle, prefix):
    """A KSP on the saddle point, then the command line. By default a direct
    solve: MUMPS LDLᵀ of the symmetric indefinite K (2×2 pivots; 2.2× faster
    than its LU on the 15×30 jersey, ``benchmarks/results/solver_sweep.json``)
    with 100 % extra workspace for delayed pivots (ICNTL(14)); LAPACK LU for
    a dense K.

    Fieldsplit preconditioners get the fields "u" (coordinates) and "l"
    (multipliers), e.g. ``-<prefix>pc_type fieldsplit
    -<prefix>pc_fieldsplit_type schur``.
    """
    ksp = PETSc.KSP().create(comm=saddle.K.getComm())
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(saddle.K)
    ksp.setType("preonly")
    pc = ksp.getPC()
    solver = "petsc" if saddle.K.getType() == "seqdense" else "mumps"
    pc.setType("lu" if solver == "petsc" else "cholesky")
    pc.setFactorSolverType(solver)
    options = PETSc.Options(prefix)
    if solver == "mumps" and not options.hasName("mat_mumps_icntl_14"):
        options.setValue("mat_mumps_icntl_14", 100)
    ksp.setErrorIfNotConverged(True)
    ksp.setFromOptions()
    if pc.getType() in ("lu", "cholesky") and \
            not options.hasName("pc_factor_mat_solver_type"):
        pc.setFactorSolverType(solver)         # kept under -<prefix>pc_type lu
    if pc.getType() == "fieldsplit" and saddle.constrained:
        pc.setFieldSplitIS(("u", saddle.fields[0]), ("l", saddle.fields[1]))
    return ksp
