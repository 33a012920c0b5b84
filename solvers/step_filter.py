"""A step filter on Newton's updates: a line-search pre-check that scales
the update so that the new iterate keeps a condition the system states (the
yarn contact's: no two yarn surfaces touch).

PETSc's Newton takes X ← X − λY with the update Y; SNESLineSearchSetPreCheck
lets a callback change Y before the line search. petsc4py 3.18 does not
wrap it, so it is set through the C library (``libpetsc``), the callback a
ctypes function that sees X and Y as numpy arrays on their own storage.
"""

import ctypes

import numpy as np

from .libpetsc import Int, check, library

__all__ = ["set_step_filter"]

_PRECHECK = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p,
                             ctypes.c_void_p, ctypes.POINTER(ctypes.c_int),
                             ctypes.c_void_p)


def _array(vec, read):
    """(local array of a Vec handle on its storage, pointer to restore)."""
    lib, ptr, n = library(), ctypes.c_void_p(), Int()
    check(lib.VecGetLocalSize(ctypes.c_void_p(vec), ctypes.byref(n)), "VecGetLocalSize")
    get = lib.VecGetArrayRead if read else lib.VecGetArray
    check(get(ctypes.c_void_p(vec), ctypes.byref(ptr)), "VecGetArray")
    if not n.value:
        return np.empty(0), ptr
    return np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(ctypes.c_double)),
                                 shape=(n.value,)), ptr


def set_step_filter(snes, fraction):
    """Scale every Newton update Y of ``snes`` by t = ``fraction(x, y)``
    (local arrays of the iterate X and of Y; collective, t ∈ [0, 1], the same
    on every rank) when t < 1. Returns the ctypes callback, which the caller
    keeps as long as ``snes`` (PETSc holds only its address)."""
    lib = library()
    ls = ctypes.c_void_p()
    check(lib.SNESGetLineSearch(ctypes.c_void_p(snes.handle), ctypes.byref(ls)),
          "SNESGetLineSearch")

    def precheck(_, X, Y, changed, ctx):
        try:
            x, px = _array(X, True)
            y, py = _array(Y, False)
            try:
                t = fraction(x, y)
                if t < 1.0:
                    y *= t
                    changed[0] = 1
            finally:
                lib.VecRestoreArrayRead(ctypes.c_void_p(X), ctypes.byref(px))
                lib.VecRestoreArray(ctypes.c_void_p(Y), ctypes.byref(py))
        except Exception as err:           # noqa: BLE001 (reported to PETSc)
            precheck.error = err
            return 1
        return 0

    callback = _PRECHECK(precheck)
    check(lib.SNESLineSearchSetPreCheck(ls, callback, None),
          "SNESLineSearchSetPreCheck")
    return callback
