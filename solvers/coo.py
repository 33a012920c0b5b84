"""PETSc's COO assembly, which petsc4py 3.18 does not wrap.

MatSetPreallocationCOO fixes a matrix's entries as a list of (row, column)
pairs in global numbering; rows may belong to other ranks (their values are
sent there) and repeated pairs are summed. MatSetValuesCOO then takes the
values in that order in one call, with the communication planned once.
That is what a Newton matrix with a fixed pattern needs on several ranks:
[A Cᵀ; C 0] is written from the values of A and C as they are, Cᵀ's entries
being C's sent to the rows they land in (no MatTranspose, no setValuesCSR
row by row).
"""

import numpy as np
from petsc4py import PETSc

from .libpetsc import check, library

__all__ = ["coo_matrix", "set_values"]


def coo_matrix(comm, sizes, rows, cols, bsize=None):
    """An AIJ matrix of ``sizes`` ((local, global) rows and columns) whose
    entries are the global pairs (rows[k], cols[k]) given on this rank."""
    A = PETSc.Mat().create(comm=comm)
    A.setSizes(sizes, bsize=bsize)
    A.setType(PETSc.Mat.Type.AIJ)
    i = np.ascontiguousarray(rows, dtype=PETSc.IntType)
    j = np.ascontiguousarray(cols, dtype=PETSc.IntType)
    check(library().MatSetPreallocationCOO(A.handle, len(i), i.ctypes.data,
                                           j.ctypes.data), "MatSetPreallocationCOO")
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
    return A


def set_values(A, values):
    """The values of a ``coo_matrix``'s entries, in their order (summed where
    a pair repeats); A is assembled after, in a new state."""
    v = np.ascontiguousarray(values, dtype=PETSc.ScalarType)
    check(library().MatSetValuesCOO(A.handle, v.ctypes.data,
                                    int(PETSc.InsertMode.INSERT_VALUES)),
          "MatSetValuesCOO")
    A.assemble()
