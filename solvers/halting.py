"""A request to stop, heard inside a step.

Whoever drives the steps (``knitfem.run.simulation``) installs ``ask``, a
collective function that returns the number of a signal any rank received
(0: none). Newton's convergence test (``integrators.step_convergence``)
asks at every iteration and ends the solve when one came; the integrator
then raises ``Halted``: the step in progress is abandoned, and the state is
that of the last accepted step. A step of many Newton iterations thus
answers within one iteration, not at its end (under ``mpirun``, Open MPI
kills the ranks one second after it forwards the signal).
"""

__all__ = ["Halted", "ask_with", "requested", "halt_if_requested"]

_ask = [None]
_heard = [0]


class Halted(BaseException):
    """The step in progress was abandoned for the signal ``signum``
    (a BaseException: no retry of the step catches it)."""

    def __init__(self, signum):
        super().__init__(f"the step was abandoned for signal {signum}")
        self.signum = signum


def ask_with(fn):
    """Have Newton ask ``fn()`` (collective) at every iteration (None: nobody
    asks); returns the function it replaces."""
    old, _ask[0] = _ask[0], fn
    _heard[0] = 0
    return old


def requested():
    """The signal to stop for, asked of the installed function (collective
    when one is installed; 0 when none is)."""
    if _ask[0] is not None:
        _heard[0] = _heard[0] or int(_ask[0]())
    return _heard[0]


def halt_if_requested():
    """Raise ``Halted`` when the last ``requested`` heard a signal (every rank
    heard the same: no communication)."""
    if _heard[0]:
        raise Halted(_heard[0])
