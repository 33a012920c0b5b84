"""Saddle-point systems [A Cᵀ; C 0] as one AIJ matrix, their KSP, and what
to do when the solver fails.

The blocks are wrapped in a MATNEST and converted to AIJ once (MUMPS cannot
factor a nest); the constraint block carries an explicit zero diagonal so
that factorisations and fieldsplit find its entries. When A's values change
(same pattern) ``update`` writes them into their places in K, so K keeps
its nonzero state and factorisations keep their symbolic phase (MUMPS's
analysis runs once a run). On one rank K is made on a value array of its
own, which ``update`` fills by one indexed copy, Cᵀ's values being C's
permuted; on several K is a COO matrix (``solvers.coo``) whose Cᵀ entries
are C's sent to the rows they land in (at 40×160 a Newton matrix took 0.32 s
to form through MatTranspose and setValuesCSR, 0.17 s so; the nest's Cᵀ
then only gives the fields). Small serial systems (the reduced model's) can be
held dense instead and factorised by LAPACK's pivoting LU. Each rank's
rows are [its A rows, its C rows], so a saddle vector's local array is the
concatenation of the two local parts.

Regularised Jacobian. Serial MUMPS pairs every zero-diagonal constraint
row with a coordinate before ordering (maximum weighted matching, ICNTL(6);
constrained ordering, ICNTL(12)); with the matrix distributed over ranks it
cannot, and its LDLᵀ delays some 17 000 pivots of the 20×40 jersey (1 200
serially), tripling the flops and overflowing its workspace. With
``-<prefix>saddle_regularization τ`` > 0 (the default on more than one rank)
the linear solves use the LDLᵀ of the quasi-definite

    P = [A Cᵀ; C −δI],   δ = τ / max diag A,

which factorises stably in any order without pivoting (MUMPS CNTL(1) = 0).
Newton keeps K in its residual, so P only makes it an inexact Newton whose
iterations and converged state are those of K (measured: the same Newton
counts and states over three steps of the 10×20 jersey); ``-<prefix>ksp_type gmres``
solves K itself, in one or two iterations.
"""

from contextlib import nullcontext

import numpy as np
from petsc4py import PETSc

from knitfem.assembly import csr_positions, csr_rows

from .coo import coo_matrix, set_values
from .libpetsc import Int, library, seqaij_values

