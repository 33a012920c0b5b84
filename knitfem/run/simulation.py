"""Time stepping driver: output, checkpoints, failure detection, summary.

    while t < t_end:  (ε, ε̇), h ← integrator.step(t, ε, ε̇, t_stop);  t ← t + h

The integrator chooses the step h (fixed, or by its error control) and lands
exactly on t_stop, the next snapshot time or t_end. Every ``output_every``
steps the driver prints a progress line (step, t, dt, Newton/KSP iterations,
rejected steps, energies, constraint violation), appends the yarn
centrelines to the time series and, at the requested snapshot times, has a
PNG drawn (by ``painter.Painter``, a worker process on rank 0, while the
stepping goes on); every ``checkpoint_every`` steps it writes a checkpoint.
The files are the business of ``output.OutputDirectory``; the driver only
calls it.

Every step ends with one cheap collective check (the state finite, the
constraint drift |g(ε)| within ``drift_tol``, no stop signal pending), so a
failure is reported at the step where it happened and a bad state never
reaches a checkpoint. A failure stops the run with one line naming the step,
the time and the quantity (``SimulationError``); a PETSc error inside a step
names the solver, the error and the option to change; SIGINT/SIGTERM finish
the step, write a final checkpoint and the summary, and raise
``interrupts.Interrupted``. Everything written so far stays on disk.
"""

import os
import sys
import time

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from solvers import halting
from solvers import progress as step_notes
from solvers.integrators import SimulationError
from solvers.petsc_errors import petsc_failure
from solvers.saddle import WORKSPACE_RAISED

from knitfem.contact.gaps import YarnGaps
from knitfem.contact.motion import moving
from knitfem.yarn import bspline
from knitfem.run import interrupts
from knitfem import io
from knitfem.run import output
from knitfem.run.painter import Painter

__all__ = ["Simulation", "SimulationError"]

EV_GAPS = PETSc.Log.Event("knitYarnGaps")
EV_OUTPUT = PETSc.Log.Event("knitOutput")
EV_CHECKPOINT = PETSc.Log.Event("knitCheckpoint")


def sag_below_supports(fabric, P, low):
    """How far the lowest point ``low`` hangs below the lowest held point
    (m), for the yarns P (``Curves``); None when nothing is held."""
    yarns, s = fabric.fixed
    if not len(yarns):
        return None
    return float(P.at(yarns, s)[:, 1].min() - low[1])


