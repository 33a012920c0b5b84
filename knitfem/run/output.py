"""A run's output directory: the claim, the time series, checkpoints, summary.

    DIR/.knitfem.lock         the run that writes here (host, pid, start time)
    DIR/yarns.xdmf, yarns/    the time series (``io.CentrelineSeries``)
    DIR/tubes/                its frames as tube meshes (``io.TubeFrames``)
    DIR/checkpoint.h5         the newest checkpoint; checkpoint.prev.h5 the one before
    DIR/summary.json          what the run did
    DIR/*.png, *.gif          snapshots and animation (of this run only)

The directory is claimed before any file in it is opened: the lock file is
created atomically (a hard link of a complete temporary), so of two runs
started on one directory the second refuses in one line naming the first.
A lock left by a run that is gone (same host, pid no longer alive) is taken
over with a note. Every file is written under a unique temporary name and
renamed into place, so a run stopped at any instant leaves whole files.

A checkpoint holds what is needed to continue: the state (ε, ε̇), t, the
step, the counters, the rest-state measures, the snapshot frames, the
integrator's own state, and the problem's fingerprint (scene, sizes,
material, quadrature, integrator, dt, model, version). Its datasets carry
HDF5 Fletcher-32 checksums and its metadata the checksums of the HDF5 1.10
format; a restart compares the fingerprint with the new run's and refuses
any difference it was not told to accept. Rank 0 does the file work and
broadcasts the outcome, so every rank agrees on success or failure.
"""

import json
import os
import socket
import time

import numpy as np

from knitfem import io
from knitfem.errors import KnitError

__all__ = ["OutputDirectory", "OutputError", "Checkpoint", "FINGERPRINT_OPTIONS",
           "CHANGEABLE", "restart_command", "version"]

LOCK = ".knitfem.lock"
CHECKPOINT, PREVIOUS = "checkpoint.h5", "checkpoint.prev.h5"
FORMAT = 2

# fingerprint entry -> the option that sets it (for the one-line refusal)
FINGERPRINT_OPTIONS = {
    "scene": "-knit_scene", "model": "-knit_model", "rows": "-knit_rows",
    "cols": "-knit_cols",
    "radius": "-knit_radius", "tilt": "-knit_tilt", "length": "-knit_length",
    "span": "-knit_span", "segments": "-knit_segments", "lod": "-knit_lod",
    "rho": "-knit_rho", "EA": "-knit_EA", "EI": "-knit_EI",
    "gravity": "-knit_gravity", "damping": "-knit_damping",
    "quadrature": "-knit_quadrature", "sampling": "-knit_sampling",
    "integrator": "-knit_integrator", "dt": "-knit_dt",
    "unknowns": "the model size", "geometry": "the rest geometry "
    "(-knit_volume or the pattern)", "version": "the knitfem version"}


class OutputError(RuntimeError):
    """A file of the output directory could not be written (one line)."""


def version():
    """The installed knitfem version."""
    from importlib import metadata

    try:
        return metadata.version("knitfem")
    except metadata.PackageNotFoundError:
        return "unknown"


