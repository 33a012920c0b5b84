"""Saddle-point systems [A Cᵀ; C 0] as one AIJ matrix, their KSP, and what
to do when the solver fails.

K is one AIJ matrix on a value array of its own (``aij.OwnAIJ``), laid out
once from A's and C's patterns with an explicit zero diagonal in the
constraint block (factorisations and fieldsplit find its entries). When A's
values change (same pattern) ``update`` writes them into their places in K
by one indexed copy from where A keeps them, and C's, when they change,
through an SF that also sends Cᵀ's entries to the ranks whose rows they
land in. So K keeps its nonzero state and factorisations keep their
symbolic phase (MUMPS's analysis runs once a run), and no MatSetValues,
MatConvert or COO assembly runs in a Newton iteration (at 40×80 on two
ranks the COO matrices took 0.32 s to set up and 20 ms a Newton iteration
to fill). Small serial systems (the reduced model's) are held dense
instead, through a MATNEST converted once, and factorised by LAPACK's
pivoting LU. Each rank's rows are [its A rows, its C rows], so a saddle
vector's local array is the concatenation of the two local parts.

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

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from knitfem.model.assembly import csr_positions, csr_rows

from .aij import OwnAIJ, storage_pattern, storage_values
from .libpetsc import Int, library
from .progress import note

__all__ = ["SaddlePoint", "saddle_ksp", "detect_null_pivots", "SolverFailure",
           "solve_saddle", "ksp_failure", "failure_or_retry", "pc_failure"]


EV_REFACTOR = PETSc.Log.Event("knitMumpsRefactor")
WORKSPACE = 200
"""Default MUMPS ICNTL(14), extra workspace (%) over its estimate for delayed
pivots: the hanging 7×7 (``make demo``) ran out at 100 at t = 0.27 s of its
3 s and fits at 200. MUMPS allocates it but touches only what it uses: the
peak RSS of a step of the 50×100 jersey is the same at 100 and 200 (1.10 GB)."""
ORDERING = 6
"""MUMPS's ordering of the saddle point on one rank unless told otherwise
(ICNTL(7)): QAMD. Its own choice here is AMF (Debian's MUMPS has no METIS
or SCOTCH), whose factors grow fast with the yarn contact's pairs in the
pattern. Factorisation time, AMF against QAMD: the full 20×40 jersey's first
step 2.05 s against 0.50 s (PORD 0.70 s), the drape 12×12 96 against 43 ms,
the hanging 7×7 8.2 against 6.2 ms; without yarn contact the same within
10 % (40×80: 0.77 s each). In a run on several ranks MUMPS chooses (QAMD
was 10 % slower on 2 ranks at 40×80), also for a solver on one of them
(the option would stay in the database for the run's other solvers)."""


def zero_diagonal(comm, n_local, n_global):
    """An AIJ matrix holding explicit zeros on its diagonal."""
    start = comm.tompi4py().exscan(n_local) or 0
    ptr = np.arange(n_local + 1, dtype=PETSc.IntType)
    idx = np.arange(start, start + n_local, dtype=PETSc.IntType)
    Z = PETSc.Mat().createAIJ(((n_local, n_global), (n_local, n_global)),
                              csr=(ptr, idx, np.zeros(n_local)), comm=comm)
    Z.assemble()
    return Z


def _in_storage_order(indptr, indices, position, sizes):
    """(rows, columns) of a ``storage_pattern`` in storage order, and its
    block sizes."""
    rows = csr_rows(indptr)
    if position is None:
        return rows, indices, sizes
    r, c = np.empty_like(rows), np.empty_like(indices)
    r[position], c[position] = rows, indices
    return r, c, sizes


def _copy_off_diagonal(blocks):
    """Storage blocks for a new ``OwnAIJ``: the diagonal block's arrays
    shared (PETSc only reads them), the off-diagonal block's copied (PETSc
    renumbers its columns in place)."""
    return blocks[:1] + [(ptr, cols.copy()) for ptr, cols in blocks[1:]]


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
        self.P, self.delta, self.nest, self.sf = None, 0.0, None, None
        self.nu = A.getLocalSize()[0]
        self.nl = C.getLocalSize()[0] if C is not None else 0
        self.constrained = C is not None and C.getSize()[0] > 0
        if not self.constrained:
            self.nl, self.K = 0, A
            self.P = A
            return
        comm = A.getComm()
        # K's rows on rank r: its rows of A, then its rows of C
        self.k_ranges = np.add(A.getOwnershipRanges(), C.getOwnershipRanges())
        first = self.k_ranges[comm.getRank()]
        self.fields = [PETSc.IS().createStride(size, first=start, step=1, comm=comm)
                       for size, start in ((self.nu, first),
                                           (self.nl, first + self.nu))]
        if dense and comm.getSize() == 1:
            self.Ct = C.transpose(PETSc.Mat())
            self.Z = zero_diagonal(comm, *C.getSizes()[0])
            self.nest = PETSc.Mat().createNest([[A, self.Ct], [C, self.Z]], comm=comm)
            self.aij = self.nest.convert("aij", PETSc.Mat())
            self.K = self.aij.convert("dense", PETSc.Mat())
            self.P = self.K
            return
        blocks = self._own_values()
        tau = regularization_option(prefix, comm) if prefix else 0.0
        self.P = self.K if tau == 0 else self.regularized(tau, blocks)

    def _own_values(self):
        """K on a value array of its own (``aij.OwnAIJ``), laid out from A's
        and C's storage without a sort of their entries, and the places
        their values go; returns K's storage blocks.

        A row of A's part holds A's row, then Cᵀ's (columns of the
        multipliers); a row of C's part C's row, then its diagonal. K's
        diagonal block is these runs as they come (A's and C's diagonal
        blocks, Cᵀ's entries of this rank's multipliers); the few entries
        of its off-diagonal block (couplings with other ranks' courses) are
        sorted. Cᵀ's entries come from C's through a transposed matrix of
        C's entry numbers; an SF (``self.sf``) sends C's values to their
        places in K, on whatever rank they land."""
        comm, rank = self.A.getComm(), self.A.getComm().getRank()
        nu, nl, k = self.nu, self.nl, self.k_ranges
        n = nu + nl
        a0, c0 = self.A.getOwnershipRange()[0], self.C.getOwnershipRange()[0]
        a_rows, a_cols, self.a_sizes = _in_storage_order(*storage_pattern(self.A))
        ci, cj, c_position, self.c_sizes = storage_pattern(self.C)
        c_rows, c_cols, _ = _in_storage_order(ci, cj, c_position, self.c_sizes)
        t_rows, t_cols, t_owner, t_index = self._transposed_entries(ci, cj, c_position)
        t_in = t_owner == rank
        lam = np.arange(nl)
        na, nc = self.a_sizes[0], self.c_sizes[0]
        # (rows, local columns) of the diagonal block's runs, in row order
        runs = [(a_rows[:na], a_cols[:na] - a0 if a0 else a_cols[:na]),
                (t_rows[t_in], nu + t_cols[t_in] - c0),
                (nu + c_rows[:nc], c_cols[:nc] - a0),
                (nu + lam, nu + lam)]
        counts = [np.bincount(rows, minlength=n) for rows, _ in runs]
        dptr = np.zeros(n + 1, dtype=PETSc.IntType)
        np.cumsum(sum(counts), out=dptr[1:])
        dcols = np.empty(dptr[-1], dtype=PETSc.IntType)
        first, inside = dptr[:-1].astype(np.int64), []
        for (rows, cols), count in zip(runs, counts):
            pos = csr_positions(np.concatenate([[0], np.cumsum(count)]), first)
            dcols[pos] = cols
            inside.append(pos)
            first += count
        # the off-diagonal block's, in K's global columns, sorted
        a, c = (np.asarray(M.getOwnershipRanges()) for M in (self.A, self.C))
        orows = np.concatenate([a_rows[na:], t_rows[~t_in], nu + c_rows[nc:]])
        ocols = np.concatenate([self._to_k(a_cols[na:], a, 0 * a),
                                self._to_k(t_cols[~t_in], c, np.diff(a)),
                                self._to_k(c_cols[nc:], a, 0 * a)])
        order = np.lexsort((ocols, orows))
        outside = np.empty(len(order), dtype=np.int64)
        outside[order] = dptr[-1] + np.arange(len(order))
        optr = np.zeros(n + 1, dtype=PETSc.IntType)
        np.cumsum(np.bincount(orows, minlength=n), out=optr[1:])
        blocks = [(dptr, dcols)]
        if comm.getSize() > 1:
            blocks.append((optr, ocols[order]))
        # where A's, Cᵀ's and C's values go, in their storage order
        no_a, no_t = len(a_rows) - na, np.count_nonzero(~t_in)
        a_pos = np.concatenate([inside[0], outside[:no_a]]) if no_a else inside[0]
        t_pos = np.empty(len(t_rows), dtype=np.int64)
        t_pos[t_in], t_pos[~t_in] = inside[1], outside[no_a:no_a + no_t]
        c_pos = np.concatenate([inside[2], outside[no_a + no_t:]])
        self.diagonal = inside[3]
        self.a_pos = np.split(a_pos, np.cumsum(self.a_sizes)[:-1])
        self.own = [OwnAIJ(comm, ((n, k[-1]), (n, k[-1])), _copy_off_diagonal(blocks))]
        self.K = self.own[0].mat
        # C's values (roots: this rank's, in storage order) to C's and Cᵀ's places
        self.sf = PETSc.SF().create(comm=comm)
        remote = np.empty((len(c_pos) + len(t_pos), 2), dtype=PETSc.IntType)
        remote[:len(c_pos), 0] = rank
        remote[:len(c_pos), 1] = np.arange(len(c_pos))
        remote[len(c_pos):, 0], remote[len(c_pos):, 1] = t_owner, t_index
        leaves = np.concatenate([c_pos, t_pos]).astype(PETSc.IntType)
        self.sf.setGraph(len(c_pos), leaves, remote.ravel())
        self.sf.setUp()
        self._write_values(constraints=True)
        return blocks

    def _transposed_entries(self, indptr, indices, position):
        """Cᵀ's entries in this rank's rows (local row, global column of C's
        row) in CSR order, and where their values are in C's storage (the
        owning rank, the position there): the transpose of C with the
        numbers of its entries for values. C's rows are (indptr, indices)
        here, their entries at ``position`` in its storage."""
        comm = self.C.getComm()
        nnz = len(indices)
        offsets = np.concatenate([[0], np.cumsum(comm.tompi4py().allgather(nnz))])
        ids = np.arange(nnz) if position is None else position
        numbers = PETSc.Mat().createAIJ(self.C.getSizes(), csr=(
            indptr, indices, (offsets[comm.getRank()] + ids).astype(np.float64)),
            comm=comm)
        transposed = numbers.transpose(PETSc.Mat())
        ti, tj, tv = transposed.getValuesCSR()
        for M in (numbers, transposed):
            M.destroy()
        ids = tv.astype(np.int64)
        owner = np.searchsorted(offsets, ids, side="right") - 1
        return csr_rows(ti), tj, owner, ids - offsets[owner]

    def regularized(self, tau, blocks):
        """P = K − δ [0 0; 0 I] with δ = τ / max diag A, on K's storage
        ``blocks``."""
        self.delta = tau / self.A.getDiagonal().norm(PETSc.NormType.INFINITY)
        self.own.append(OwnAIJ(self.A.getComm(), self.K.getSizes(),
                               _copy_off_diagonal(blocks)))
        self._write_values(constraints=False)
        return self.own[1].mat

    def _to_k(self, cols, ranges, shift):
        """K's global index of global index ``cols`` of a block whose
        ownership is ``ranges``: j − (block's first on its rank r) + (K's
        first on r) + ``shift``[r] (A's rows on r for a multiplier)."""
        owner = np.searchsorted(ranges, cols, side="right") - 1
        return cols - ranges[owner] + self.k_ranges[owner] + shift[owner]

    def update(self, constraints=False):
        """Refresh K after A's values changed, and C's with ``constraints``
        (same nonzero patterns)."""
        if self.aij is not None:
            if constraints:
                self.C.transpose(self.Ct)
            self._dense_update(constraints)
        elif self.constrained:
            self._write_values(constraints)

    def _write_values(self, constraints):
        """A's values, and C's with ``constraints``, into their places in K's
        value array (read where A and C keep them); P's is K's with −δ on
        the multipliers' diagonal. K and P are assembled: a new state, so
        factorisations redo."""
        K = self.own[0].values
        with storage_values(self.A, self.a_sizes) as parts:
            for values, pos in zip(parts, self.a_pos):
                K[pos] = values
        if constraints:
            with storage_values(self.C, self.c_sizes) as parts:
                roots = np.concatenate(parts)
            self.sf.bcastBegin(MPI.DOUBLE, roots, K, MPI.REPLACE)
            self.sf.bcastEnd(MPI.DOUBLE, roots, K, MPI.REPLACE)
        for own in self.own[1:]:
            own.values[:] = K
            own.values[self.diagonal] = -self.delta
        for own in self.own:
            own.assemble()

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
            C[csr_rows(indptr), indices] = values
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
            for obj in (self.nest, self.K, self.aij, P, self.sf,
                        *self.fields):
                if obj is not None:
                    obj.destroy()
            if self.nest is not None:
                self.Ct.destroy()
                self.Z.destroy()


def regularization_option(prefix, comm):
    """τ of -<prefix>saddle_regularization: 1 on more than one rank, else 0."""
    from knitfem.cli.options import KnitOptions

    opts = KnitOptions(prefix + "saddle_")
    return opts.getReal("regularization", 1.0 if comm.getSize() > 1 else 0.0,
                        "solve with the LDLt of [A C^T; C -tau/max(diag A) I] "
                        "without pivoting (0: pivoting LDLt of K)",
                        nonnegative=True)


def detect_null_pivots(pc, prefix):
    """Have a MUMPS factorisation of ``pc`` (set from its options) detect
    null pivots (ICNTL(24) = 1) and solve on the rest, unless
    -<prefix>mat_mumps_icntl_24 says otherwise (``saddle_ksp``)."""
    if pc.getType() in ("lu", "cholesky") and pc.getFactorSolverType() == "mumps" \
            and not PETSc.Options(prefix).hasName("mat_mumps_icntl_24"):
        pc.setFactorSetUpSolverType()
        pc.getFactorMatrix().setMumpsIcntl(24, 1)


def saddle_ksp(saddle, prefix, null_pivots=False):
    """A KSP on the saddle point, then the command line. By default a direct
    solve: MUMPS LDLᵀ of the symmetric indefinite K (2×2 pivots; 2.2× faster
    than its LU on the 15×30 jersey, ``benchmarks/results/solver_sweep.json``)
    with ``WORKSPACE`` % extra workspace for delayed pivots (ICNTL(14)),
    ordered by ``ORDERING`` on one rank (ICNTL(7)); LAPACK LU for
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

    ``null_pivots``: MUMPS detects null pivots (ICNTL(24) = 1) and solves on
    the rest, for a system whose A can be singular (a mixed model whose Γ_mix
    has a null space). Serial MUMPS pivots past them anyway; parallel MUMPS
    factors its root front by ScaLAPACK without pivoting, and its solves were
    then too inaccurate for Newton to converge (|F| stalled at 5e-11 against
    2e-12 serially, in the mixed model's free spin on 2 ranks).
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
        options.setValue("mat_mumps_icntl_14", WORKSPACE)
    if solver == "mumps" and PETSc.COMM_WORLD.getSize() == 1 and \
            not options.hasName("mat_mumps_icntl_7"):     # a serial run
        options.setValue("mat_mumps_icntl_7", ORDERING)
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
    if null_pivots:
        detect_null_pivots(pc, prefix)
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
    from knitfem.cli.options import KnitOptions

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


def negative_pivots(ksp):
    """The number of negative pivots (eigenvalues) of ksp's operator,
    factorised now by MUMPS's LDLᵀ (INFOG(12); a solve with the operator
    unchanged reuses the factors); None where the KSP does not factorise it
    so (LU, a Krylov method) or the factorisation failed (the solve then
    reports it)."""
    pc = ksp.getPC()
    if pc.getType() != "cholesky" or pc.getFactorSolverType() != "mumps":
        return None
    ksp.setOperators(*ksp.getOperators())       # set up again, not skipped
    ksp.setUp()
    F = pc.getFactorMatrix()
    return F.getMumpsInfog(12) if F.getMumpsInfog(1) >= 0 else None


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
    6400 %), recorded in ``WORKSPACE_RAISED`` (said at the end of a run, and
    at once by ``progress.note``) and None is returned, the caller then
    repeats the solve. Anything
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
                with EV_REFACTOR:
                    refactor(ksp, new)
                WORKSPACE_RAISED[prefix] = new
                note(f"MUMPS ran out of workspace (INFOG(1) = {info}): factorising "
                     f"again with -{prefix}mat_mumps_icntl_14 {new}", always=True)
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
    text = str(err).lower()
    options = (f"-{prefix}snes_linesearch_type and its options"
               if "line search" in text or "linesearch" in text
               else f"-{prefix}ksp_type / -{prefix}pc_type")
    return SolverFailure(f"PETSc error in the {prefix} solve "
                         f"({last[-1] if last else err}): change {options}")


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
