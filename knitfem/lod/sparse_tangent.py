"""The reduced tangent Γᵀ K Γ on a fixed sparse pattern.

With Γ = Γ̃ ⊗ I₃, two volume control points c and d are coupled by Γᵀ K Γ
only where some yarn element (or a stitch of the shell stretch) reaches
both: its entries lie in the pattern of Γ̃ᵀ |K| Γ̃, which is that of the
reduced mass Γ̃ᵀ m Γ̃ (``ReducedModel.m``, PtAP's structural product) and of
the shell's stitch windows. That pattern, each entry a full 3 × 3 block, is
laid out once; a Newton iteration zeroes its values, adds each part's
contribution and hands PETSc the values in place: the AIJ matrix keeps its
nonzero pattern, so a sparse factorisation (MUMPS, by the ``reduced_``
options) keeps its symbolic phase. A part whose entries keep their places
(the sampled elements' Γ_Sᵀ K_S Γ_S, the shell's) finds their positions in
the pattern once (``positions``) and adds its values there (``add_at``):
the sampled elements by the compiled ``GroupedTangent.add_into``, or by
``PatchProduct`` (numpy, the reference); the contact with bodies, whose
points within the gap change, keeps the positions of each group of volume
patches it has met (``QuadratureProduct``, its GEMMs by a compiled loop or
by numpy's). A scipy matrix is
placed by a binary search of its entries' keys (row · 3n + column) among
the pattern's (``add``: the reference the placed parts are tested
against).
"""

import numpy as np
from petsc4py import PETSc
from scipy import sparse

from knitfem.lod.rows import VERSION as ROWS_VERSION, add_at
from knitfem.model.assembly import create_aij
from knitfem.yarn.kernels import compiled_module

__all__ = ["DenseValues", "PatchProduct", "QuadratureProduct", "SparseTangent",
           "TangentPart", "patches", "scalar_pattern"]


def patches(cols):
    """The volume patches of the rows of Γ̃ whose columns are ``cols`` (m, k):
    a patch is the rows with the same columns. Returns (the patches'
    columns (npatch, k), each row's patch (m,))."""
    columns, patch = np.unique(cols, axis=0, return_inverse=True)
    return columns, patch.ravel()


def scalar_pattern(A):
    """The structure of the local rows of a scalar AIJ ``A`` (n × n) from
    every rank, as a scipy CSR matrix of ones on every rank (collective)."""
    indptr, indices, _ = A.getValuesCSR()
    lo, _ = A.getOwnershipRange()
    rows = np.repeat(np.arange(lo, lo + len(indptr) - 1), np.diff(indptr))
    comm = A.getComm().tompi4py()
    if comm.size > 1:
        rows = np.concatenate(comm.allgather(rows))
        indices = np.concatenate(comm.allgather(indices))
    n = A.getSize()[0]
    return sparse.csr_matrix((np.ones(len(rows)), (rows, indices)), shape=(n, n))


