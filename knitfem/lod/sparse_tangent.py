"""The reduced tangent Γᵀ K Γ on a fixed sparse pattern.

With Γ = Γ̃ ⊗ I₃, two volume control points c and d are coupled by Γᵀ K Γ
only where some yarn element (or a stitch of the shell stretch) reaches
both: its entries lie in the pattern of Γ̃ᵀ |K| Γ̃, which is that of the
reduced mass Γ̃ᵀ m Γ̃ (``ReducedModel.m``, PtAP's structural product) and of
the shell's stitch windows. That pattern, each entry a full 3 × 3 block, is
laid out once; a Newton iteration zeroes its values, adds each part's
contribution (a scipy sparse matrix, the sampled elements' Γ_Sᵀ K_S Γ_S, or a
dense one) by a binary search of its entries' keys (row · 3n + column) among
the pattern's, and hands PETSc the values in place: the AIJ matrix keeps its
nonzero pattern, so a sparse factorisation (MUMPS, by the ``reduced_``
options) keeps its symbolic phase.
"""

import numpy as np
from petsc4py import PETSc
from scipy import sparse

from knitfem.model.assembly import create_aij

__all__ = ["SparseTangent", "scalar_pattern"]


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
    ``assemble`` sums them over the ranks.
    """

    def __init__(self, comm, pattern, rows):
        self.comm = comm
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

    def zero(self):
        self.values[:] = 0.0

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
