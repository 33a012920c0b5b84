"""A run's pictures, drawn in a worker process beside the stepping.

    painter = Painter()                     # rank 0: python -m knitfem.painter
    painter.submit("draw", path, P, radius, title=...)   # returns at once
    painter.finish()                        # waits; raises the first job's error

The worker imports matplotlib as soon as it starts (while the run sets up),
then reads jobs from its stdin, each a pickle of (name, args, kwargs) of a
drawing function of ``knitfem.io``, and runs them in order on its own core.
After a job fails it runs no more (as when the pictures were drawn in line);
when its stdin closes it writes back one pickle, the first job's exception
or None, and exits. It is fork+exec (``subprocess``), safe after MPI_Init,
and imports neither MPI nor PETSc. It ignores SIGINT and SIGTERM, which the
terminal's process group (or a batch system) sends it with the run: the run
finishes its step, and its close waits for the pictures, or kills the
worker when it stops at once.
"""

import os
import pickle
import signal
import subprocess
import sys

__all__ = ["Painter"]


class Painter:
    """The worker process that draws the pictures (call on rank 0 only)."""

    def __init__(self):
        here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        path = os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p)
        self.proc = subprocess.Popen([sys.executable, "-m", "knitfem.painter"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     env=dict(os.environ, PYTHONPATH=path))
        self.paths = []

    def submit(self, name, path, *args, **kwargs):
        """Queue ``io.<name>(path, *args, **kwargs)``; returns at once (or when
        the pipe has room). A worker that has died is reported by ``finish``."""
        self.paths.append(path)
        try:
            pickle.dump((name, (path,) + args, kwargs), self.proc.stdin,
                        protocol=pickle.HIGHEST_PROTOCOL)
            self.proc.stdin.flush()
        except BrokenPipeError:
            pass

    def finish(self):
        """Wait until every picture is drawn; raise the first job's error, or
        an OutputError when the worker died. The worker is gone afterwards,
        also when the wait is interrupted."""
        try:
            try:
                self.proc.stdin.close()
            except BrokenPipeError:
                pass
            try:
                error = pickle.load(self.proc.stdout)
            except (EOFError, pickle.UnpicklingError):
                error = self._died()
        finally:
            self.stop()
        if error is not None:
            raise error

    def _died(self):
        from .output import OutputError

        code = self.proc.wait()
        how = (f"was killed by {signal.Signals(-code).name}" if code < 0
               else f"exited with status {code}")
        where = os.path.dirname(os.path.abspath(self.paths[0])) if self.paths else "."
        return OutputError(f"the picture worker (pid {self.proc.pid}) {how} before "
                           f"it finished; pictures in {where} may be missing")

    def stop(self):
        """End the worker now if it still runs (idempotent)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        for pipe in (self.proc.stdin, self.proc.stdout):
            try:
                pipe.close()
            except BrokenPipeError:
                pass


def _portable(error):
    """``error`` if it survives a pickle round trip, else a RuntimeError
    that names it."""
    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:
        return RuntimeError(f"{type(error).__name__}: {error}")


def main():
    """The worker: draw every job read from stdin, then report on stdout."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    from . import io

    error = None
    try:
        io._pyplot()                     # the import, while the run sets up
    except Exception as e:
        error = e
    while True:
        try:
            name, args, kwargs = pickle.load(sys.stdin.buffer)
        except EOFError:
            break
        if error is None:
            try:
                getattr(io, name)(*args, **kwargs)
            except Exception as e:
                error = e
    try:
        os.write(sys.stdout.fileno(), pickle.dumps(_portable(error)))
    except BrokenPipeError:
        pass


if __name__ == "__main__":
    main()
