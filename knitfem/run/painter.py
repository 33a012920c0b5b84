"""A run's pictures, drawn in a worker process beside the stepping.

    painter = Painter()                     # rank 0: python -m knitfem.run.painter
    painter.submit("draw", path, P, radius, title=...)   # returns at once
    painter.finish()                        # waits; raises the first job's error

The worker imports matplotlib as soon as it starts (while the run sets up),
then reads jobs from a socket, each a pickle of (name, args, kwargs) of a
drawing function of ``knitfem.io``, and runs them in order on its own core.
After a job fails it runs no more (as when the pictures were drawn in line);
when the run closes its end it answers with one pickle, the first job's
exception or None, and exits; it also exits, after the jobs it has, when
the run has gone. It is fork+exec (``subprocess``), safe after MPI_Init,
and imports neither MPI nor PETSc. It ignores SIGINT and SIGTERM, which the
terminal's process group (or a batch system) sends it with the run: the run
stops at its next Newton iteration or step, and its close waits for the
pictures, or kills the worker when it stops at once.
"""

import os
import pickle
import signal
import socket
import subprocess
import sys

__all__ = ["Painter"]

STOPS = {signal.SIGINT, signal.SIGTERM}


class Painter:
    """The worker process that draws the pictures (call on rank 0 only).

    Jobs and the answer go over a socket pair: a send to a worker that has
    died is an error here (MSG_NOSIGNAL), not a SIGPIPE, which PETSc's signal
    handler would turn into a crash."""

    def __init__(self):
        here = os.path.dirname(os.path.dirname(os.path.dirname(
            os.path.abspath(__file__))))
        path = os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH")) if p)
        self.sock, theirs = socket.socketpair()
        # the worker starts with the stop signals blocked, until it ignores them
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, STOPS)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "knitfem.run.painter", str(theirs.fileno())],
                pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL,
                env=dict(os.environ, PYTHONPATH=path))
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            theirs.close()
        self.paths = []

    def submit(self, name, path, *args, **kwargs):
        """Queue ``io.<name>(path, *args, **kwargs)``; returns at once (or when
        the socket has room). A worker that has died is reported by ``finish``."""
        self.paths.append(path)
        job = pickle.dumps((name, (path,) + args, kwargs), pickle.HIGHEST_PROTOCOL)
        try:
            self.sock.sendall(job, socket.MSG_NOSIGNAL)
        except OSError:
            pass

    def finish(self):
        """Wait until every picture is drawn; raise the first job's error, or
        an OutputError when the worker died. The worker is gone afterwards,
        also when the wait is interrupted."""
        try:
            answer = b""
            try:
                self.sock.shutdown(socket.SHUT_WR)
                while chunk := self.sock.recv(1 << 16):
                    answer += chunk
                error = pickle.loads(answer)
            except (OSError, EOFError, pickle.UnpicklingError):
                error = self._died()
        finally:
            self.stop()
        if error is not None:
            raise error

    def _died(self):
        from knitfem.run.output import OutputError

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
        self.sock.close()


def _portable(error):
    """``error`` if it survives a pickle round trip, else a RuntimeError
    that names it."""
    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:
        return RuntimeError(f"{type(error).__name__}: {error}")


def main(fd):
    """The worker: draw every job read from socket ``fd``, then answer on it."""
    for sig in STOPS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)
    os.nice(19)              # a core the ranks leave idle; never one they use
    from knitfem import io

    try:
        io._pyplot()                     # the import, while the run sets up
    except Exception:
        pass                             # the first picture fails the same way
    error = None
    with socket.socket(fileno=fd) as sock, sock.makefile("rb") as jobs:
        while True:
            try:
                name, args, kwargs = pickle.load(jobs)
            except EOFError:
                break
            if error is None:
                try:
                    getattr(io, name)(*args, **kwargs)
                except Exception as e:
                    error = e
        try:
            sock.sendall(pickle.dumps(_portable(error)))
        except OSError:                  # the run has gone
            pass


if __name__ == "__main__":
    main(int(sys.argv[1]))
