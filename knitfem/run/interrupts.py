"""SIGINT (Ctrl-C) and SIGTERM (what batch systems send first).

During set-up a signal ends the run at once (``Interrupted``, exit 128 +
signal number: 130, 143). While a run steps, it is held: the step finishes,
every rank learns of it at the step's check (one reduction), and the run
writes a final checkpoint and its summary before it stops. A second signal
stops at once (the files stay whole: each is renamed into place).
"""

import signal

__all__ = ["Interrupted", "install", "hold", "pending"]


class Interrupted(BaseException):
    """The run was stopped by a signal; ``code`` is the exit status."""

    def __init__(self, signum, message=""):
        super().__init__(message or f"interrupted by {signal.Signals(signum).name}")
        self.signum, self.code = signum, 128 + signum


_state = {"held": False, "pending": 0}


def _handler(signum, frame):
    if _state["held"] and not _state["pending"]:
        _state["pending"] = signum
        return
    raise Interrupted(signum)         # set-up, or a second signal: stop now


def install():
    """Route SIGINT and SIGTERM to ``Interrupted`` (main thread only)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _handler)


def hold(on):
    """Hold signals (while stepping) or let them raise again."""
    _state["held"] = bool(on)


def pending():
    """The signal number received while held (0: none)."""
    return _state["pending"]