def _start_time(pid):
    """The start time of process ``pid`` in clock ticks since boot (Linux),
    None when unknown: tells a live run from a new process reusing its pid."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[19])
    except (OSError, IndexError, ValueError):
        return None


def _alive(owner):
    """Whether the run described by a lock's ``owner`` dict still runs here."""
    try:
        os.kill(owner["pid"], 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    start = _start_time(owner["pid"])
    return start is None or owner.get("start") in (None, start)


def _describe(owner):
    return (f"pid {owner.get('pid')} on {owner.get('host')}, started "
            f"{owner.get('time', '?')}: {owner.get('command', '?')}")


class OutputDirectory:
    """The output directory ``path`` of one run. Collective.

    ``claim()`` creates it and takes its lock (KnitError, exit 2, when it is
    not writable or another live run holds it); ``release()`` gives it back.
    ``rank0(fn)`` runs a file operation on rank 0 and raises the same
    OutputError on every rank if it fails.
    """

    def __init__(self, comm, path, command=""):
        self.comm, self.path, self.command = comm, path, command
        self.owner, self.note, self.me = None, "", None

    def file(self, name):
        return os.path.join(self.path, name)

    # -- the claim ----------------------------------------------------------
    def claim(self):
        """Create the directory, take its lock and remove temporaries a
        killed run left there (collective)."""
        if self.owner is not None:
            return self
        err = note = None
        try:
            if self.comm.rank == 0:
                try:
                    os.makedirs(self.path, exist_ok=True)
                    note = self._take()
                    for name in os.listdir(self.path):   # left by a run killed
                        if name.startswith(".") and ".tmp" in name:
                            os.remove(self.file(name))
                except KnitError as e:
                    err = str(e)
                except OSError as e:
                    err = (f"-o {self.path}: cannot write the output directory "
                           f"({e.strerror}); choose a writable directory with -o DIR")
            err, self.note = self.comm.tompi4py().bcast((err, note), root=0)
        except BaseException:            # a signal while claiming: our lock back
            self._remove_own_lock()
            raise
        if err:
            raise KnitError(err)
        self.owner = True
        return self

    def _take(self):
        """Rank 0: take the lock; returns a note when a stale one was taken over."""
        me = dict(host=socket.gethostname(), pid=os.getpid(),
                  start=_start_time(os.getpid()),
                  time=time.strftime("%Y-%m-%d %H:%M:%S"), command=self.command)
        lock = self.file(LOCK)

        def write(tmp):
            with open(tmp, "w") as f:
                json.dump(me, f)
                f.flush()
                os.fsync(f.fileno())

        tmp = self.file(f".lock.{me['host']}.{me['pid']}.tmp")
        self.me = me                     # ours once linked (``_remove_own_lock``)
        try:
            write(tmp)
            note = None
            for _ in range(2):
                try:
                    os.link(tmp, lock)
                    return note
                except FileExistsError:
                    note = self._stale(lock, me)
            raise KnitError(f"-o {self.path}: could not take the lock {lock}")
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)

    def _stale(self, lock, me):
        """The lock exists: refuse if its run lives (or cannot be checked),
        else move it aside atomically and return a note."""
        try:
            with open(lock) as f:
                owner = json.load(f)
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            owner = {}
        if owner.get("host") != me["host"] or _alive(owner):
            raise KnitError(
                f"-o {self.path}: another run writes there ({_describe(owner)}); "
                f"wait for it, choose another -o, or remove {lock} if that run "
                "is gone")
        aside = self.file(f".stale.{me['host']}.{me['pid']}.lock")
        os.replace(lock, aside)
        with open(aside) as f:
            moved = f.read()
        os.remove(aside)
        if json.loads(moved or "{}") != owner:      # another run took it meanwhile
            raise KnitError(f"-o {self.path}: another run has just taken it")
        return (f"note: took over {self.path} from a run that is gone "
                f"({_describe(owner)})")

    def release(self):
        """Give the directory back (collective; only our own lock is removed)."""
        if self.owner is None:
            return
        self.owner = None
        if self.comm.rank == 0:
            self._remove_own_lock()

    def _remove_own_lock(self):
        """Rank 0: remove the lock if it is this run's (another's stays)."""
        if self.me is None:
            return
        try:
            with open(self.file(LOCK)) as f:
                if json.load(f) == self.me:
                    os.remove(self.file(LOCK))
        except (OSError, ValueError):
            pass

    # -- rank-0 file work that every rank agrees on --------------------------
    def rank0(self, fn, *args):
        """``fn(*args)`` on rank 0; its OSError becomes one OutputError on
        every rank. Returns fn's result on rank 0, None elsewhere."""
        err = result = None
        if self.comm.rank == 0:
            try:
                result = fn(*args)
            except OutputError as e:
                err = str(e)
            except OSError as e:
                err = (f"cannot write {e.filename or self.path}: "
                       f"{e.strerror or str(e).splitlines()[0]}")
            except Exception as e:      # h5py raises some I/O errors as others
                err = f"cannot write in {self.path}: {type(e).__name__}: {e}"
        if self.comm.size > 1:
            err = self.comm.tompi4py().bcast(err, root=0)
        if err:
            raise OutputError(err)
        return result

    def remove(self, name):
        """Remove a file of the directory if it is there (rank 0)."""
        if os.path.exists(self.file(name)):
            os.remove(self.file(name))

    def remove_pictures(self):
        """Remove the PNG and GIF pictures an earlier run left here (rank 0),
        so that every picture in the directory is of the run now writing."""
        for name in os.listdir(self.path):
            if name.endswith((".png", ".gif")) and os.path.isfile(self.file(name)):
                os.remove(self.file(name))

    def write_json(self, name, rec):
        """A JSON file, atomically (rank 0)."""
        def write(tmp):
            with open(tmp, "w") as f:
                json.dump(rec, f, indent=1)

        self.rank0(io.atomic_write, self.file(name), write)

    # -- checkpoints ---------------------------------------------------------
    def write_checkpoint(self, ckpt):
        """Rank 0 keeps the previous checkpoint as checkpoint.prev.h5 (a hard
        link renamed into place) and writes ``ckpt`` to a temporary renamed
        over checkpoint.h5. A non-finite state is refused before anything is
        touched."""
        def write():
            if not (np.isfinite(ckpt.x).all() and np.isfinite(ckpt.v).all()):
                raise OutputError("the state is not finite; the last checkpoint "
                                  "is kept")
            path, prev = self.file(CHECKPOINT), self.file(PREVIOUS)
            # checkpoint.h5 never goes missing; both names are one file when a
            # run was killed between the two renames (rename would do nothing)
            if os.path.exists(path) and not (os.path.exists(prev)
                                             and os.path.samefile(path, prev)):
                io.atomic_write(prev, lambda tmp: os.link(path, tmp))
            io.atomic_write(path, ckpt.save)

        self.rank0(write)
        return self.file(CHECKPOINT)


