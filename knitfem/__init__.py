"""knitfem: yarn-level and reduced (mechanical level of detail) knitwear on PETSc.

The public Python API is ``__all__`` (``knitfem.api`` and the classes it
returns); each name is imported on first use, so that ``import knitfem``
imports no PETSc and a program may call ``petsc4py.init(argv)`` after it.

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

_PUBLIC = {
    "jersey": "knitfem.api", "scene": "knitfem.api", "material": "knitfem.api",
    "full_model": "knitfem.api",
    "reduced_model": "knitfem.api", "mixed_model": "knitfem.api",
    "integrator": "knitfem.api", "simulation": "knitfem.api",
    "start": "knitfem.api", "advance": "knitfem.api",
    "equilibrium": "knitfem.api", "control_points": "knitfem.api",
    "centrelines": "knitfem.api", "picture": "knitfem.api",
    "Jersey": "knitfem.knit.pattern", "Fabric": "knitfem.knit.fabric",
    "Material": "knitfem.model.full", "Simulation": "knitfem.run.simulation",
    "KnitError": "knitfem.errors", "SimulationError": "solvers.integrators",
}
"""Each public name and the module that defines it, imported on first use
(none is the name of a subpackage, which importing it would shadow)."""

__all__ = sorted(_PUBLIC)


def __getattr__(name):
    """The public names on first use: importing them imports PETSc, which the
    command line must initialise with its options first (``petsc4py.init``)."""
    if name not in _PUBLIC:
        raise AttributeError(f"module 'knitfem' has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
