"""Time stepping driver: output, checkpoints, failure detection, summary.

    while t < t_end:  (ε, ε̇), h ← integrator.step(t, ε, ε̇, t_stop);  t ← t + h

The integrator chooses the step h (fixed, or by its error control) and lands
exactly on t_stop, the next snapshot time or t_end. Every ``output_every``
steps the driver prints a progress line (step, t, dt, Newton/KSP iterations,
rejected steps, energies, constraint violation), appends the yarn
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
                 view="oblique"):
        self.system, self.integrator, self.out, self.scene = system, integrator, out, scene
        self.output_every, self.snapshots = max(1, output_every), sorted(snapshots)
        self.drift_tol, self.checkpoint_every = drift_tol, checkpoint_every
        self.verbose, self.view = verbose, view
        self.comm = system.comm
        self.x, self.v = system.rest_state(), system.rest_state()
        self.v.zeroEntries()
        self.t, self.step_count = 0.0, 0
        self.stats = {"newton": 0, "ksp": 0, "rejected": 0}
        self.steps_taken = []            # (dt) of this process's accepted steps
        self.energy = []                 # (t, kinetic, elastic + gravity)
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
        self.frames = []

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
                    total_energy=kinetic + elastic + potential,
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
        for ts in due:
            self.frames.append((f"t = {ts:g} s", P))
            io.draw(self._path(f"{self.scene}_t{ts:g}s.png"), P,
                    self.full.fabric.radius, view=self.view,
                    title=f"{self.scene}, {self.system.kind} model, t = {ts:g} s",
                    extent=self.extent)

    def write_panels(self):
        """The snapshots of this run side by side in one PNG (rank 0)."""
        if self.out is None or self.comm.rank or not self.frames:
            return
        titles, frames = zip(*self.frames)
        io.draw_panels(self._path(f"{self.scene}_snapshots.png"), frames,
                       self.full.fabric.radius, titles, view=self.view,
                       extent=self.extent)
        self.frames = []

    def checkpoint(self):
        """HDF5 checkpoint of everything needed to continue bit-exactly."""
        import h5py

        mpi = self.comm.tompi4py()
        xs = mpi.gather(self.x.getArray(readonly=True), root=0)
        vs = mpi.gather(self.v.getArray(readonly=True), root=0)
        state = {k: mpi.gather(np.atleast_1d(a), root=0) if np.ndim(a) else a
                 for k, a in self.integrator.state().items()}
        if self.comm.rank == 0:
            tmp = self._path("checkpoint.h5.tmp")
            with h5py.File(tmp, "w") as f:
                f["x"], f["v"] = np.concatenate(xs), np.concatenate(vs)
                for k, a in state.items():
                    f[f"integrator/{k}"] = np.concatenate(a) if isinstance(a, list) \
                        else a
                f["stats"] = [self.stats[k] for k in ("newton", "ksp", "rejected")]
                if self.initial_lowest is not None:
                    f.attrs["initial_lowest"] = self.initial_lowest
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
                saved = {k: a[...] for k, a in f.get("integrator", {}).items()}
                stats = f["stats"][...] if "stats" in f else None
                lowest = f.attrs.get("initial_lowest")
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
        if saved:
            self.integrator.set_state(self.local_parts(saved))
        if lowest is not None:
            self.initial_lowest = float(lowest)
        if stats is not None:
            self.stats.update(zip(("newton", "ksp", "rejected"), map(int, stats)))
        self.snapshots = [s for s in self.snapshots if s > self.t + 1e-9]

    def local_parts(self, saved):
        """This rank's slices of gathered integrator state arrays (the local
        sizes are those of the integrator's own ``state()``)."""
        mpi, out = self.comm.tompi4py(), {}
        for k, a in self.integrator.state().items():
            if np.ndim(a):
                lo = mpi.exscan(len(a)) or 0
                out[k] = saved[k][lo:lo + len(a)]
            else:
                out[k] = saved[k][()]
        return out

    def progress(self, m):
        if self.verbose:
            dt = self.steps_taken[-1] if self.steps_taken else self.integrator.dt
            PETSc.Sys.Print(
                f"step {self.step_count:6d}  t {self.t:8.4f}  dt {dt:.2e}  newton "
                f"{self.stats['newton']:4d}  ksp {self.stats['ksp']:5d}  rejected "
                f"{self.stats['rejected']:3d}  kinetic {m['kinetic_energy']:.4e}  "
                f"elastic {m['elastic_energy']:.4e}  |C x - d| "
                f"{m['max_constraint_violation']:.2e}", comm=self.comm)

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
        start = time.perf_counter()
        tiny = 1e-12 * max(1.0, abs(t_end))
        P, pts = self.geometry()
        if self.comm.rank == 0:
            # room for the rest shape to swing or sag down by its own size
            lo, hi = pts.reshape(-1, 3).min(0), pts.reshape(-1, 3).max(0)
            span, size = hi - lo, (hi - lo).max()
            self.extent = (lo - [0.15 * span[0], size, 0.2 * size],
                           hi + [0.15 * span[0], 0.1 * size, 0.2 * size])
            if self.initial_lowest is None:
                self.initial_lowest = pts[..., 1].min()
        if not self.energy:
            self.record_energy(self.measures())
        if self.step_count == 0:
            self.write_output(P, pts)
        stage = PETSc.Log.Stage("Time stepping")
        try:
            while self.t < t_end - tiny:
                stop = t_end
                if self.snapshots and self.t < self.snapshots[0] - tiny:
                    stop = min(stop, self.snapshots[0])
                stage.push()
                try:
                    st = self.integrator.step(self.t, self.x, self.v, stop)
                finally:
                    stage.pop()
                self.step_count += 1
                landed = abs(self.t + st["dt"] - stop) <= tiny
                self.t = stop if landed else self.t + st["dt"]
                self.steps_taken.append(st["dt"])
                for k in self.stats:
                    self.stats[k] += st[k]
                last = self.t >= t_end - tiny
                snap = self.snapshots and self.t >= self.snapshots[0] - 1e-9
                if self.step_count % self.output_every == 0 or last or snap:
                    m = self.measures()
                    self.check(m)
                    self.record_energy(m)
                    self.progress(m)
                    self.write_output(*self.geometry())
                if self.checkpoint_every and self.out and \
                        self.step_count % self.checkpoint_every == 0:
                    self.checkpoint()
        except SimulationError as err:
            self.close()
            raise SimulationError(f"step {self.step_count + 1}, t = "
                                  f"{self.t:.6g} s: {err}") from None
        self.wall_time = time.perf_counter() - start
        summary = self.summary()
        self.close()
        return summary

    def record_energy(self, m):
        """Keep (t, kinetic, elastic + gravity energy) of a progress point."""
        self.energy.append((self.t, m["kinetic_energy"],
                            m["elastic_energy"] + m["gravity_energy"]))

    def energy_record(self):
        """Total energy E = T + E_el + E_g over the run and its drift
        E(t_end) − E(0), absolute (J) and over the largest kinetic energy."""
        t, kin, pot = np.array(self.energy).T
        total = kin + pot
        drift = float(total[-1] - total[0])
        return dict(energy_drift=drift,
                    energy_drift_relative=drift / max(kin.max(), 1e-300),
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
                   dt=self.integrator.dt, dt_min=float(taken.min()),
                   dt_max=float(taken.max()),
                   adaptive=bool(control is not None and control.adaptive),
                   rejected_steps=self.stats["rejected"],
                   t_end=self.t, wall_time_s=self.wall_time,
                   unknowns=s.M.getSize()[0] + s.C.getSize()[0], ranks=self.comm.size,
                   newton_iterations=self.stats["newton"],
                   ksp_iterations=self.stats["ksp"], **m)
        if rec["adaptive"]:
            rec.update(rtol=control.rtol, atol=control.atol)
        if self.energy:
            rec.update(self.energy_record())
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
