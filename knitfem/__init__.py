"""knitfem: yarn-level and reduced (mechanical level of detail) knitwear on PETSc.

One BLAS thread per MPI rank unless the environment says otherwise: the dense
products here are small, and ranks, not threads, share the cores. A process
not started by mpirun (an MPI singleton) uses Open MPI's ob1 messaging
unless told otherwise: probing UCX for a single process costs 0.2 s of
start-up (0.33 s against 0.13 s for MPI_Init) and can carry no message.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if not {"OMPI_COMM_WORLD_SIZE", "PMIX_RANK"} & set(os.environ):
    os.environ.setdefault("OMPI_MCA_pml", "ob1")
