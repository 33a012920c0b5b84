"""Tests run serial and under mpirun: PETSc is initialised without pytest's
arguments, and every test ends with garbage collection and a barrier."""

import gc
import sys

import petsc4py

petsc4py.init(sys.argv[:1] + ["-skip_petscrc"])

import pytest  # noqa: E402
from mpi4py import MPI  # noqa: E402


@pytest.fixture(autouse=True)
def collective_cleanup():
    yield
    gc.collect()
    MPI.COMM_WORLD.Barrier()
