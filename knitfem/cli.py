"""knitfem command line: ``knitfem <command> [-knit_... options] [PETSc options]``.

Commands
  dofs      the unknowns table (paper, Figure 9), counted from assembled objects
  pattern   write a jersey's centrelines (VTU) and a PNG picture
  run       simulate a scene (full or reduced model), see ``knitfem run -help``
  deform    impose a deformation on the bounding volume and rebuild the yarns

PETSc reads the command line once, in ``main``, before anything imports
``petsc4py.PETSc``. Every failure ends the program with one line and an
exit status: 2 bad input (an option, a checkpoint that does not match, an
output directory in use or not writable), 3 a simulation that failed, 130
and 143 SIGINT and SIGTERM. ``KNITFEM_TRACEBACK=1`` shows the traceback of
an unexpected error.
"""

import os
import sys

import petsc4py

COMMANDS = ("dofs", "pattern", "run", "deform")


def main(argv=None):
    argv = list(sys.argv if argv is None else argv)
    command = argv[1] if len(argv) > 1 and not argv[1].startswith("-") else None
    from .interrupts import Interrupted, install

    install()
    try:
        petsc4py.init([argv[0]] + argv[2 if command else 1:])
        return _command(command)
    except Interrupted as stop:
        if os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK", "0")) \
                == "0":
            print(f"knitfem {command}: {stop} during set-up, before any step",
                  flush=True)
        return stop.code


def _command(command):
    from petsc4py import PETSc

    from solvers.integrators import SimulationError

    from .options import KnitError

    if command not in COMMANDS:
        if PETSc.Options().hasName("help") or command is None:
            PETSc.Sys.Print(__doc__)
            return 0 if command is None else 2
        PETSc.Sys.Print(f"knitfem: error: unknown command {command!r}: use one of "
                        + ", ".join(COMMANDS))
        return 2
    from . import commands

    try:
        return getattr(commands, command)(PETSc.COMM_WORLD) or 0
    except KnitError as err:
        PETSc.Sys.Print(f"knitfem {command}: error: {err}")
        return 2
    except (SimulationError, PETSc.Error, OSError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        PETSc.Sys.Print(f"knitfem {command}: error: {type(err).__name__}: {first}")
        return 3
    except Exception as err:
        if os.environ.get("KNITFEM_TRACEBACK"):
            raise
        PETSc.Sys.Print(f"knitfem {command}: internal error: {type(err).__name__}: "
                        f"{err} (KNITFEM_TRACEBACK=1 shows where)")
        return 1


if __name__ == "__main__":
    sys.exit(main())
