"""AIJ matrices on value arrays of our own, and where an AIJ matrix keeps its
values.

PETSc stores a rank's rows of an AIJ matrix as sequential CSR blocks: on
several ranks a diagonal block (the columns the rank owns, numbered from
its first) and an off-diagonal block (the other columns); on one rank the
first only. Rows are sorted by column in both, so the *storage order* of a
rank's entries is its CSR order with the diagonal block's entries taken out
in front (``storage_positions``).

``OwnAIJ`` makes a matrix whose values are one numpy array of ours, in
storage order (MatCreateSeqAIJWithArrays; MatCreateMPIAIJWithSplitArrays on
several ranks): an assembly after indexed stores into that array makes them
the matrix's, with no MatSetValues, no COO and no copy. ``storage_pattern``
and ``storage_values`` read any AIJ matrix's entries in storage order, its
values on its own arrays, so that a Newton matrix is written from its
blocks' values as they are.
"""

import ctypes
from contextlib import ExitStack, contextmanager

import numpy as np
from petsc4py import PETSc

from knitfem.model.assembly import csr_rows

from .libpetsc import check, library, seqaij_values

__all__ = ["OwnAIJ", "storage_positions", "storage_pattern", "storage_values"]


def storage_positions(indptr, indices, start, end):
    """Storage position of every entry of a rank's CSR rows (global columns
    sorted in each row) whose diagonal block is the columns [start, end):
    the diagonal block's entries first, in CSR order, then the others.
    Returns (positions, number of diagonal-block entries)."""
    diagonal = (indices >= start) & (indices < end)
    nd = int(np.count_nonzero(diagonal))
    position = np.empty(len(indices), dtype=np.int64)
    position[diagonal] = np.arange(nd)
    position[~diagonal] = nd + np.arange(len(indices) - nd)
    return position, nd


class OwnAIJ:
    """An AIJ matrix of ``sizes`` ((local, global) rows, columns) holding
    ``values`` (storage order) itself. Collective.

    ``blocks`` are the CSR patterns (indptr, columns) of this rank's
    storage blocks: on one rank one block; on several the diagonal block
    (columns numbered from the rank's first) and the off-diagonal block
    (global columns; PETSc renumbers that array in place). Write into
    ``values``, then ``assemble``. ``from_csr`` makes one from the rank's
    rows in CSR order.
    """

    def __init__(self, comm, sizes, blocks, bsize=None):
        blocks = [tuple(np.asarray(a, dtype=PETSc.IntType) for a in block)
                  for block in blocks]
        ends = np.cumsum([0] + [len(cols) for _, cols in blocks])
        self.values = np.zeros(ends[-1], dtype=PETSc.ScalarType)
        csr = [(ptr, cols, self.values[lo:hi])
               for (ptr, cols), lo, hi in zip(blocks, ends[:-1], ends[1:])]
        self.csr = csr                  # PETSc holds these arrays: keep them
        self.mat = PETSc.Mat().createAIJWithArrays(
            sizes, csr[0] if len(csr) == 1 else tuple(csr), comm=comm)
        if bsize:
            self.mat.setBlockSize(bsize)
        self.mat.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        self.position = None

    @classmethod
    def from_csr(cls, comm, sizes, indptr, indices, bsize=None):
        """One on the pattern (indptr, global columns sorted in each row) of
        this rank's rows; ``place`` maps its CSR positions into ``values``."""
        if comm.getSize() == 1:
            return cls(comm, sizes, [(indptr, indices)], bsize)
        n = sizes[1][0]
        start = comm.tompi4py().exscan(n) or 0
        position, nd = storage_positions(indptr, indices, start, start + n)
        rows = csr_rows(indptr)
        diagonal = position < nd
        blocks = []
        for part, cols in ((diagonal, indices[diagonal] - start),
                           (~diagonal, indices[~diagonal])):
            ptr = np.zeros(len(indptr), dtype=PETSc.IntType)
            np.cumsum(np.bincount(rows[part], minlength=len(indptr) - 1), out=ptr[1:])
            blocks.append((ptr, cols))
        own = cls(comm, sizes, blocks, bsize)
        own.position = position
        return own

    def place(self, slots):
        """Positions in ``values`` of the CSR positions ``slots`` (−1 kept)."""
        if self.position is None:
            return slots
        return np.where(slots >= 0, self.position[np.maximum(slots, 0)], -1)

    def assemble(self):
        """A new state of the matrix: what ``values`` holds now."""
        self.mat.assemble()


def storage_pattern(A):
    """A rank's rows of AIJ matrix A: (indptr, global columns) in CSR order,
    the storage position of every entry (None on one rank, where they are
    the same) and the sizes of its storage blocks (``storage_values``)."""
    indptr, indices, _ = A.getValuesCSR()
    if A.getComm().getSize() == 1:
        return indptr, indices, None, [len(indices)]
    start, end = A.getOwnershipRangeColumn()
    position, nd = storage_positions(indptr, indices, start, end)
    return indptr, indices, position, [nd, len(indices) - nd]


@contextmanager
def storage_values(A, sizes):
    """A's values in storage order as read-only views on its own arrays,
    one a block of ``sizes`` (``storage_pattern``), valid inside the
    ``with``."""
    if A.getComm().getSize() == 1:
        blocks = [A.handle]
    else:
        diagonal, off = ctypes.c_void_p(), ctypes.c_void_p()
        check(library().MatMPIAIJGetSeqAIJ(A.handle, ctypes.byref(diagonal),
                                           ctypes.byref(off), None),
              "MatMPIAIJGetSeqAIJ")
        blocks = [diagonal.value, off.value]
    with ExitStack() as stack:
        yield [stack.enter_context(seqaij_values(b, n)) for b, n in zip(blocks, sizes)]