class SparseTangent:
    """Γᵀ K Γ (3n × 3n, block size 3) on the pattern ``pattern`` (a scalar
    n × n scipy matrix whose structure couples the volume's control points)
    with full 3 × 3 blocks: an AIJ matrix whose rows are distributed like
    ``rows`` = (lo, hi) of this rank (collective).

    Every rank adds the contributions of its own yarns to any row;
    ``assemble`` sums them over the ranks. ``compiled``: values added by
    the compiled scatter, else by numpy's bincount (``rows.add_at``).
    """

    def __init__(self, comm, pattern, rows, compiled=True):
        self.comm, self.compiled = comm, compiled
        P = sparse.kron(sparse.csr_matrix(pattern, dtype=float),
                        np.ones((3, 3)), format="csr")
        P.sum_duplicates()
        P.sort_indices()
        self.N = N = P.shape[0]
        self.indptr = P.indptr.astype(np.int64)
        self.indices = P.indices.astype(np.int64)
        self.keys = np.repeat(np.arange(N, dtype=np.int64), np.diff(self.indptr)) \
            * N + self.indices
        self.values = np.zeros(len(self.indices))
        self.outside = 0                   # entries added outside the pattern
        lo, hi = rows
        self.lo, self.hi = lo, hi
        self.local = slice(self.indptr[lo], self.indptr[hi])
        csr = (self.indptr[lo:hi + 1] - self.indptr[lo],
               self.indices[self.local].astype(PETSc.IntType))
        if comm.size > 1:
            self.mat = create_aij(comm, (hi - lo, N), (hi - lo, N),
                                  (*csr, self.values[self.local]), bsize=3)
        else:
            self.mat = PETSc.Mat().createAIJWithArrays(
                (N, N), (csr[0].astype(PETSc.IntType), csr[1], self.values), comm=comm)
            self.mat.setBlockSize(3)
            self.mat.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        self.mat.setOptionsPrefix("reduced_K_")

    @property
    def nnz(self):
        return len(self.values)

    @property
    def layout(self):
        """Whose positions these values are at: itself (a ``TangentPart``'s is
        its tangent's), the key of the parts' laid-out positions."""
        return self

    def zero(self):
        self.values[:] = 0.0

    def positions(self, rows, cols):
        """The positions in ``values`` of the entries (rows, cols) (arrays of
        a shape), found once: ``nnz`` (a slot past the end, which ``add_at``
        drops) for those outside the pattern, and counted (``outside``)."""
        keys = np.asarray(rows, dtype=np.int64) * self.N + cols
        pos = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        hit = self.keys[pos] == keys
        self.outside += int(np.count_nonzero(~hit))
        return np.where(hit, pos, self.nnz)

    def add_at(self, pos, x):
        """values[pos] += x (arrays of a shape, ``pos`` from ``positions``),
        entries at the same position summed, those at ``nnz`` dropped."""
        add_at(self.values, pos, x, self.compiled)

    def add(self, A):
        """values += the entries of the scipy sparse matrix ``A`` (3n × 3n);
        entries outside the pattern are dropped and counted (``outside``)."""
        A = A.tocoo()
        keys = A.row.astype(np.int64) * self.N + A.col
        pos = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        hit = self.keys[pos] == keys
        self.outside += int(np.count_nonzero(A.data[~hit]))
        self.values += np.bincount(pos[hit], A.data[hit], minlength=len(self.values))

    def add_dense(self, R):
        """values += the pattern's entries of the dense ``R`` (3n × 3n)."""
        self.values += R.ravel()[self.keys]

    def assemble(self):
        """The values summed over the ranks into the matrix, assembled (a new
        state: factorisations redo). Returns the matrix (collective)."""
        if self.comm.size > 1:
            from mpi4py import MPI

            self.comm.tompi4py().Allreduce(MPI.IN_PLACE, self.values, op=MPI.SUM)
            lo, hi = self.lo, self.hi
            self.mat.setValuesCSR(self.indptr[lo:hi + 1] - self.indptr[lo],
                                  self.indices[self.local], self.values[self.local])
        self.mat.assemble()
        return self.mat

    def destroy(self):
        self.mat.destroy()


class TangentPart:
    """One part's share of a ``SparseTangent`` T: T's pattern and positions,
    values of its own, so that parts formed side by side (``lod.parts``)
    are added into T's afterwards in a fixed order."""

    def __init__(self, T):
        self.T, self.N, self.nnz, self.compiled = T, T.N, T.nnz, T.compiled
        self.layout = T
        self.values = np.zeros(T.nnz)

    def zero(self):
        self.values[:] = 0.0

    def positions(self, rows, cols):
        """T's ``positions``."""
        return self.T.positions(rows, cols)

    def add_at(self, pos, x):
        """values[pos] += x, as T's ``add_at``."""
        add_at(self.values, pos, x, self.compiled)

    def add_dense(self, R):
        """values += the pattern's entries of the dense ``R``, as T's."""
        self.values += R.ravel()[self.T.keys]


