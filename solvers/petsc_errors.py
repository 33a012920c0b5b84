"""PETSc errors raised inside a solver, said in one line.

A PETSc error inside a step (a MUMPS factorisation out of workspace, a KSP
that did not converge under ``-ksp_error_if_not_converged`` …) arrives as a
``PETSc.Error`` whose text is PETSc's traceback. ``petsc_failure`` keeps the
solver's options prefix, PETSc's error code, the reason PETSc gives, and the
option to change.
"""

import re

from petsc4py import PETSc

__all__ = ["petsc_failure"]

# MUMPS INFOG(1) codes that more workspace (ICNTL(14)) cures
MUMPS_WORKSPACE = (-8, -9, -11, -12, -14, -15, -17, -20, -27)


def petsc_failure(err, prefix):
    """One line for a PETSc error raised inside the solver with options
    prefix ``prefix``: the solver, PETSc's error code and its reason, and the
    option to change."""
    text = str(err)
    lines = [re.sub(r"^\[\d+\]\s*", "", s).strip() for s in text.splitlines()]
    reason = next((s for s in reversed(lines) if s and "()" not in s
                   and not s.startswith("error code")), "")
    infog = re.search(r"INFOG\(1\)=(-?\d+)", text)
    p = f"-{prefix}"
    if infog and int(infog.group(1)) in MUMPS_WORKSPACE:
        icntl = PETSc.Options().getInt(f"{prefix}mat_mumps_icntl_14", 20)
        advice = f"raise {p}mat_mumps_icntl_14 (MUMPS workspace, now {icntl} %)"
    elif infog and int(infog.group(1)) in (-10, -6):
        advice = (f"the matrix is singular: check the constraints, or use "
                  f"{p}pc_factor_mat_solver_type superlu")
    elif infog and int(infog.group(1)) == -13:
        advice = "MUMPS ran out of memory: use more ranks or a smaller problem"
    else:
        advice = f"change {p}ksp_type / {p}pc_type, or a smaller -knit_dt"
    return (f"PETSc error {getattr(err, 'ierr', '?')} in the {p} solver "
            f"({reason or 'no reason given'}); {advice}")
