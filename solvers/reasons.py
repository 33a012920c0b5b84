"""PETSc converged reasons by name (DIVERGED_MAX_IT), for messages."""

__all__ = ["reason_name"]


def reason_name(solver):
    """The name of a SNES, KSP or TS converged reason, e.g. ``DIVERGED_MAX_IT``."""
    value = solver.getConvergedReason()
    names = [k for k, v in vars(type(solver).ConvergedReason).items()
             if v == value and not k.startswith("_")]
    return names[-1] if names else str(value)


def solve_failure(snes, err):
    """One line for a SNES solve that raised: the KSP's reason by name when a
    linear solve failed (KSPs here stop on -ksp_error_if_not_converged),
    else the last line of PETSc's message."""
    ksp = snes.getKSP()
    if ksp.getConvergedReason() < 0:
        return (f"linear solve failed ({reason_name(ksp)} after "
                f"{ksp.getIterationNumber()} iterations)")
    lines = [s.strip() for s in str(err).splitlines() if s.strip()]
    return lines[-1] if lines else type(err).__name__
