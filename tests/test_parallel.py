"""Distributed by whole yarns: matrices under mpirun -n P equal one rank's."""

import numpy as np
import pytest
import scipy.sparse as sp
from petsc4py import PETSc

from knitfem.model import FullModel, Material
from knitfem.pattern import Jersey, jersey_fabric


def local_rows_equal(A, ref):
    """A's local rows (global columns) equal the same rows of the serial ref."""
    lo, hi = A.getOwnershipRange()
    indptr, indices, values = A.getValuesCSR()
    mine = sp.csr_matrix((values, indices, indptr), shape=(hi - lo, A.getSize()[1]))
    indptr, indices, values = ref.getValuesCSR()
    full = sp.csr_matrix((values, indices, indptr), shape=ref.getSize())
    return abs(mine - full[lo:hi]).max() <= 1e-15 * abs(full).max()


@pytest.fixture(scope="module")
def models():
    fab = jersey_fabric(Jersey(5, 3), hold_top=True)
    par = FullModel(PETSc.COMM_WORLD, fab, Material())
    ser = FullModel(PETSc.COMM_SELF, fab, Material())
    yield par, ser
    par.destroy()
    ser.destroy()


@pytest.mark.parametrize("name", ["m", "M", "c", "C"])
def test_matrix_equals_serial(models, name):
    par, ser = models
    A, R = getattr(par, name), getattr(ser, name)
    assert A.getSize() == R.getSize()
    ok = par.comm.tompi4py().allreduce(local_rows_equal(A, R), op=min)
    assert ok


def test_constraint_rhs_and_gravity_equal_serial(models):
    par, ser = models
    for a, b in ((par.d, ser.d), (par.Qg, ser.Qg)):
        lo, hi = a.getOwnershipRange()
        assert np.array_equal(a.getArray(), b.getArray()[lo:hi])


def test_whole_yarns_per_rank(models):
    par, _ = models
    lay = par.layout
    lo, hi = par.M.getOwnershipRange()
    assert (lo, hi) == (3 * lay.cp_start, 3 * lay.cp_end)
    assert lay.cp_start % lay.ncp_per_yarn == 0
