"""SIGINT (Ctrl-C) and SIGTERM (what batch systems send first).

During set-up a signal ends the run at once (``Interrupted``, exit 128 +
signal number: 130, 143). While a run steps, it is held: every rank learns
of it at the next Newton iteration (``solvers.halting``: one reduction each),
which abandons the step in progress (a step without Newton, the explicit
integrator's, finishes, and it is heard at the step's check), and the run
writes a final checkpoint of the last accepted step, says so in one line
(``announce``, at once: the run's last pictures may still be drawn after it)
and writes its summary before it stops. A second signal stops at once (the
files stay whole: each is renamed into place).

Under ``mpirun`` the signal reaches mpirun, which sends SIGTERM to every rank
and SIGKILL one second later (Open MPI's ``odls_base_sigkill_timeout``): the
line and the summary come first so they are out within that second. The exit
status is then mpirun's own (Open MPI's), not 130 or 143.
"""

import signal

__all__ = ["Interrupted", "install", "hold", "pending", "announce"]


class Interrupted(BaseException):
    """The run was stopped by a signal; ``code`` is the exit status."""

    def __init__(self, signum, message=""):
        super().__init__(message or f"interrupted by {signal.Signals(signum).name}")
        self.signum, self.code = signum, 128 + signum
        self.said = False             # its line is printed (``announce``)


_state = {"held": False, "pending": 0, "say": None}


def _handler(signum, frame):
    if _state["held"] and not _state["pending"]:
        _state["pending"] = signum
        return
    raise Interrupted(signum)         # set-up, or a second signal: stop now


def install(say=None):
    """Route SIGINT and SIGTERM to ``Interrupted`` (main thread only), none
    pending; ``say`` prints an interruption's one line (``announce``)."""
    _state["say"], _state["pending"] = say, 0
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _handler)


def hold(on):
    """Hold signals (while stepping) or let them raise again."""
    _state["held"] = bool(on)


def pending():
    """The signal number received while held (0: none)."""
    return _state["pending"]


def announce(stop):
    """Print ``stop``'s line now with the ``say`` given to ``install`` (every
    rank calls it; ``say`` prints once), and mark it said."""
    if _state["say"] is not None and not stop.said:
        _state["say"](str(stop))
        stop.said = True