__all__ = ["SaddlePoint", "saddle_ksp", "SolverFailure", "solve_saddle",
           "ksp_failure", "failure_or_retry", "pc_failure"]


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
    ``dense`` holds K as a dense matrix (one rank only). With a ``prefix``,
    ``-<prefix>saddle_regularization τ`` builds the preconditioning matrix
    P = [A Cᵀ; C −δI] (module docstring); otherwise P is K. ``blocks``
    (size, overlap) → [(coordinates, constraint rows)], global indices of A
    and C, gives the subdomains of an additive Schwarz preconditioner
    (``subdomains``; the full model's ``yarn_blocks``).
    """

    def __init__(self, A, C, dense=False, prefix=None, blocks=None):
        self.A, self.C, self.aij, self.blocks = A, C, None, blocks
        self.P, self.delta, self.arrays = None, 0.0, None
        self.nu = A.getLocalSize()[0]
        self.nl = C.getLocalSize()[0] if C is not None else 0
        self.constrained = C is not None and C.getSize()[0] > 0
        if not self.constrained:
            self.nl, self.nest, self.K = 0, None, A
            self.P = A
            return
        comm = A.getComm()
        self.Ct = C.transpose(PETSc.Mat())
        self.Z = zero_diagonal(comm, *C.getSizes()[0])
        self.nest = PETSc.Mat().createNest([[A, self.Ct], [C, self.Z]], comm=comm)
        self.fields = self.nest.getNestISs()[0]
        # K's rows on rank r: its rows of A, then its rows of C
        self.k_ranges = np.add(A.getOwnershipRanges(), C.getOwnershipRanges())
        if comm.getSize() > 1:
            self._coo_values()
        elif dense:
            self.aij = self.nest.convert("aij", PETSc.Mat())
            self.K = self.aij.convert("dense", PETSc.Mat())
        else:
            self._own_values()
        tau = regularization_option(prefix, comm) if prefix and not dense else 0.0
        self.P = self.K if tau == 0 else self.regularized(tau)
        if comm.getSize() > 1:
            self.update()                         # the COO matrices' first values

    def _own_values(self):
        """On one rank K is built on a value array of its own (``arrays``),
        its CSR laid out from A's and C's without a sort of its entries: row
        i < nu is A's row i, then Cᵀ's (columns nu + r); row nu + r is C's
        row r, then its zero diagonal. ``slots`` are the places of A's, Cᵀ's
        and C's values in it; Cᵀ's values are C's permuted by ``transpose``
        (C's entries ordered by column, rows ascending)."""
        nu, nl = self.nu, self.nl
        ai, aj, _ = self.A.getValuesCSR()
        ci, cj, _ = self.C.getValuesCSR()
        self.transpose = np.argsort(cj, kind="stable")
        ti = np.searchsorted(cj[self.transpose], np.arange(nu + 1))
        la, lt, lc = np.diff(ai), np.diff(ti), np.diff(ci)
        indptr = np.zeros(nu + nl + 1, dtype=PETSc.IntType)
        np.cumsum(np.concatenate([la + lt, lc + 1]), out=indptr[1:])
        first = indptr.astype(np.int64)
        a_pos = csr_positions(ai, first[:nu])
        t_pos = csr_positions(ti, first[:nu] + la)
        c_pos = csr_positions(ci, first[nu:-1])
        self.slots = a_pos, t_pos, c_pos
        self.diagonal = first[nu + 1:] - 1                       # the −δI block
        indices = np.empty(indptr[-1], dtype=PETSc.IntType)
        indices[a_pos] = aj
        indices[t_pos] = nu + csr_rows(ci)[self.transpose]
        indices[c_pos] = cj
        indices[self.diagonal] = nu + np.arange(nl)
        self.arrays = [np.zeros(indptr[-1], dtype=PETSc.ScalarType)]
        self._write_arrays()
        self.K = self._on_array(nu + nl, indptr, indices, self.arrays[0])

    @staticmethod
    def _on_array(n, indptr, indices, values):
        """An n × n AIJ matrix holding ``values`` itself (one rank)."""
        K = PETSc.Mat().createAIJWithArrays(n, (indptr, indices, values),
                                            comm=PETSc.COMM_SELF)
        K.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        return K

    def regularized(self, tau):
        """P = K − δ [0 0; 0 I] with δ = τ / max diag A (same pattern as K)."""
        self.delta = tau / self.A.getDiagonal().norm(PETSc.NormType.INFINITY)
        if self.arrays is not None:
            indptr, indices, values = self.K.getValuesCSR()
            values[self.diagonal] = -self.delta
            self.arrays.append(values)
            return self._on_array(self.K.getSize()[0], indptr, indices, values)
        P = coo_matrix(self.K.getComm(), self.K.getSizes(), *self.coo)
        self.coo_targets.append((P, np.full(self.nl, -self.delta)))
        return P

    def _coo_values(self):
        """On several ranks K is a COO matrix (``solvers.coo``) of A's
        entries, Cᵀ's (C's sent to the rows they land in), C's and the
        multipliers' diagonal, written from A's and C's values as they are."""
        a, c = (np.asarray(M.getOwnershipRanges()) for M in (self.A, self.C))
        k, rank = self.k_ranges, self.A.getComm().getRank()
        ai, aj, _ = self.A.getValuesCSR()
        ci, cj, _ = self.C.getValuesCSR()
        a_rows = k[rank] + csr_rows(ai)
        c_rows = k[rank] + self.nu + csr_rows(ci)
        a_cols, c_cols = self._to_k(aj, a, 0 * a), self._to_k(cj, a, 0 * a)
        lam = k[rank] + self.nu + np.arange(self.nl)
        self.coo = (np.concatenate([a_rows, c_cols, c_rows, lam]),
                    np.concatenate([a_cols, c_rows, c_cols, lam]))
        self.K = coo_matrix(self.A.getComm(), self.nest.getSizes(), *self.coo)
        self.coo_targets = [(self.K, np.zeros(self.nl))]     # (matrix, its λ diagonal)

    def _to_k(self, cols, ranges, shift):
        """K's global index of global index ``cols`` of a block whose
        ownership is ``ranges``: j − (block's first on its rank r) + (K's
        first on r) + ``shift``[r] (A's rows on r for a multiplier)."""
        owner = np.searchsorted(ranges, cols, side="right") - 1
        return cols - ranges[owner] + self.k_ranges[owner] + shift[owner]

    def update(self, constraints=False):
        """Refresh K after A's values changed, and C's with ``constraints``
        (same nonzero patterns)."""
        if self.arrays is not None:
            self._write_arrays()
            for K in (self.K, self.P) if self.P is not self.K else (self.K,):
                K.assemble()                 # a new state: factorisations redo
            return
        if self.aij is not None:
            if constraints:
                self.C.transpose(self.Ct)
            self._dense_update(constraints)
        elif self.constrained:
            a, c = self.A.getValuesCSR()[2], self.C.getValuesCSR()[2]
            for K, diagonal in self.coo_targets:
                set_values(K, np.concatenate([a, c, c, diagonal]))

    def _write_arrays(self):
        """A's and C's values into their places in K's value arrays (read
        where A and C keep them when they are sequential AIJ)."""
        a, t, c = self.slots
        with aij_values(self.A, len(a)) as va, aij_values(self.C, len(c)) as vc:
            for array in self.arrays:
                array[a] = va
                array[t] = vc[self.transpose]
                array[c] = vc

    def _dense_update(self, constraints):
        """A dense K written in place: A's block from A's values when A's
        pattern is dense (the reduced model's), C and Cᵀ when they changed;
        else through the nest (MatConvert)."""
        nu = self.nu
        indptr, _, values = self.A.getValuesCSR()
        if len(values) != nu * nu:
            self.nest.convert("aij", self.aij)
            self.aij.convert("dense", self.K)
            return
        Kd = self.K.getDenseArray()
        Kd[:nu, :nu] = values.reshape(nu, nu)
        if constraints:
            C = np.zeros((self.nl, nu))
            indptr, indices, values = self.C.getValuesCSR()
            C[np.repeat(np.arange(self.nl), np.diff(indptr)), indices] = values
            Kd[nu:, :nu], Kd[:nu, nu:] = C, C.T
        self.K.assemble()                    # a new state: LU refactorises

    def createVec(self):
        return self.K.createVecRight()

    def subdomains(self, size, overlap):
        """``blocks(size, overlap)`` as index sets of K (``_to_k``)."""
        a, c = (np.asarray(M.getOwnershipRanges()) for M in (self.A, self.C))
        sets = []
        for coords, rows in self.blocks(size, overlap):
            index = np.concatenate([self._to_k(coords, a, 0 * a),
                                    self._to_k(rows, c, np.diff(a))])
            sets.append(PETSc.IS().createGeneral(np.sort(index).astype(PETSc.IntType),
                                                 comm=PETSc.COMM_SELF))
        return sets

    def split(self, z):
        """Local arrays (u part, λ part) of a saddle vector, as views."""
        a = z.getArray()
        return a[: self.nu], a[self.nu:]

    def destroy(self):
        if self.constrained:
            P = self.P if self.P is not self.K else None
            for obj in (self.Ct, self.Z, self.nest, self.K, self.aij, P):
                if obj is not None:
                    obj.destroy()


def aij_values(A, nnz):
    """A context giving the ``nnz`` values of AIJ matrix A in CSR order: a
    view of its own storage when it is sequential, else a copy."""
    if A.getType() == PETSc.Mat.Type.SEQAIJ:
        return seqaij_values(A, nnz)
    return nullcontext(A.getValuesCSR()[2])


def regularization_option(prefix, comm):
    """τ of -<prefix>saddle_regularization: 1 on more than one rank, else 0."""
    from knitfem.options import KnitOptions

    opts = KnitOptions(prefix + "saddle_")
    return opts.getReal("regularization", 1.0 if comm.getSize() > 1 else 0.0,
                        "solve with the LDLt of [A C^T; C -tau/max(diag A) I] "
                        "without pivoting (0: pivoting LDLt of K)",
                        nonnegative=True)


def saddle_ksp(saddle, prefix):
    """A KSP on the saddle point, then the command line. By default a direct
    solve: MUMPS LDLᵀ of the symmetric indefinite K (2×2 pivots; 2.2× faster
    than its LU on the 15×30 jersey, ``benchmarks/results/solver_sweep.json``)
    with 100 % extra workspace for delayed pivots (ICNTL(14)); LAPACK LU for
    a dense K. With a regularised P (``saddle.delta`` > 0): MUMPS LDLᵀ of P
    without pivoting (a Krylov method chosen by options, at most 30
    iterations, solves K with it).

    Additive Schwarz (``-<prefix>pc_type asm``) on a saddle point with
    ``blocks`` gets whole-course subdomains, ``-<prefix>saddle_asm_courses``
    courses each widened by ``-<prefix>saddle_asm_overlap`` courses either
    side, factorised by MUMPS LDLᵀ (``-<prefix>sub_pc_type``), unless
    ``-<prefix>pc_asm_overlap`` asks for PETSc's overlap in the matrix graph
    (which cuts yarns) instead.

    Fieldsplit preconditioners get the fields "u" (coordinates) and "l"
    (multipliers), e.g. ``-<prefix>pc_type fieldsplit
    -<prefix>pc_fieldsplit_type schur``.
    """
    ksp = PETSc.KSP().create(comm=saddle.K.getComm())
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(saddle.K, saddle.P)
    ksp.setType("preonly")
    if saddle.delta:
        ksp.setTolerances(max_it=30)
    pc = ksp.getPC()
    solver = "petsc" if saddle.K.getType() == "seqdense" else "mumps"
    pc.setType("lu" if solver == "petsc" else "cholesky")
    pc.setFactorSolverType(solver)
    options = PETSc.Options(prefix)
    if solver == "mumps" and not options.hasName("mat_mumps_icntl_14"):
        options.setValue("mat_mumps_icntl_14", 100)
    ksp.setFromOptions()
    # a direct solve raises its factorisation's error at once; a Krylov
    # method leaves its reason (DIVERGED_ITS, DIVERGED_PC_FAILED) for Newton
    # and the step control (an error inside KSPSolve would leave PETSc's
    # PCPreSolve nesting raised, and every later solve fails for that)
    ksp.setErrorIfNotConverged(ksp.getType() == "preonly")
    if pc.getType() in ("lu", "cholesky") and \
            not options.hasName("pc_factor_mat_solver_type"):
        pc.setFactorSolverType(solver)         # kept under -<prefix>pc_type lu
    if saddle.delta and pc.getType() in ("lu", "cholesky") and \
            pc.getFactorSolverType() == "mumps" and \
            not options.hasName("mat_mumps_cntl_1"):
        pc.setFactorSetUpSolverType()
        pc.getFactorMatrix().setMumpsCntl(1, 0.0)   # P is quasi-definite
    if pc.getType() == "asm" and saddle.constrained and saddle.blocks and \
            not options.hasName("pc_asm_overlap"):
        pc.setASMLocalSubdomains(*_course_subdomains(saddle, prefix))
        pc.setASMOverlap(0)
    if pc.getType() == "fieldsplit" and saddle.constrained:
        u, lam = ("u", saddle.fields[0]), ("l", saddle.fields[1])
        # with P regularised, −δI comes first: its Schur complement
        # A + CᵀC/δ is SPD and "selfp" assembles it exactly
        pc.setFieldSplitIS(*((lam, u) if saddle.delta else (u, lam)))
    return ksp


def _course_subdomains(saddle, prefix):
    """(count, index sets) of the whole-course subdomains that the options
    ask for; their own saddle points are factorised (MUMPS LDLᵀ: 25 s
    against LU's 31 s and 1.3 against 1.6 GiB for the 40×80 step) unless
    told."""
    from knitfem.options import KnitOptions

    opts = KnitOptions(prefix + "saddle_asm_")
    size = opts.getInt("courses", 4, "courses in a Schwarz subdomain", minimum=1)
    overlap = opts.getInt("overlap", 4, "courses a Schwarz subdomain reaches "
                          "beyond its own either side", minimum=0)
    options = PETSc.Options(prefix)
    for name, value in (("sub_ksp_type", "preonly"), ("sub_pc_type", "cholesky"),
                        ("sub_pc_factor_mat_solver_type", "mumps")):
        if not options.hasName(name):
            options.setValue(name, value)
    sets = saddle.subdomains(size, overlap)
    return len(sets), sets


# -- when the solver fails -------------------------------------------------
class SolverFailure(RuntimeError):
    """A linear solver failed; the message is one line naming the solver,
    its reason and the option to change. ``curable``: a smaller step may
    cure it (a Krylov method out of iterations or diverging on a matrix
    that a smaller step makes closer to the mass matrix), as opposed to a
    zero pivot, a failed factorisation or a PETSc error."""

    def __init__(self, line, curable=False):
        super().__init__(line)
        self.curable = curable


MUMPS_WORKSPACE_MAX = 6400     # ICNTL(14), percent: 64× the analysis estimate

KSPReason = PETSc.KSP.ConvergedReason
CURABLE = (KSPReason.DIVERGED_MAX_IT, KSPReason.DIVERGED_DTOL,
           KSPReason.DIVERGED_BREAKDOWN, KSPReason.DIVERGED_NANORINF)

# PCFailedReason (petscpc.h), which petsc4py 3.18 does not wrap
PC_FAILED = {-1: "set-up error", 1: "structurally zero pivot",
             2: "numerically zero pivot", 3: "out of memory in the factorisation",
             4: "factorisation failed", 5: "a sub-preconditioner failed"}


def pc_failure(pc):
    """Why a preconditioner failed, in words: its PCFailedReason, followed
    into fieldsplit blocks, and a zero pivot's row and value (PETSc's
    PCGetFailedReason and MatFactorGetErrorZeroPivot through ctypes)."""
    import ctypes

    lib, code = library(), ctypes.c_int(0)
    lib.PCGetFailedReason(ctypes.c_void_p(pc.handle), ctypes.byref(code))
    where = f"PC {pc.getType()}"
    if pc.getType() == "fieldsplit":
        # a block whose preconditioner failed first: it makes the others fail
        subs = sorted(((sub.getConvergedReason() != KSPReason.DIVERGED_PCSETUP_FAILED,
                        name, sub) for name, sub in zip("ul", pc.getFieldSplitSubKSP())
                       if sub.getConvergedReason() < 0), key=lambda e: e[:2])
        if subs:
            other, name, sub = subs[0]
            why = _reason(sub) if other else pc_failure(sub.getPC())
            return f"{where}, block {name!r} ({sub.getType()}): {why}"
    if code.value in (1, 2) and pc.getType() in ("lu", "cholesky", "ilu", "icc"):
        pivot, row = ctypes.c_double(0.0), Int(0)
        lib.MatFactorGetErrorZeroPivot(ctypes.c_void_p(pc.getFactorMatrix().handle),
                                       ctypes.byref(pivot), ctypes.byref(row))
        return (f"{where}: {PC_FAILED[code.value]} in row {row.value} "
                f"(value {pivot.value:.3g})")
    return f"{where}: {PC_FAILED.get(code.value, f'PCFailedReason {code.value}')}"


def _reason(ksp):
    """A KSP's converged reason by name."""
    return next((k for k, v in vars(KSPReason).items()
                 if v == ksp.getConvergedReason() and not k.startswith("_")),
                str(ksp.getConvergedReason()))


def _factor(ksp):
    """(PC, MUMPS factor matrix or None) of a KSP with a factorisation PC."""
    pc = ksp.getPC()
    if pc.getType() not in ("lu", "cholesky"):
        return pc, None
    solver = pc.getFactorSolverType()
    return pc, pc.getFactorMatrix() if solver == "mumps" else None


def refactor(ksp, icntl14):
    """Drop the failed MUMPS factor (it would skip its numeric phase after any
    error) for a new one with ICNTL(14) = ``icntl14`` (also in the options
    database, which the new factor reads) and the old CNTL(1)."""
    pc, F = _factor(ksp)
    cntl1 = F.getMumpsCntl(1)
    PETSc.Options(ksp.getOptionsPrefix()).setValue("mat_mumps_icntl_14", icntl14)
    A, P = ksp.getOperators()
    pc.reset()
    ksp.setOperators(A, P)
    pc.setFactorSetUpSolverType()
    F = pc.getFactorMatrix()
    F.setMumpsIcntl(14, icntl14)
    F.setMumpsCntl(1, cntl1)


def ksp_failure(ksp):
    """The SolverFailure of a KSP whose last solve did not converge: the
    solver, its reason by name (with the iterations and the residual, or
    what made the preconditioner fail) and the option to change."""
    prefix = ksp.getOptionsPrefix() or ""
    reason = ksp.getConvergedReason()
    solver = f"KSP {ksp.getType()} with PC {ksp.getPC().getType()}"
    if reason == KSPReason.DIVERGED_PCSETUP_FAILED:
        why = pc_failure(ksp.getPC())
        advice = (f"use -{prefix}pc_fieldsplit_schur_precondition selfp (the "
                  f"constraint block is zero)" if "block 'l'" in why
                  else f"change -{prefix}pc_type")
        return SolverFailure(f"{solver} failed (DIVERGED_PCSETUP_FAILED, {why}): "
                             f"{advice}")
    return SolverFailure(
        f"{solver} did not converge ({_reason(ksp)}, {ksp.getIterationNumber()} "
        f"iterations, residual {ksp.getResidualNorm():.3g}): raise "
        f"-{prefix}ksp_max_it or change -{prefix}pc_type", reason in CURABLE)


WORKSPACE_RAISED = {}       # options prefix → the ICNTL(14) MUMPS was given


def failure_or_retry(ksp, err=None):
    """After a failed solve with ``ksp``, raised as the PETSc error ``err`` or
    only left in its reason (collective).

    MUMPS out of workspace (INFOG(1) = −8 or −9): ICNTL(14) is doubled (up to
    6400 %), recorded in ``WORKSPACE_RAISED`` (said at the end of a run, not
    in the middle of its progress lines) and None is returned, the caller
    then repeats the solve. Anything
    else: the ``SolverFailure`` naming the solver, its reason and the option
    to change.
    """
    prefix = ksp.getOptionsPrefix() or ""
    pc, F = _factor(ksp)
    if F is not None:
        info, more = F.getMumpsInfog(1), F.getMumpsInfo(2)
        if info in (-8, -9):
            icntl14 = F.getMumpsIcntl(14)
            if icntl14 < MUMPS_WORKSPACE_MAX:
                new = min(max(2 * icntl14, 100), MUMPS_WORKSPACE_MAX)
                refactor(ksp, new)
                WORKSPACE_RAISED[prefix] = new
                return None
            return SolverFailure(
                f"MUMPS factorisation out of workspace (INFOG(1) = {info}) even "
                f"with -{prefix}mat_mumps_icntl_14 {icntl14}: use more ranks "
                f"or another solver (-{prefix}pc_factor_mat_solver_type)")
        if info == -10:
            return SolverFailure(
                f"MUMPS: K is numerically singular (INFOG(1) = -10): redundant "
                f"constraints? -{prefix}mat_mumps_icntl_24 1 detects null pivots")
        if info == -13:
            return SolverFailure(
                f"MUMPS could not allocate memory (INFOG(1) = -13, INFO(2) = "
                f"{more}): use more ranks or -{prefix}mat_mumps_icntl_35 2 "
                f"(BLR compression)")
        if info < 0:
            return SolverFailure(
                f"MUMPS failed with INFOG(1) = {info}, INFO(2) = {more} (MUMPS "
                f"users' guide, error diagnostics): try "
                f"-{prefix}pc_factor_mat_solver_type superlu_dist")
    if ksp.getConvergedReason() < 0 or err is None:
        return ksp_failure(ksp)
    last = [s.strip() for s in str(err).splitlines() if s.strip()]
    return SolverFailure(f"PETSc error in the {prefix} solve "
                         f"({last[-1] if last else err}): change "
                         f"-{prefix}ksp_type / -{prefix}pc_type")


def solve_saddle(solve, ksp):
    """``solve()``, repeated with more MUMPS workspace while it runs out of
    it; any other failure, raised or only left in the KSP's reason, raises
    its ``SolverFailure`` (collective)."""
    while True:
        try:
            result = solve()
        except PETSc.Error as err:
            failure = failure_or_retry(ksp, err)
        else:
            if ksp.getConvergedReason() >= 0:
                return result
            failure = failure_or_retry(ksp)
        if failure is not None:
            raise failure