class Simulation:
    """Drive a mechanical system with an integrator. Collective.

    Parameters
    ----------
    system : FullModel or ReducedModel
    integrator : solvers.integrators.SymplecticEuler or BackwardEuler
    out : str, output.OutputDirectory or None
        Output directory (None: write nothing). A path is claimed here and
        released by ``close``; a directory object stays its owner's.
    problem : dict
        The problem's description (scene, sizes, material …); completed by
        ``fingerprint`` it is what a checkpoint must agree on.
    command : list of str
        The command line, to print how to continue after an interrupt.
    painter : painter.Painter or None
        Rank 0: the worker that draws the pictures, started early by the
        caller (its matplotlib import then overlaps the set-up); one is
        started at the first picture otherwise. ``close`` finishes it.
    series : str
        File name of the XDMF series of the yarns in the output directory.
    settled : callable or None
        Of the energies of an output frame (``energies``): True ends the run
        there, before t_end (a relaxation that has come to rest).
    slow_step : float
        Seconds into a step after which its retries get a progress line
        (``heard``; 0: every retry). More MUMPS workspace always gets one.
    report : dict
        The scene's own entries in the summary (e.g. the sleeve's elbow angle).
    tubes : str
        A format of ``io.TUBE_FORMATS``: every output frame also as a
        triangle mesh of the yarns' tubes, DIR/tubes/<step>.<format> ("":
        none).
    """

    def __init__(self, system, integrator, out=None, scene="", output_every=10,
                 snapshots=(), drift_tol=1e-6, checkpoint_every=0, verbose=True,
                 view="oblique", problem=None, command=None, adapt=None,
                 animation="", energy_growth=0.5, stall_steps=100, painter=None,
                 series="yarns.xdmf", settled=None, slow_step=5.0, report=None,
                 tubes=""):
        self.system, self.integrator, self.scene = system, integrator, scene
        self.comm = system.comm
        self.output = out
        if isinstance(out, str):
            self.output = output.OutputDirectory(self.comm, out).claim()
        self.own_output = isinstance(out, str)
        self.out = self.output.path if self.output else None
        self.problem, self.command = dict(problem or {}), command or sys.argv
        self.report = dict(report or {})    # the scene's own words in the summary
        self.output_every, self.snapshots = max(1, output_every), sorted(snapshots)
        self.drift_tol, self.checkpoint_every = drift_tol, checkpoint_every
        self.energy_growth, self.stall_steps = energy_growth, stall_steps
        self.verbose, self.view, self.animation = verbose, view, animation
        self.slow_step, self.step_start = slow_step, None
        self.adapt = adapt          # called after every step (knitfem.lod.adapt)
        self.series_name, self.settled = series, settled
        self.x, self.v = system.start_state(), system.start_state()
        self.v.zeroEntries()
        self.t, self.step_count = 0.0, 0
        self.stats = {"newton": 0, "ksp": 0, "rejected": 0, "linear_failures": 0}
        self.steps_taken = []            # dt of every accepted step
        self.energy = []                 # (t, kinetic, elastic + gravity)
        self.energy_seen = None          # check_energy's summary of them
        self.series, self.series_from = None, None
        self.tubes, self.tube_frames = tubes, None
        self.restarted_from, self.last_checkpoint = None, None
        self.full = getattr(system, "full", system)
        self.bodies = tuple(self.full.fabric.bodies)
        self.body_series = None
        self.min_collider = np.inf
        self.weights = self.full.m.createVecLeft()
        one = self.full.m.createVecRight()
        one.set(1.0)
        self.full.m.mult(one, self.weights)
        self.total_mass = self.weights.sum()
        self.eps = self.full.M.createVecLeft()
        self.r = system.C.createVecLeft()
        self.rf = self.full.C.createVecLeft()
        self.Mv = system.M.createVecLeft()
        self.frames, self.movie = [], []
        self.painter = painter
        self.initial_lowest = None
        self.rest_measures()
        self.problem = self.fingerprint()

    def rest_measures(self):
        """Lowest point of the initial (rest) state; the yarn gaps' arclength
        from its centrelines (rank 0)."""
        _, pts = self.geometry()
        self.gaps = None
        if self.comm.rank == 0:
            self.initial_lowest = float(pts.points[:, 1].min())
            self.gaps = YarnGaps(pts, self.full.fabric.radius)

    def fingerprint(self):
        """What a checkpoint must agree on to be continued by this run: the
        problem's description, the model, integrator, dt, size, a digest of
        the rest geometry and the version (collective)."""
        import hashlib

        rest = self.system.gather_points(self.system.rest_state())
        digest = hashlib.sha256(np.ascontiguousarray(rest).tobytes()).hexdigest() \
            if rest is not None else None
        c = getattr(self.integrator, "control", None)
        dt = f"adaptive, rtol {c.rtol:g}, atol {c.atol:g}" \
            if c is not None and c.adaptive else self.integrator.dt
        sampling = {}
        if self.system.kind == "reduced":          # the sampled set or every element
            rep = getattr(self.system, "sampling", None) or {}
            sampling["sampling"] = [rep.get("kind", "exact"), rep.get("tol")]
        return dict(self.problem, **sampling, model=self.system.kind,
                    integrator=self.integrator.name, dt=dt,
                    unknowns=self.x.getSize(), version=output.version(),
                    geometry=self.comm.tompi4py().bcast(digest, root=0)[:16])

    # -- measures ------------------------------------------------------------
    def centroid(self, eps):
        """Mass-weighted centroid Σ_i (m 1)_i p_i / Σ m (collective)."""
        w = self.weights.getArray(readonly=True)
        p = eps.getArray(readonly=True).reshape(-1, 3)
        c = self.comm.tompi4py().allreduce(w @ p)
        return c / self.total_mass

    def energies(self):
        """What every progress line shows (collective): kinetic, elastic (and
        barrier) and gravity energy, ``|C q − d|``, and the smallest distance to
        a body so far; only the reduced state, but for the bodies."""
        s = self.system
        s.M.mult(self.v, self.Mv)
        kinetic = 0.5 * self.v.dot(self.Mv)
        elastic = s.elastic_energy(self.x)
        potential = -s.Qg.dot(self.x)
        s.constraint_residual(self.x, self.r)
        bodies = {}
        if self.full.barrier is not None:        # the smallest over the frames
            eps = s.full_state(self.x, self.eps)
            self.min_collider = min(self.min_collider,
                                    self.full.min_collider_distance(eps))
            bodies = dict(min_collider_distance=self.min_collider)
        return dict(**bodies, kinetic_energy=kinetic, elastic_energy=elastic,
                    gravity_energy=potential,
                    total_energy=kinetic + elastic + potential,
                    max_constraint_violation=self.r.norm(PETSc.NormType.INFINITY))

    def measures(self):
        """The energies, and the yarn-level contact residuals, strain and
        centroid (collective)."""
        s, mpi = self.system, self.comm.tompi4py()
        m = self.energies()
        eps = s.full_state(self.x, self.eps)
        self.full.constraint_residual(eps, self.rf)
        strain = s.strain(self.x)
        max_strain = mpi.allreduce(np.abs(strain).max() if strain.size else 0.0,
                                   op=__import__("mpi4py").MPI.MAX)
        return dict(m, max_contact_residual=self.rf.norm(PETSc.NormType.INFINITY),
                    max_strain=max_strain, centroid=self.centroid(eps).tolist())

    def geometry(self):
        """Rank 0: the yarns (``Curves``) and their sampled centrelines."""
        P = self.system.gather_points(self.x)
        return (P, io.centrelines(P)) if P is not None else (None, None)

    def control_points(self):
        """Rank 0: the yarns (``Curves``) (collective)."""
        return self.system.gather_points(self.x)

    # -- output --------------------------------------------------------------
    def posed(self, t=None):
        """The bodies where they are now, or at time ``t`` (a moving one as
        its posed body)."""
        return tuple((b.body if t is None else b.body_at(t)) if moving(b) else b
                     for b in self.bodies)

    @property
    def moving(self):
        """Whether a body moves (it works on the knit)."""
        return any(map(moving, self.bodies))

    def _path(self, name):
        return os.path.join(self.out, name)

    def write_output(self, P):
        """A frame of the time series, and the snapshots now due (every rank
        drops them from its list; rank 0 writes and has their PNGs drawn,
        measures the frame's yarn gap, and every rank learns of an I/O
        failure)."""
        due = []
        while self.snapshots and self.t >= self.snapshots[0] - 1e-9:
            due.append(self.snapshots.pop(0))
        if self.output is None:
            return
        if self.comm.rank == 0:
            for ts in due:
                self.draw_snapshot(f"t = {ts:g} s", P)
            with EV_GAPS:
                self.gaps.add(self.t, io.centrelines(P))
        self.output.rank0(self._write_frame, P)

    def paint(self, name, *args, **kwargs):
        """Have ``io.<name>(*args, **kwargs)`` drawn by the painter (rank 0;
        started here if the caller gave none)."""
        if self.painter is None:
            self.painter = Painter()
        self.painter.submit(name, *args, **kwargs)

    def draw_snapshot(self, title, P):
        """Keep a snapshot for the panel and have its PNG drawn (rank 0), the
        bodies as they were at its time (title: "t = 0.4 s")."""
        when = title.split()[2]
        bodies = self.posed(float(when))
        self.frames.append((title, P, bodies))
        self.paint("draw", self._path(f"{self.scene}_t{when}s.png"), P,
                   self.full.fabric.radius, view=self.view, bodies=bodies,
                   title=f"{self.scene}, {self.system.kind} model, {title}")

    def _write_frame(self, P):
        if self.series is None:
            keep, note = self.series_from or (None, "")
            self.series = io.CentrelineSeries(self._path(self.series_name), P,
                                              self.full.fabric.radius, keep, note)
            if self.bodies:                  # for ParaView, beside the yarns
                size = float(np.ptp(P.points, axis=0).max())
                io.write_bodies(self._path("bodies.vtu"), self.posed(), size)
                self.body_series = io.BodySeries(self._path("bodies.xdmf"),
                                                 self.posed(), size, keep, note)
            if self.tubes:                   # for renderers, beside the yarns
                self.tube_frames = io.TubeFrames(
                    self._path("tubes"), self.tubes, self.full.fabric.closed,
                    self.full.fabric.radius, keep)
            else:
                io.TubeFrames.remove(self._path("tubes"), keep)
        self.series.write(self.step_count, self.t, P)
        if self.tube_frames is not None:
            self.tube_frames.write(self.step_count, P)
        if self.body_series is not None:
            self.body_series.write(self.step_count, self.t, self.posed())
        if self.animation:
            self.movie.append((self.t, P, self.posed()))

    def write_panels(self):
        """The pictures still to draw, once the stepping is over: the
        snapshots side by side in one PNG in one scale that fits them all,
        and the animation of the output frames; returns when the painter
        has drawn every picture (its failure is an OutputError on every
        rank)."""
        if self.output is None:
            return
        self.output.rank0(self._write_panels)
        self.frames, self.movie = [], []

    def _write_panels(self):
        if self.frames:
            titles, frames, bodies = zip(*self.frames)
            self.paint("draw_panels", self._path(f"{self.scene}_snapshots.png"),
                       frames, self.full.fabric.radius, titles, view=self.view,
                       bodies=bodies)
        if len(self.movie) > 1:
            times, frames, bodies = zip(*self.movie)
            self.paint("animate", self._path(self.animation), times, frames,
                       self.full.fabric.radius, view=self.view, bodies=bodies,
                       title=f"{self.scene}, {self.system.kind} model")
        if self.painter is not None:
            painter, self.painter = self.painter, None
            painter.finish()

    def checkpoint(self):
        """Write a checkpoint of everything needed to continue (collective);
        returns its path."""
        with EV_CHECKPOINT:
            return self._checkpoint()

    def _checkpoint(self):
        mpi = self.comm.tompi4py()
        xs = mpi.gather(self.x.getArray(readonly=True), root=0)
        vs = mpi.gather(self.v.getArray(readonly=True), root=0)
        # an integrator's own state (same on every rank), e.g. its step size
        # the integrator's own state: each rank's part of its arrays, gathered
        state = {k: mpi.gather(np.atleast_1d(a), root=0) if np.ndim(a) else a
                 for k, a in self.integrator.state().items()}
        if self.comm.rank == 0:
            state = {k: np.concatenate(a) if isinstance(a, list) else a
                     for k, a in state.items()}
        extra = dict(initial_lowest=self.initial_lowest, integrator=state,
                     steps_taken=self.steps_taken, energy=self.energy,
                     restarted_from=self.restarted_from,
                     min_yarn_gap=self.gaps and (self.gaps.smallest, self.gaps.time),
                     sliding=self.full.constraints.sliding_parameters(),
                     yarn_contact=self.full.contact_state())
        ckpt = output.Checkpoint(np.concatenate(xs), np.concatenate(vs), self.t,
                                 self.step_count, self.problem, self.stats,
                                 extra, [f[:2] for f in self.frames]) \
            if self.comm.rank == 0 else None
        path = self.output.write_checkpoint(ckpt)
        self.last_checkpoint = (path, self.step_count)
        return path

    def restart(self, path, change=()):
        """Continue from a checkpoint written by ``checkpoint`` (collective).

        The checkpoint's fingerprint must equal this run's except for the
        entries in ``change`` (KnitError otherwise). A changed dt keeps t
        continuous. Into the checkpoint's own directory the time series keeps
        its frames up to the checkpoint and goes on; elsewhere a new series
        notes where it continues from.
        """
        from knitfem.errors import KnitError

        mine = self.problem
        err = ckpt = None
        if self.comm.rank == 0:
            try:
                ckpt = output.Checkpoint.load(path)
                ckpt.compare(path, mine, change)
            except KnitError as e:
                err = str(e)
        mpi = self.comm.tompi4py()
        err = mpi.bcast(err, root=0)
        if err:
            raise KnitError(err)
        ckpt = mpi.bcast(ckpt, root=0)
        # one step from rest, thrown away, makes the solver's choices that
        # depend on the first matrix (MUMPS's analysis: pivot order, scaling)
        # those of the uninterrupted run, so the restart continues bit-exactly
        # (if that step fails, as after a change of dt it may, so be it)
        x, v = self.x.copy(), self.v.copy()
        try:
            self.integrator.step(0.0, x, v)
        except (SimulationError, PETSc.Error):
            pass
        x.destroy()
        v.destroy()
        lo, hi = self.x.getOwnershipRange()
        self.x.getArray()[:], self.v.getArray()[:] = ckpt.x[lo:hi], ckpt.v[lo:hi]
        self.t, self.step_count = ckpt.t, ckpt.step
        if ckpt.extra.get("sliding") is not None:     # where crossings had slid
            self.full.set_sliding_parameters(ckpt.extra["sliding"])
        if self.full is self.system:          # the yarn contact's pairs and list
            self.full.set_contact_state(ckpt.extra.get("yarn_contact"))
        self.stats.update(ckpt.stats)
        self.frames = []
        if self.comm.rank == 0 and self.output is not None:   # drawn again
            fabric = self.full.fabric
            for title, P in ckpt.frames:
                self.draw_snapshot(title, fabric.curves(fabric.X).moved(P))
        extra = ckpt.extra
        self.initial_lowest = extra.get("initial_lowest", self.initial_lowest)
        self.steps_taken = list(extra.get("steps_taken", []))
        self.energy = [tuple(e) for e in extra.get("energy", [])]
        self.energy_seen = None
        same = [ckpt.fingerprint.get(k) == mine[k] for k in ("integrator", "dt")]
        if extra.get("integrator") and all(same):       # else it starts afresh
            self.integrator.set_state(self.local_parts(extra["integrator"]))
        self.restarted_from = [os.path.abspath(path), ckpt.step, ckpt.t]
        self.snapshots = [s for s in self.snapshots if s > self.t + 1e-9]
        same = self.out and os.path.realpath(os.path.dirname(os.path.abspath(path))) \
            == os.path.realpath(self.out)
        self.series_from = (ckpt.step, "") if same else (
            None, f"continues {path} (step {ckpt.step}, t = {ckpt.t:g} s)")
        if same and self.gaps and extra.get("min_yarn_gap"):   # the series' frames
            self.gaps.smallest, self.gaps.time = extra["min_yarn_gap"]

    def local_parts(self, saved):
        """This rank's slices of gathered integrator state arrays (the local
        sizes are those of the integrator's own ``state()``)."""
        mpi, out = self.comm.tompi4py(), {}
        for k, a in self.integrator.state().items():
            lo = mpi.exscan(len(a) if np.ndim(a) else 0) or 0
            out[k] = np.asarray(saved[k])[lo:lo + len(a)] if np.ndim(a) else saved[k]
        return out

    def progress(self, m):
        """One line: step, t, running totals of Newton and KSP iterations,
        energies, drift, wall time so far and the time left at this pace."""
        if self.verbose:
            elapsed = time.perf_counter() - self.clock[0]
            done = (self.t - self.clock[1]) / (self.clock[2] - self.clock[1])
            left = elapsed * (1 - done) / done if done > 0 else float("nan")
            dt = self.steps_taken[-1] if self.steps_taken else self.integrator.dt
            PETSc.Sys.Print(
                f"step {self.step_count:6d}  t {self.t:.4f} s  dt {dt:.2e} s  total "
                f"its: newton {self.stats['newton']:5d} ksp {self.stats['ksp']:5d} "
                f"rejected {self.stats['rejected']:3d}{self.linear_note()}  E_kin "
                f"{m['kinetic_energy']:.3e} J  E_el {m['elastic_energy']:.3e} J  "
                f"|Cx-d| {m['max_constraint_violation']:.1e} m  elapsed "
                f"{elapsed:.1f} s, left ~{left:.1f} s", comm=self.comm)

    def heard(self, message, always):
        """A note from inside the step in progress (``solvers.progress``): a
        line when the step already takes ``slow_step`` seconds, or always."""
        elapsed = time.perf_counter() - self.step_start
        if self.verbose and (always or elapsed >= self.slow_step):
            PETSc.Sys.Print(f"step {self.step_count + 1:6d}  t {self.t:.4f} s  in "
                            f"progress for {elapsed:.1f} s: {message}", comm=self.comm)

    def linear_note(self):
        """`` (N linear solves failed)`` in the progress line, when some did."""
        n = self.stats["linear_failures"]
        return f" (linear solves failed: {n})" if n else ""

    # -- the loop ------------------------------------------------------------
    def guard(self):
        """After every step, one reduction (collective): raise SimulationError
        if the state is not finite or |g(ε)| exceeds ``drift_tol``; return
        the stop signal any rank received (0: none)."""
        s = self.system
        x, v = self.x.getArray(readonly=True), self.v.getArray(readonly=True)
        bad = not (np.isfinite(x).all() and np.isfinite(v).all())
        drift = 0.0
        if not bad:
            s.constraint_residual(self.x, self.r)
            r = self.r.getArray(readonly=True)
            drift = float(np.abs(r).max()) if r.size else 0.0
        flags = np.array([float(bad), drift, float(interrupts.pending())])
        self.comm.tompi4py().Allreduce(MPI.IN_PLACE, flags, op=MPI.MAX)
        bad, drift, signum = flags
        if bad or not np.isfinite(drift):
            raise SimulationError("the state is not finite (NaN or inf)")
        if drift > self.drift_tol:
            raise SimulationError(f"constraint drift {drift:.3e} m exceeds "
                                  f"-knit_drift_tol {self.drift_tol:g}")
        return int(signum)

    def signal_anywhere(self):
        """The stop signal any rank received (0: none; collective): asked at
        every Newton iteration of a step (``solvers.halting``)."""
        if self.comm.size == 1:
            return interrupts.pending()
        return self.comm.tompi4py().allreduce(interrupts.pending(), op=MPI.MAX)

    def after_step(self, signum):
        """Checkpoint when due; on a stop signal a final checkpoint, its line
        with the restart command (``interrupts.announce``), the summary marked
        interrupted, and ``Interrupted`` (collective)."""
        due = self.checkpoint_every and self.step_count % self.checkpoint_every == 0
        if self.output is not None and (due or signum):
            self.checkpoint()
        if not signum:
            return
        name = interrupts.Interrupted(signum).args[0].split()[-1]
        self.wall_time = time.perf_counter() - self.start
        where = f"step {self.step_count}, t = {self.t:.6g} s"
        if self.output is None:
            stop = interrupts.Interrupted(signum, f"interrupted by {name} at {where}; "
                                          "no output directory, nothing to restart")
        else:
            path = self.last_checkpoint[0]
            stop = interrupts.Interrupted(
                signum, f"interrupted by {name} at {where}; checkpoint {path}; "
                f"continue with: "
                f"{output.restart_command(self.command, path, self.comm.size)}")
        interrupts.announce(stop)            # before mpirun's SIGKILL can come
        self.write_summary(self.summary(), f"interrupted by {name}")
        raise stop

    def solver_prefix(self):
        for name in ("snes", "ksp"):
            obj = getattr(self.integrator, name, None)
            if obj is not None:
                return obj.getOptionsPrefix() or ""
        return ""

    def failure(self, err):
        """The one-line SimulationError for ``err`` at the step in progress."""
        if isinstance(err, PETSc.Error):
            err = petsc_failure(err, self.solver_prefix())
        kept = "" if self.last_checkpoint is None else (
            f"; last checkpoint {self.last_checkpoint[0]} (step "
            f"{self.last_checkpoint[1]})")
        return SimulationError(f"step {self.at[0]}, t = {self.at[1]:.6g} s: "
                               f"{err}{kept}")

    def run(self, t_end):
        """Integrate to t_end. Returns the summary dict; raises SimulationError
        (one line: step, time, quantity) or interrupts.Interrupted."""
        self.start = time.perf_counter()
        self.at = (self.step_count, self.t)
        tiny = 1e-12 * max(1.0, abs(t_end))
        if not self.energy:
            self.record_energy(self.energies())
        stage = PETSc.Log.Stage("Time stepping")
        interrupts.hold(True)
        try:
            if self.step_count == 0:
                if self.output is not None:     # nothing of an earlier run
                    self.output.rank0(self.output.remove, "summary.json")
                    self.output.rank0(self.output.remove_pictures)
                self.write_output(self.control_points())
            # wall_time_s: the stepping, after the start's measures and frame
            start = self.start = time.perf_counter()
            self.clock = (start, self.t, t_end)
            while self.t < t_end - tiny:
                stop = t_end
                if self.snapshots and self.t < self.snapshots[0] - tiny:
                    stop = min(stop, self.snapshots[0])
                self.at = (self.step_count + 1, min(stop, self.t + self.integrator.dt))
                stage.push()
                self.step_start = time.perf_counter()
                heard = step_notes.listen(self.heard)
                asked = halting.ask_with(self.signal_anywhere)
                try:
                    st = self.integrator.step(self.t, self.x, self.v, stop)
                except halting.Halted as halted:    # (x, v) still the last step's
                    self.after_step(halted.signum)
                finally:
                    halting.ask_with(asked)
                    step_notes.listen(heard)
                    stage.pop()
                self.step_count += 1
                landed = abs(self.t + st["dt"] - stop) <= tiny
                self.t = stop if landed else self.t + st["dt"]
                self.steps_taken.append(st["dt"])
                for k in self.stats:
                    self.stats[k] += st[k]
                if self.adapt is not None:
                    self.adapt(self)
                signum = self.guard()
                last = self.t >= t_end - tiny
                snap = self.snapshots and self.t >= self.snapshots[0] - 1e-9
                if self.step_count % self.output_every == 0 or last or snap:
                    with EV_OUTPUT:
                        m = self.energies()
                        self.record_energy(m)
                        self.progress(m)
                        self.write_output(self.control_points())
                    self.check_energy()
                    if self.settled is not None and self.settled(m):
                        break
                self.check_pace(t_end)
                self.after_step(signum)
            self.wall_time = time.perf_counter() - start
            summary = self.summary()
            self.write_summary(summary, "completed")
        except (SimulationError, output.OutputError, PETSc.Error) as err:
            failure = self.failure(err)
            self.write_summary(dict(steps=self.step_count, t_end=self.t,
                                    newton_iterations=self.stats["newton"],
                                    ksp_iterations=self.stats["ksp"]),
                               f"failed: {failure}", quiet=True)
            raise failure from None
        finally:
            interrupts.hold(False)
            self.close()
        return summary

    def record_energy(self, m):
        """Keep (t, kinetic, elastic + gravity energy) of a progress point."""
        self.energy.append((self.t, m["kinetic_energy"],
                            m["elastic_energy"] + m["gravity_energy"]))

    def check_energy(self):
        """Raise SimulationError when the total energy E = T + V (elastic,
        barrier, gravity and loads: all conservative) has grown above its
        lowest so far by more than ``energy_growth`` times the energy scale
        of the motion, the larger of the highest kinetic energy and the
        potential energy released at earlier progress points. Damping only
        takes energy away, so growth is the integrator's (a generalized-α
        step feeding unresolved stiff modes, say). Bodies that move work on
        the knit: no check then."""
        if not self.energy_growth or len(self.energy) < 3 or self.moving:
            return
        # (points seen, lowest total, highest kinetic, lowest potential) of the
        # earlier points, brought up to date with the new ones only
        seen, low, kin_max, pot_min = self.energy_seen or (0, np.inf, 0.0, np.inf)
        for _, kin, pot in self.energy[seen:-1]:
            low, kin_max, pot_min = min(low, kin + pot), max(kin_max, kin), min(pot_min, pot)
        self.energy_seen = (len(self.energy) - 1, low, kin_max, pot_min)
        _, kin, pot = self.energy[-1]
        total, low = kin + pot, min(low, kin + pot)
        scale = max(kin_max, self.energy[0][2] - pot_min)
        grown = total - low
        if scale > 0 and grown > self.energy_growth * scale:
            raise SimulationError(
                f"the total energy grew by {grown:.3g} J (from {low:.3g} to "
                f"{total:.3g} J) with no source, {grown / scale:.3g} times the "
                f"motion's energy {scale:.3g} J: the integrator is unstable here "
                f"(-knit_energy_growth {self.energy_growth:g}; try -knit_integrator "
                f"bdf2)", curable=False)

    def check_pace(self, t_end):
        """Raise SimulationError when the last ``stall_steps`` accepted steps
        of an error-controlled run were all shorter than 1e-5 of the
        simulated time: the run crawls (a fixed -knit_dt is the user's)."""
        control = getattr(self.integrator, "control", None)
        if control is None or not control.adaptive:
            return
        n = self.stall_steps
        taken = self.steps_taken[-n:]
        if n and len(taken) == n and max(taken) < 1e-5 * t_end:
            raise SimulationError(
                f"the step has stayed below {max(taken):.2g} s for {n} steps, "
                f"{(t_end - self.t) / max(taken):.2g} more to go at this pace: the "
                f"run crawls (-knit_stall_steps {n})", curable=False)

    def energy_record(self):
        """Total energy E = T + E_el + E_g over the run and its drift
        E(t_end) − E(0), absolute (J) and over the largest kinetic energy
        (None where nothing moved: a relaxation's pseudo-time)."""
        t, kin, pot = np.array(self.energy).T
        total = kin + pot
        drift = float(total[-1] - total[0])
        return dict(energy_drift=drift,
                    energy_drift_relative=drift / kin.max() if kin.max() > 0 else None,
                    energy_history=dict(t=t.tolist(), kinetic=kin.tolist(),
                                        total=total.tolist()))

    def summary(self):
        m = self.measures()
        P, pts = self.geometry()
        s = self.system
        taken = np.array(self.steps_taken or [self.integrator.dt])
        control = getattr(self.integrator, "control", None)
        rec = dict(scene=self.scene, model=s.kind,
                   integrator=self.integrator.name, steps=self.step_count,
                   dt_next=self.integrator.dt, dt_min=float(taken.min()),
                   dt_max=float(taken.max()),
                   adaptive=bool(control is not None and control.adaptive),
                   rejected_steps=self.stats["rejected"],
                   linear_failures=self.stats["linear_failures"],
                   mumps_workspace_raised=dict(WORKSPACE_RAISED),
                   t_end=self.t, wall_time_s=self.wall_time,
                   unknowns=s.M.getSize()[0] + s.C.getSize()[0], ranks=self.comm.size,
                   yarn_control_points=len(self.full.fabric.X),
                   newton_iterations=self.stats["newton"],
                   ksp_iterations=self.stats["ksp"], **self.report, **m,
                   **self.full.slide_report(self.eps))
        if rec["adaptive"]:
            rec.update(rtol=control.rtol, atol=control.atol)
        if getattr(s, "sampling", None):
            rec["sampling"] = s.sampling
        if getattr(s, "yarn_contact", None) is not None:
            rec.update(yarn_contact_pattern_rebuilds=s.pattern_rebuilds,
                       yarn_contact_missed_entries=s.yarn_contact.missed)
        if self.energy:
            rec.update(self.energy_record())
        if self.comm.rank == 0:
            flat = pts.points
            low = flat[np.argmin(flat[:, 1])]
            if self.bodies:
                rec["bodies"] = [b.geometry() for b in self.posed()]
                centre = self.posed()[0]
                centre = getattr(centre, "centre", getattr(centre, "a", None))
                if centre is not None:
                    rec["lowest_point_below_collider_centre"] = float(centre[1] - low[1])
            if self.gaps.time is None:          # no frame (a static solve)
                self.gaps.add(self.t, pts)
            rec.update(self.gaps.record())
            rec.update(lowest_point=low.tolist(),
                       drop=float(self.initial_lowest - low[1]),
                       sag=sag_below_supports(self.system.fabric, P, low),
                       tip=P.at([0], P.nseg[:1])[0].tolist())
        return self.comm.tompi4py().bcast(rec, root=0)

    def write_summary(self, rec, status, quiet=False):
        """summary.json (atomically), with how the run ended and, after a
        restart, the checkpoint it continued (collective). ``quiet``: a
        failure to write it is not reported (a failure is being already)."""
        if self.output is None:
            return
        try:
            self.output.write_json("summary.json", dict(
                rec, status=status, restarted_from=self.restarted_from))
        except output.OutputError:
            if not quiet:
                raise

    def close(self):
        """Draw the last pictures, wait for the painter, and release a
        directory claimed here."""
        try:
            self.write_panels()
        finally:
            self.series = self.tube_frames = None
            if self.painter is not None:         # write_panels did not finish it
                self.painter.stop()
                self.painter = None
            if self.own_output:
                self.output.release()