class Checkpoint:
    """The contents of a checkpoint (rank 0 holds the arrays).

    x, v : all coordinates and velocities; t, step; stats : counters;
    fingerprint : dict; extra : dict of JSON values (rest-state measures,
    t origin, the integrator's ``state()``, whose numpy arrays come back as
    lists); frames : [(title, P)] snapshots, the yarns P (``Curves``) saved
    as their control points (N, 3) and loaded as those.
    """

    def __init__(self, x, v, t, step, fingerprint, stats, extra=None, frames=()):
        self.x, self.v, self.t, self.step = x, v, float(t), int(step)
        self.fingerprint, self.stats = dict(fingerprint), dict(stats)
        self.extra, self.frames = dict(extra or {}), list(frames)

    def save(self, path):
        def fill(f):
            for name, data in (("x", self.x), ("v", self.v)):
                f.create_dataset(name, data=data, fletcher32=True, chunks=True)
            for i, (title, P) in enumerate(self.frames):
                d = f.create_dataset(f"frames/{i}", data=np.asarray(P), fletcher32=True,
                                     chunks=True)
                d.attrs["title"] = title
            f.attrs.update(format=FORMAT, t=self.t, step=self.step,
                           fingerprint=json.dumps(self.fingerprint),
                           stats=json.dumps(self.stats),
                           extra=json.dumps(self.extra, default=_plain))

        io.write_hdf5(path, fill, libver="latest")

    @classmethod
    def load(cls, path):
        """Read and verify a checkpoint; KnitError (one line) when it cannot
        be trusted."""
        import h5py

        try:
            with h5py.File(path, "r") as f:
                if int(f.attrs.get("format", 1)) != FORMAT:
                    raise KnitError(f"-knit_restart {path}: written by an older "
                                    "knitfem without checksums or fingerprint; "
                                    "rerun from the start")
                x, v = f["x"][...], f["v"][...]
                frames = [(f["frames"][k].attrs["title"], f["frames"][k][...])
                          for k in sorted(f.get("frames", {}), key=int)]
                a = f.attrs
                ckpt = cls(x, v, a["t"], a["step"], json.loads(a["fingerprint"]),
                           json.loads(a["stats"]), json.loads(a["extra"]), frames)
        except KnitError:
            raise
        except FileNotFoundError:
            raise KnitError(f"-knit_restart {path}: no such file") from None
        except (OSError, KeyError, ValueError, TypeError) as err:
            why = str(err).split("(")[0].strip() or type(err).__name__
            raise KnitError(f"-knit_restart {path}: corrupt or not a knitfem "
                            f"checkpoint ({why}); use the one before, "
                            f"{os.path.join(os.path.dirname(path), PREVIOUS)}"
                            ) from None
        if not (np.isfinite(ckpt.x).all() and np.isfinite(ckpt.v).all()):
            raise KnitError(f"-knit_restart {path}: the state is not finite")
        return ckpt

    def compare(self, path, fingerprint, change=()):
        """Refuse (KnitError naming the option) any fingerprint entry that
        differs from this run's and is not in ``change``."""
        keys = set(self.fingerprint) | set(fingerprint)
        for key in [k for k in FINGERPRINT_OPTIONS if k in keys] + sorted(
                keys - set(FINGERPRINT_OPTIONS)):
            old, new = self.fingerprint.get(key), fingerprint.get(key)
            if old == new or key in change:
                continue
            hint = (f"; to change it deliberately add -knit_restart_change {key}"
                    if key in CHANGEABLE else "")
            raise KnitError(f"-knit_restart {path}: the checkpoint was written with "
                            f"{FINGERPRINT_OPTIONS.get(key, key)} {_show(old)}, this "
                            f"run has {_show(new)}; use the same value{hint}")


# what a restart may change on purpose (the state stays meaningful)
CHANGEABLE = ("dt", "integrator", "rho", "EA", "EI", "gravity", "damping",
              "quadrature", "sampling", "version")


def restart_command(argv, checkpoint, ranks=1):
    """The command line that continues a run from ``checkpoint``."""
    import shlex

    args, skip = [], False
    for a in argv[1:]:
        if skip:
            skip = False
        elif a in ("-knit_restart", "-knit_restart_change"):
            skip = True
        else:
            args.append(a)
    head = ["mpirun", "-n", str(ranks)] if ranks > 1 else []
    return shlex.join(head + ["knitfem"] + args + ["-knit_restart", checkpoint])


def _plain(value):
    """numpy arrays and scalars as JSON lists and numbers (exact: Python
    writes floats in their shortest round-trip form)."""
    return value.tolist()


def _show(value):
    if isinstance(value, list):
        return ",".join(map(str, value))
    return "(none)" if value is None else str(value)
