"""PETSc converged reasons by name (DIVERGED_MAX_IT), for messages."""

__all__ = ["reason_name"]


def reason_name(solver):
    """The name of a SNES, KSP or TS converged reason, e.g. ``DIVERGED_MAX_IT``."""
    value = solver.getConvergedReason()
    names = [k for k, v in vars(type(solver).ConvergedReason).items()
             if v == value and not k.startswith("_")]
    return names[-1] if names else str(value)

