"""Time stepping driver: output, checkpoints, failure detection, summary.

    for n = 1 … N:  (ε, ε̇) ← integrator.step(t, ε, ε̇)

Every ``output_every`` steps the driver prints a progress line (step, t,
Newton/KSP iterations, energies, constraint violation), appends the yarn
centrelines to an XDMF/HDF5 time series and, at the requested snapshot
times, draws a PNG. A non-finite state, a failed Newton solve or a constraint
drift above ``drift_tol`` stops the run with one line naming the step, the
time and the quantity; everything written so far stays on disk.
"""

import json
import os
import time

import numpy as np
from petsc4py import PETSc

from solvers.integrators import SimulationError

from . import bspline, io

__all__ = ["Simulation", "SimulationError"]


class Simulation:
    """Drive a mechanical system with an integrator. Collective.

    Parameters
    ----------
    system : FullModel or ReducedModel
    integrator : solvers.integrators.SymplecticEuler or BackwardEuler
    out : str or None
        Output directory (None: write nothing).
    """

    def __init__(self, system, integrator, out=None, scene="", output_every=10,
                 snapshots=(), drift_tol=1e-6, checkpoint_every=0, verbose=True,
                 view="oblique", animation=""):
        self.system, self.integrator, self.out, self.scene = system, integrator, out, scene
        self.output_every, self.snapshots = max(1, output_every), sorted(snapshots)
        self.drift_tol, self.checkpoint_every = drift_tol, checkpoint_every
        self.verbose, self.view, self.animation = verbose, view, animation
        self.comm = system.comm
        self.x, self.v = system.rest_state(), system.rest_state()
        self.v.zeroEntries()
        self.t, self.step_count, self.stats = 0.0, 0, {"newton": 0, "ksp": 0}
        self.series = None
        self.full = getattr(system, "full", system)
        self.weights = self.full.m.createVecLeft()
        one = self.full.m.createVecRight()
        one.set(1.0)
        self.full.m.mult(one, self.weights)
        self.total_mass = self.weights.sum()
        self.eps = self.full.M.createVecLeft()
        self.r = system.C.createVecLeft()
        self.rf = self.full.C.createVecLeft()
        self.Mv = system.M.createVecLeft()
        self.initial_lowest = None
        self.frames, self.movie = [], []

    # -- measures ------------------------------------------------------------
    def centroid(self, eps):
        """Mass-weighted centroid Σ_i (m 1)_i p_i / Σ m (collective)."""
        w = self.weights.getArray(readonly=True)
        p = eps.getArray(readonly=True).reshape(-1, 3)
        c = self.comm.tompi4py().allreduce(w @ p)
        return c / self.total_mass

    def measures(self):
        """Energies, constraint residuals, strain, centroid (collective)."""
        s, mpi = self.system, self.comm.tompi4py()
        eps = s.full_state(self.x, self.eps)
        s.M.mult(self.v, self.Mv)
        kinetic = 0.5 * self.v.dot(self.Mv)
        elastic = s.elastic_energy(self.x)
        potential = -s.Qg.dot(self.x)
        s.C.mult(self.x, self.r)
        self.r.axpy(-1.0, s.d)
        self.full.C.mult(eps, self.rf)
        self.rf.axpy(-1.0, self.full.d)
        strain = s.strain(self.x)
        max_strain = mpi.allreduce(np.abs(strain).max() if strain.size else 0.0,
                                   op=__import__("mpi4py").MPI.MAX)
        return dict(kinetic_energy=kinetic, elastic_energy=elastic,
                    gravity_energy=potential,
                    max_constraint_violation=self.r.norm(PETSc.NormType.INFINITY),
                    max_contact_residual=self.rf.norm(PETSc.NormType.INFINITY),
                    max_strain=max_strain, centroid=self.centroid(eps).tolist())

    def geometry(self):
        """Rank 0: control points (nyarn, ncp, 3) and sampled centrelines."""
        P = self.system.gather_points(self.x)
        return (P, io.centrelines(P)) if P is not None else (None, None)

    # -- output --------------------------------------------------------------
    def _path(self, name):
        return os.path.join(self.out, name)

    def write_output(self, P, pts):
        """A frame of the XDMF series, and the snapshots now due (every rank
        drops them from its list; rank 0 writes)."""
        due = []
        while self.snapshots and self.t >= self.snapshots[0] - 1e-9:
            due.append(self.snapshots.pop(0))
        if self.out is None or self.comm.rank:
            return
        if self.series is None:
            self.series = io.CentrelineSeries(self._path("yarns.xdmf"), P,
                                              self.full.fabric.radius)
        self.series.write(self.t, P)
        if self.animation:
            self.movie.append((self.t, P))
        for ts in due:
            self.frames.append((f"t = {ts:g} s", P))
            io.draw(self._path(f"{self.scene}_t{ts:g}s.png"), P,
                    self.full.fabric.radius, view=self.view,
                    title=f"{self.scene}, {self.system.kind} model, t = {ts:g} s")

    def write_panels(self):
        """The snapshots of this run side by side in one PNG, in one scale
        that fits them all, and the animation of the output frames (rank 0)."""
        if self.out is None or self.comm.rank:
            return
        if self.frames:
            titles, frames = zip(*self.frames)
            io.draw_panels(self._path(f"{self.scene}_snapshots.png"), frames,
                           self.full.fabric.radius, titles, view=self.view)
        if len(self.movie) > 1:
            times, frames = zip(*self.movie)
            io.animate(self._path(self.animation), times, frames,
                       self.full.fabric.radius, view=self.view,
                       title=f"{self.scene}, {self.system.kind} model")
        self.frames, self.movie = [], []

    def checkpoint(self):
        """HDF5 checkpoint of everything needed to continue bit-exactly."""
        import h5py

        xs = self.comm.tompi4py().gather(self.x.getArray(readonly=True), root=0)
        vs = self.comm.tompi4py().gather(self.v.getArray(readonly=True), root=0)
        if self.comm.rank == 0:
            tmp = self._path("checkpoint.h5.tmp")
            with h5py.File(tmp, "w") as f:
                f["x"], f["v"] = np.concatenate(xs), np.concatenate(vs)
                f.attrs.update(t=self.t, step=self.step_count, kind=self.system.kind,
                               scene=self.scene, dt=self.integrator.dt,
                               options=json.dumps(PETSc.Options().getAll()))
            os.replace(tmp, self._path("checkpoint.h5"))

    def restart(self, path):
        """Continue from an HDF5 checkpoint written by ``checkpoint``."""
        import h5py

        from .options import KnitError

        try:
            with h5py.File(path, "r") as f:
                x, v = f["x"][...], f["v"][...]
                t, step, kind = f.attrs["t"], int(f.attrs["step"]), f.attrs["kind"]
        except (OSError, KeyError) as err:
            raise KnitError(f"-knit_restart {path}: not a knitfem checkpoint "
                            f"({err})") from None
        if kind != self.system.kind or len(x) != self.x.getSize():
            raise KnitError(f"-knit_restart {path}: checkpoint holds a {kind} model "
                            f"with {len(x)} unknowns, this run a {self.system.kind} "
                            f"model with {self.x.getSize()}")
        lo, hi = self.x.getOwnershipRange()
        self.x.getArray()[:], self.v.getArray()[:] = x[lo:hi], v[lo:hi]
        self.t, self.step_count = float(t), step
        self.snapshots = [s for s in self.snapshots if s > self.t + 1e-9]

    def progress(self, m):
        """One line: step, t, running totals of Newton and KSP iterations,
        energies, drift, wall time so far and the time left at this pace."""
        if self.verbose:
            elapsed = time.perf_counter() - self.clock[0]
            done = (self.t - self.clock[1]) / (self.clock[2] - self.clock[1])
            left = elapsed * (1 - done) / done if done > 0 else float("nan")
            PETSc.Sys.Print(
                f"step {self.step_count:6d}  t {self.t:.4f} s  total its: newton "
                f"{self.stats['newton']:5d} ksp {self.stats['ksp']:5d}  E_kin "
                f"{m['kinetic_energy']:.3e} J  E_el {m['elastic_energy']:.3e} J  "
                f"|Cx-d| {m['max_constraint_violation']:.1e} m  elapsed "
                f"{elapsed:.1f} s, left ~{left:.1f} s", comm=self.comm)

    # -- the loop ------------------------------------------------------------
    def check(self, m):
        finite = np.isfinite([m["kinetic_energy"], m["elastic_energy"]]).all() and \
            np.isfinite(self.x.norm())
        if not finite:
            raise SimulationError("the state is not finite (NaN or inf)")
        if m["max_constraint_violation"] > self.drift_tol:
            raise SimulationError(
                f"constraint drift {m['max_constraint_violation']:.3e} m exceeds "
                f"-knit_drift_tol {self.drift_tol:g}")

    def run(self, t_end):
        """Integrate to t_end. Returns the summary dict; raises SimulationError."""
        dt = self.integrator.dt
        nsteps = int(round((t_end - self.t) / dt))
        start = time.perf_counter()
        self.clock = (start, self.t, t_end)
        P, pts = self.geometry()
        if self.comm.rank == 0 and self.initial_lowest is None:
            self.initial_lowest = pts[..., 1].min()
        if self.step_count == 0:
            self.write_output(P, pts)
        stage = PETSc.Log.Stage("Time stepping")
        try:
            for _ in range(nsteps):
                stage.push()
                try:
                    st = self.integrator.step(self.t, self.x, self.v)
                finally:
                    stage.pop()
                self.step_count += 1
                self.t = self.step_count * dt
                for k in st:
                    self.stats[k] += st[k]
                last = self.step_count == int(round(t_end / dt))
                snap = self.snapshots and self.t >= self.snapshots[0] - 1e-9
                if self.step_count % self.output_every == 0 or last or snap:
                    m = self.measures()
                    self.check(m)
                    self.progress(m)
                    self.write_output(*self.geometry())
                if self.checkpoint_every and self.out and \
                        self.step_count % self.checkpoint_every == 0:
                    self.checkpoint()
        except SimulationError as err:
            self.close()
            raise SimulationError(f"step {self.step_count + 1}, t = "
                                  f"{self.t + dt:.6g} s: {err}") from None
        self.wall_time = time.perf_counter() - start
        summary = self.summary()
        self.close()
        return summary

    def summary(self):
        m = self.measures()
        P, pts = self.geometry()
        s = self.system
        rec = dict(scene=self.scene, model=s.kind,
                   integrator=self.integrator.name, steps=self.step_count,
                   dt=self.integrator.dt, t_end=self.t, wall_time_s=self.wall_time,
                   unknowns=s.M.getSize()[0] + s.C.getSize()[0], ranks=self.comm.size,
                   newton_iterations=self.stats["newton"],
                   ksp_iterations=self.stats["ksp"], **m)
        if self.comm.rank == 0:
            flat = pts.reshape(-1, 3)
            low = flat[np.argmin(flat[:, 1])]
            rec.update(lowest_point=low.tolist(),
                       sag=float(self.initial_lowest - low[1]),
                       tip=bspline.curve_points(P[0], np.array([P.shape[1] - 3.0]))[0]
                       .tolist())
            if self.out:
                with open(self._path("summary.json"), "w") as f:
                    json.dump(rec, f, indent=1)
        return self.comm.tompi4py().bcast(rec, root=0)

    def close(self):
        self.write_panels()
        if self.series is not None:
            self.series.close()
            self.series = None
