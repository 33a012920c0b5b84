"""What a long step is doing, said while it does it.

A step that is retried (Newton failed and the step is shortened, or its
error was too large) or whose factorisation runs out of MUMPS workspace and
is done again with more calls ``note``; whoever drives the steps
(``knitfem.run.simulation``) listens and decides what to print. Collective
in the sense that every rank notes the same retries.
"""

__all__ = ["note", "listen"]

_listener = [None]


def listen(fn):
    """Have ``fn(message, always)`` hear the notes (None: nobody); returns
    the listener it replaces."""
    old, _listener[0] = _listener[0], fn
    return old


def note(message, always=False):
    """Say ``message``: a retry (``always`` False: worth a line only in a
    step that already takes long) or a workspace increase (always)."""
    if _listener[0] is not None:
        _listener[0](message, always)
