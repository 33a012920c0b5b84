"""knitfem command line: ``knitfem <command> [-knit_... options] [PETSc options]``.

PETSc reads the command line once, in ``main``, before anything imports
``petsc4py.PETSc``. ``-help`` (or ``-h``, ``--help``) is kept from PETSc, so
that it prints our options only and the command stops before it runs. Every
failure ends the program with one line on stderr and an exit status: 2 bad
input (an option's value, an option of ours that no command declares, a
checkpoint that does not match, an output directory in use or not
writable), 3 a simulation that failed, 130 and 143 SIGINT and SIGTERM (under
``mpirun`` the exit status is Open MPI's: see ``knitfem.run.interrupts``). A
PETSc option that nothing read gets a warning at the end.
``KNITFEM_TRACEBACK=1`` shows the traceback of an unexpected error.
"""

import os
import sys

import petsc4py

COMMANDS = ("dofs", "pattern", "relax", "run", "deform")
HELP = ("-help", "-h", "--help")

USAGE = """\
usage: knitfem <command> [-knit_... options] [PETSc options]

commands (each one's options: knitfem <command> -help)
  dofs      the unknowns table (paper, Figure 9), counted from assembled objects
              knitfem dofs -knit_rows 15 -knit_cols 30 -knit_lod 5,5
  pattern   write a jersey's (or a tube's) centrelines (VTU) and a PNG picture
              knitfem pattern -knit_rows 7 -knit_cols 7 -o out/pattern
              knitfem pattern -knit_shape tube -knit_rows 10 -knit_cols 16 -o out/tube
  relax     relax a knit from its template: a straight yarn bent into its loops
              knitfem relax -knit_rows 12 -knit_cols 12 -o out/relax
  run       simulate a scene with the full or reduced model, or its statics
              knitfem run -knit_scene hanging -knit_model reduced -o out/hanging
  deform    impose a deformation on the bounding volume and rebuild the yarns
              knitfem deform -knit_mode torsion -knit_amount 90 -o out/torsion

in parallel: mpirun -n 2 knitfem run -knit_rows 15 -knit_cols 30"""


def complain(message):
    """One line on stderr, from the first rank only."""
    if os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK", "0")) == "0":
        print(message, file=sys.stderr, flush=True)


def main(argv=None):
    argv = list(sys.argv if argv is None else argv)
    command = argv[1] if len(argv) > 1 and not argv[1].startswith("-") else None
    rest = argv[2 if command else 1:]
    wants_help = any(a in HELP for a in rest)
    from knitfem.run.interrupts import Interrupted, install

    install(say=lambda line: _say(f"knitfem {command}: {line}"))
    try:
        petsc4py.init([argv[0]] + [a for a in rest if a not in HELP])
        return _command(command, wants_help)
    except Interrupted as stop:
        if not stop.said:
            complain(f"knitfem {command}: {stop} during set-up, before any step")
        return stop.code


def _say(line):
    """One line on stdout from the first rank, flushed (PETSc is initialised)."""
    from petsc4py import PETSc

    PETSc.Sys.Print(line)
    sys.stdout.flush()


def _command(command, wants_help):
    from petsc4py import PETSc

    from solvers.integrators import SimulationError

    from knitfem.cli.options import OURS, KnitError, KnitOptions, unused_options

    if command is None:
        PETSc.Sys.Print(USAGE)
        return 0
    if command not in COMMANDS:
        complain(f"knitfem: error: unknown command {command!r}: use one of "
                 f"{', '.join(COMMANDS)} (knitfem --help shows them)")
        return 2
    KnitOptions.help = wants_help
    given = set(PETSc.Options().getAll())        # the user's, before any default
    from knitfem.cli import commands

    try:
        status = getattr(commands, command)(PETSc.COMM_WORLD) or 0
    except KnitError as err:
        complain(f"knitfem {command}: error: {err}")
        return 2
    except (SimulationError, PETSc.Error, OSError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        name = "" if isinstance(err, SimulationError) else f"{type(err).__name__}: "
        complain(f"knitfem {command}: error: {name}{first}")
        return 3
    except Exception as err:
        if os.environ.get("KNITFEM_TRACEBACK"):
            raise
        complain(f"knitfem {command}: internal error: {type(err).__name__}: "
                 f"{err} (KNITFEM_TRACEBACK=1 shows where)")
        return 1
    if status == 0 and not wants_help:
        left = [k for k in unused_options() if k in given and not k.startswith(OURS)]
        if left:
            complain(f"knitfem {command}: warning: PETSc option(s) not used "
                     f"(misspelt?): {' '.join('-' + k for k in left)}{prefix_hint(left)}")
    return status


def prefix_hint(names):
    """For solver options given without a prefix, the prefixed name: knitfem's
    solvers read -full_, -reduced_, -mixed_ and -static_ options only."""
    bare = [k for k in names if k.startswith(("snes_", "ksp_", "pc_", "mat_"))]
    if not bare:
        return ""
    return (f"; solvers read their model's prefix: -full_{bare[0]} (or -reduced_, "
            f"-mixed_, -static_)")

