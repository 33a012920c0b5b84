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

import ctypes

import numpy as np
from petsc4py import PETSc

__all__ = ["coo_matrix", "set_values"]

_LIB = None


def _library():
    """The PETSc library petsc4py runs on (already loaded in this process)."""
    global _LIB
    if _LIB is None:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "libpetsc" in line}
        if not paths:
            raise RuntimeError("the PETSc library is not loaded in this process")
        _LIB = ctypes.CDLL(sorted(paths)[0])
        _LIB.MatSetPreallocationCOO.argtypes = [ctypes.c_void_p, ctypes.c_int64,
                                                ctypes.c_void_p, ctypes.c_void_p]
        _LIB.MatSetValuesCOO.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
    return _LIB


def _check(code, call):
    if code:
        raise RuntimeError(f"{call} failed with PETSc error {code}")


def coo_matrix(comm, sizes, rows, cols, bsize=None):
    """An AIJ matrix of ``sizes`` ((local, global) rows and columns) whose
    entries are the global pairs (rows[k], cols[k]) given on this rank."""
    A = PETSc.Mat().create(comm=comm)
    A.setSizes(sizes, bsize=bsize)
    A.setType(PETSc.Mat.Type.AIJ)
    i = np.ascontiguousarray(rows, dtype=PETSc.IntType)
    j = np.ascontiguousarray(cols, dtype=PETSc.IntType)
    _check(_library().MatSetPreallocationCOO(A.handle, len(i), i.ctypes.data,
                                             j.ctypes.data), "MatSetPreallocationCOO")
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
    return A


def set_values(A, values):
    """The values of a ``coo_matrix``'s entries, in their order (summed where
    a pair repeats); A is assembled after, in a new state."""
    v = np.ascontiguousarray(values, dtype=PETSc.ScalarType)
    _check(_library().MatSetValuesCOO(A.handle, v.ctypes.data,
                                      int(PETSc.InsertMode.INSERT_VALUES)),
           "MatSetValuesCOO")
    A.assemble()
