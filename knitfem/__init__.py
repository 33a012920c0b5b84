"""knitfem: yarn-level and reduced (mechanical level of detail) knitwear on PETSc.

One BLAS thread per MPI rank unless the environment says otherwise: the dense
products here are small, and ranks, not threads, share the cores. When every
rank is on this machine (an MPI singleton, or mpirun's ranks all local),
Open MPI's ob1 messaging over shared memory is used unless told otherwise:
probing UCX costs a singleton 0.2 s of start-up (MPI_Init 0.33 s against
0.13 s) and two ranks on two cores 0.3 s (the 40×80 step: 3.9 against
3.6 s). Across machines (or under another launcher) Open MPI chooses.
"""

import os


def _all_ranks_local(env):
    """No other machine takes part: a singleton, or mpirun's ranks all here."""
    if "OMPI_COMM_WORLD_SIZE" in env:
        return env.get("OMPI_COMM_WORLD_LOCAL_SIZE") == env["OMPI_COMM_WORLD_SIZE"]
    return "PMIX_RANK" not in env


os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if _all_ranks_local(os.environ):
    os.environ.setdefault("OMPI_MCA_pml", "ob1")
