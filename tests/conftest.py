"""Tests run serial and under mpirun: PETSc is initialised without pytest's
arguments, every test ends with garbage collection and a barrier, and
nothing is cached in the user's home."""

import gc
import os
import sys

import petsc4py

# Under pytest-xdist the workers inherit the environment that MPI_Init of the
# controller (which reads this file too) left: its singleton's PMIx server
# and Open MPI's job variables. Each worker is a singleton of its own, and an
# mpirun a test starts would take itself for part of that job and fail.
SINGLETON = ("PMIX_", "ORTE_", "OMPI_MCA_orte_", "OMPI_MCA_ess", "OMPI_MCA_pmix",
             "OMPI_APP_CTX_NUM_PROCS", "OMPI_ARGV", "OMPI_COMMAND")
if "PYTEST_XDIST_WORKER" in os.environ:
    for key in [k for k in os.environ if k.startswith(SINGLETON)]:
        del os.environ[key]

petsc4py.init(sys.argv[:1] + ["-skip_petscrc"])

import pytest  # noqa: E402
from mpi4py import MPI  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def cache_in_a_tmp_dir(tmp_path_factory):
    """XDG_CACHE_HOME (the sampled sets' cache) in the session's tmp dir, one
    a rank, for the tests and the knitfem processes they start: never the
    user's ~/.cache."""
    os.environ["XDG_CACHE_HOME"] = str(
        tmp_path_factory.mktemp(f"cache{MPI.COMM_WORLD.rank}"))


@pytest.fixture(autouse=True)
def collective_cleanup():
    yield
    gc.collect()
    MPI.COMM_WORLD.Barrier()


@pytest.hookimpl(trylast=True)
def pytest_configure(config):
    """Under mpirun only rank 0 reports, without colour codes (every rank
    runs every test, and the exit status still reflects each rank's
    failures)."""
    if MPI.COMM_WORLD.size > 1:
        config.get_terminal_writer().hasmarkup = False
    if MPI.COMM_WORLD.rank > 0:
        reporter = config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            config.pluginmanager.unregister(reporter)
