"""PETSc's C library, for the few calls petsc4py 3.18 does not wrap.

``library()`` opens it through petsc4py's own extension module (dlsym then
finds every PETSc symbol among that module's dependencies), so it is the
library petsc4py runs on, whatever its path.
"""

import ctypes
from contextlib import contextmanager

import numpy as np
from petsc4py import PETSc

__all__ = ["library", "Int", "check", "seqaij_values", "line_search",
           "line_search_type", "set_line_search", "line_search_lambda"]

Int = ctypes.c_int64 if np.dtype(PETSc.IntType).itemsize == 8 else ctypes.c_int32

_LIB = None


def library():
    """PETSc's C library (opened once)."""
    global _LIB
    if _LIB is None:
        _LIB = ctypes.CDLL(PETSc.__file__)
        for name in ("MatSeqAIJGetArrayRead", "MatSeqAIJRestoreArrayRead"):
            getattr(_LIB, name).argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        _LIB.MatMPIAIJGetSeqAIJ.argtypes = [ctypes.c_void_p] * 4
    return _LIB


def check(code, call):
    """Raise if a PETSc call returned an error code."""
    if code:
        raise RuntimeError(f"{call} failed with PETSc error {code}")


@contextmanager
def seqaij_values(handle, nnz):
    """The ``nnz`` values of a sequential AIJ matrix (its C handle) as a
    read-only array on its own storage (MatSeqAIJGetArrayRead;
    ``getValuesCSR`` copies the whole CSR), valid inside the ``with``."""
    lib, ptr = library(), ctypes.c_void_p()
    check(lib.MatSeqAIJGetArrayRead(handle, ctypes.byref(ptr)),
          "MatSeqAIJGetArrayRead")
    try:
        values = np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(ctypes.c_double)),
                                       shape=(nnz,)) if nnz else np.empty(0)
        values.flags.writeable = False
        yield values
    finally:
        check(lib.MatSeqAIJRestoreArrayRead(handle, ctypes.byref(ptr)),
              "MatSeqAIJRestoreArrayRead")


def _line_search(snes):
    """The C handle of the line search of ``snes`` (SNESGetLineSearch)."""
    ls = ctypes.c_void_p()
    check(library().SNESGetLineSearch(ctypes.c_void_p(snes.handle), ctypes.byref(ls)),
          "SNESGetLineSearch")
    return ls


def set_line_search(snes, kind):
    """Make ``kind`` the line search of ``snes`` (SNESLineSearchSetType);
    before ``setFromOptions``, -<prefix>snes_linesearch_type overrides it."""
    check(library().SNESLineSearchSetType(_line_search(snes), kind.encode()),
          "SNESLineSearchSetType")


def line_search_lambda(snes):
    """The step length λ of the last line search of ``snes``
    (SNESLineSearchGetLambda): the update it took is λ times Newton's."""
    lam = ctypes.c_double()
    check(library().SNESLineSearchGetLambda(_line_search(snes), ctypes.byref(lam)),
          "SNESLineSearchGetLambda")
    return lam.value


def line_search_type(snes):
    """The type of the line search of ``snes`` (SNESLineSearchGetType)."""
    name = ctypes.c_char_p()
    check(library().SNESLineSearchGetType(_line_search(snes), ctypes.byref(name)),
          "SNESLineSearchGetType")
    return name.value.decode()


@contextmanager
def line_search(snes, kind):
    """The line search of ``snes`` of the type ``kind`` inside the ``with``,
    its own type and options back after it. A pre-check belongs to the
    line search object, not to its type, and stays."""
    lib, ls, own = library(), _line_search(snes), line_search_type(snes).encode()
    check(lib.SNESLineSearchSetType(ls, kind.encode()), "SNESLineSearchSetType")
    try:
        yield
    finally:
        check(lib.SNESLineSearchSetType(ls, own), "SNESLineSearchSetType")
        check(lib.SNESLineSearchSetFromOptions(ls), "SNESLineSearchSetFromOptions")