class DenseValues:
    """A dense N × N array ``R`` seen as a ``SparseTangent``'s values (every
    entry in the pattern, at position r N + c), so that the parts laid out
    for the sparse tangent add into the dense one the same way (``R``
    C-ordered: its values are added in place; ``compiled`` as
    ``SparseTangent``'s)."""

    def __init__(self, R, compiled=True):
        self.compiled = compiled
        if not R.flags.c_contiguous:
            raise ValueError("DenseValues: R must be a C-ordered array (its entries "
                             "are added in place through a flat view)")
        self.R, self.N = R, len(R)
        self.values = R.reshape(-1)              # a view: added in place
        self.layout = self

    @property
    def nnz(self):
        return self.N * self.N

    def positions(self, rows, cols):
        return np.asarray(rows, dtype=np.int64) * self.N + cols

    def add_at(self, pos, x):
        """R's entries at ``pos`` += x (summed where they meet; ``nnz``
        dropped)."""
        add_at(self.R.reshape(-1), pos, x, self.compiled)


class PatchProduct:
    """Γᵀ K Γ (Γ = Γ̃ ⊗ I₃) of a K on a fixed pattern with full 3 × 3 blocks
    (``indptr3``, ``indices3``, as ``ElementPattern.blocks3``) over m points
    whose rows of Γ̃ are (``cols``, ``vals``), (m, k), added to the values of
    a ``SparseTangent`` ``T`` a patch of the volume at a time.

    The points over a patch P share its k columns; with U_P the columns of
    the points their rows of K reach and (i, j) a block's components,

        Y^{ij}_{pd} = Σ_q K^{ij}_{pq} Γ̃_{qd}   (p ∈ P, d ∈ U_P),
        (Γᵀ K Γ)_{(c,i),(d,j)} += Σ_{p∈P} Γ̃_{pc} Y^{ij}_{pd}   (c ∈ P's columns),

    Y a sparse map of K's blocks fixed at set-up (``Y``: padded to the
    largest patch and reach, (patches · points · reach) × blocks) and the
    second sum one GEMM a patch, its entries placed by positions found once.
    """

    def __init__(self, T, indptr3, indices3, cols, vals):
        self.T = T
        m, k = cols.shape
        nb = (indptr3[3:len(indptr3):3] - indptr3[0:-1:3]) // 9     # blocks a row
        p = np.repeat(np.arange(m), nb)                               # block (p, q)
        t = np.arange(len(p)) - np.repeat(np.cumsum(nb) - nb, nb)     # its place in row p
        q = indices3[indptr3[3 * p] + 3 * t] // 3
        c = np.arange(3)
        # the position of K^{ij}_{pq} in K's values, (blocks, 3, 3)
        self.block = indptr3[3 * p[:, None] + c][:, :, None] + 3 * t[:, None, None] + c
        keys, patch = np.unique(cols, axis=0, return_inverse=True)
        patch = patch.ravel()
        count = np.bincount(patch)
        order = np.argsort(patch, kind="stable")
        slot = np.empty(m, dtype=np.int64)                            # p's row in its patch
        slot[order] = np.arange(m) - np.repeat(np.cumsum(count) - count, count)
        n = T.N // 3
        reach, u = np.unique(patch[p][:, None] * n + cols[q], return_inverse=True)
        width = np.bincount(reach // n, minlength=len(keys))          # |U_P|
        first = np.cumsum(width) - width
        u = u.reshape(len(p), k) - first[patch[p]][:, None]           # d's place in U_P
        self.shape = (len(keys), count.max(), width.max())
        npatch, rows, wide = self.shape
        self.Y = sparse.csr_matrix(
            (vals[q].ravel(), (((patch[p] * rows + slot[p])[:, None] * wide + u).ravel(),
                               np.repeat(np.arange(len(p)), k))),
            shape=(npatch * rows * wide, len(p)))
        self.Gt = np.zeros((npatch, k, rows))                         # Γ̃_{P·}ᵀ
        self.Gt[patch, :, slot] = vals
        U = np.zeros((npatch, wide), dtype=np.int64)
        U[reach // n, np.arange(len(reach)) - first[reach // n]] = reach % n
        # the entry (c, i), (d, j) of Γᵀ K Γ of each [P, c, d, i, j] (d ∈ U_P)
        shape = (npatch, k, wide, 3, 3)
        inside = np.broadcast_to((np.arange(wide) < width[:, None])[:, None, :, None, None],
                                 shape)
        self.pos = np.full(shape, T.nnz)
        self.pos[inside] = T.positions(
            np.broadcast_to(3 * keys[:, :, None, None, None] + c[:, None], shape)[inside],
            np.broadcast_to(3 * U[:, None, :, None, None] + c, shape)[inside])

    def add(self, values):
        """T's values += Γᵀ K Γ, K given by its ``values``."""
        npatch, rows, wide = self.shape
        Y = (self.Y @ values[self.block].reshape(-1, 9)).reshape(npatch, rows, wide * 9)
        self.T.add_at(self.pos, np.matmul(self.Gt, Y))


UPPER = np.array([0, 1, 2, 4, 5, 8])
"""The entries i ≤ j of a 3 × 3 block, flat."""
LOWER = np.array([1, 2, 4])
"""Of ``UPPER``'s, where those i < j sit: their transposes fill i > j."""
SLOT_ROW, SLOT_COL = np.array([divmod(c, 3) for c in UPPER]
                              + [divmod(UPPER[c], 3)[::-1] for c in LOWER]).T
"""(i, j) of the nine slots of a block as ``QuadratureProduct`` lays them."""


class QuadratureProduct:
    """Σ_q (c_q c_qᵀ) ⊗ H_q added to the values of a ``SparseTangent`` (or a
    ``DenseValues``) ``T``, for quadrature points q of yarn elements whose
    3 × 3 blocks H_q change from call to call (the contact with bodies),

        c_q = Σ_a B_qa Γ̃_{p_a}      (the volume weights of x_q = Σ_a B_qa p_a),

    the p_a an element's four control points, their rows of Γ̃ (``cols``,
    ``vals``, (m, k)) and B (nq, 4) the basis at the quadrature points.

    A patch is the points whose rows of Γ̃ have the same columns. The
    elements are grouped by the patches of their four points (most lie in
    one, some straddle two); a group's quadrature points reach the union U
    of its patches' columns, and its share is one GEMM,

        Σ_q c_q (c_q ⊗ H_q)ᵀ = C_Uᵀ Z,   Z_q = c_q ⊗ vec H_q,

    C_U the group's c_q over U, (points, |U|), Z over the six entries i ≤ j
    of the symmetric H_q (the others are their transposes). The positions
    of a group's entries in ``T`` are found at its first call and kept (by
    U). The groups are looped over by ``_rows.quadrature_product`` where
    ``T.compiled`` (the points outside the gap, H_q = 0, left out), else in
    numpy (the reference). ``patched``: ``patches(cols)``, if the caller
    has it.
    """

    def __init__(self, T, cols, vals, B, patched=None):
        self.T, self.vals, self.B = T, vals, B
        self.n = T.N // 3
        self.columns, self.patch = patched or patches(cols)
        self.kept, self.last = {}, None

    def _positions(self, U):
        """Positions in T of the entries (3 U_k + i, 3 U_l + j), (w, w, 9),
        (i, j) = (``SLOT_ROW``, ``SLOT_COL``)."""
        key = U.tobytes()
        pos = self.kept.get(key)
        if pos is None:
            pos = self.kept[key] = self.T.positions(3 * U[:, None, None] + SLOT_ROW,
                                                    3 * U[None, :, None] + SLOT_COL)
        return pos

    def _unions(self, groups):
        """The union U of the columns of each group of patches (g, 4) as
        (columns, first, width) of the groups' U laid end to end, and where
        each patch's columns sit in its group's U, (g, 4, k)."""
        g, k = len(groups), self.columns.shape[1]
        cols = self.columns[groups].reshape(g, -1)                   # (g, 4k)
        keys = np.unique(np.arange(g)[:, None] * self.n + cols)
        first = np.searchsorted(keys, np.arange(g) * self.n)
        width = np.diff(np.append(first, len(keys)))
        within = np.searchsorted(keys, np.arange(g)[:, None] * self.n + cols) - first[:, None]
        return keys % self.n, first, width, within.reshape(g, 4, k)

    def _groups(self, conn):
        """The distinct tuples of patches of the elements' four points, (g,
        4), and each element's group: by one integer key an element (``n``
        patches, n⁴ < 2⁶³), else by numpy's unique of rows."""
        p = self.patch[conn]
        n = len(self.columns)
        if n**4 >= 2**63:
            groups, group = np.unique(p, axis=0, return_inverse=True)
            return groups, group.ravel()
        keys, group = np.unique(((p[:, 0] * n + p[:, 1]) * n + p[:, 2]) * n + p[:, 3],
                                return_inverse=True)
        return np.stack([keys // n**3, keys // n**2 % n, keys // n % n, keys % n],
                        axis=1), group

    def add(self, conn, H, out=None):
        """``out``'s values (T's, or a ``TangentPart`` of T's) += Σ_q (c_q c_qᵀ)
        ⊗ H_q over the elements of control points ``conn`` (m, 4) (rows of
        ``cols``) and H (m, nq, 3, 3)."""
        out = self.T if out is None else out
        if not len(conn):
            return
        groups, group = self._groups(conn)
        order = np.argsort(group, kind="stable")
        conn, H, group = conn[order], H[order], group[order]
        columns, first, width, within = self._unions(groups)
        m, w_max = len(conn), width.max()
        Cp = np.zeros((m, 4 * w_max))
        at = (np.arange(4)[:, None] * w_max + within[group]).reshape(m, -1)
        np.put_along_axis(Cp, at, self.vals[conn].reshape(m, -1), axis=1)
        C = np.einsum("qa,eak->eqk", self.B, Cp.reshape(m, 4, w_max))   # (m, nq, w)
        bounds = np.searchsorted(group, np.arange(len(groups) + 1))
        ends = np.cumsum(9 * width**2)
        H6 = H.reshape(m, -1, 9)[:, :, UPPER]                         # H_q symmetric
        pos = self._placed(groups, columns, first, width)
        if out.compiled:
            H6 = H6.reshape(-1, 6)
            live = np.flatnonzero(H6.any(axis=1))     # points outside the gap add 0
            rows = np.searchsorted(live, len(self.B) * bounds)
            compiled_module("knitfem.lod._rows", ROWS_VERSION).quadrature_product(
                C.reshape(-1, w_max)[live], H6[live], rows, width.astype(np.int64),
                ends - 9 * width**2, pos, out.values)
            return
        val = np.empty(ends[-1])
        for g, (s, t) in enumerate(zip(bounds[:-1], bounds[1:])):
            w = width[g]
            Cg = C[s:t, :, :w].reshape(-1, w)
            Z = (Cg[:, :, None] * H6[s:t].reshape(-1, 1, 6)).reshape(-1, 6 * w)
            V = (Cg.T @ Z).reshape(w, w, 6)                           # (k, l, i ≤ j)
            block = val[ends[g] - 9 * w * w:ends[g]].reshape(w, w, 9)
            block[:, :, :6] = V
            block[:, :, 6:] = V[:, :, LOWER].transpose(1, 0, 2)
        out.add_at(pos, val)

    def _placed(self, groups, columns, first, width):
        """The positions of ``add``'s values for these groups, laid end to
        end, kept for the last set of groups (a Newton iteration's contact
        region is often the last one's)."""
        key = groups.tobytes()
        if self.last is None or self.last[0] != key:
            self.last = (key, np.concatenate([
                self._positions(columns[f:f + w]).ravel() for f, w in zip(first, width)]))
        return self.last[1]
