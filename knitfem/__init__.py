"""knitfem: yarn-level and reduced (mechanical level of detail) knitwear on PETSc.

One BLAS thread per MPI rank unless the environment says otherwise: the dense
products here are small, and ranks, not threads, share the cores.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
