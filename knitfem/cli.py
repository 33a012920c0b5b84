"""knitfem command line: ``knitfem <command> [-knit_... options] [PETSc options]``.

Commands
  dofs      the unknowns table (paper, Figure 9), counted from assembled objects
  pattern   write a jersey's centrelines (VTU) and a PNG picture
  run       simulate a scene (full or reduced model), see ``knitfem run -help``
  deform    impose a deformation on the bounding volume and rebuild the yarns

PETSc reads the command line once, in ``main``, before anything imports
``petsc4py.PETSc``; a bad value of one of our options ends the program with a
one-line message and exit status 2.
"""

import sys

import petsc4py

COMMANDS = ("dofs", "pattern", "run", "deform")


def main(argv=None):
    argv = list(sys.argv if argv is None else argv)
    command = argv[1] if len(argv) > 1 and not argv[1].startswith("-") else None
    petsc4py.init([argv[0]] + argv[2 if command else 1:])
    from petsc4py import PETSc

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


if __name__ == "__main__":
    sys.exit(main())
