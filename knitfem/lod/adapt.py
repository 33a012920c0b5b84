"""Adaptive level of detail: an error indicator per volume patch, and the
mixed model's regions refined and coarsened in time.

Indicators. At a yarn-level state ε (= Γ_mix q), let a be the acceleration
of the full model there, contacts and fixed points included,

    [M Cᵀ] [a]   [Q(ε, 0)]
    [C 0 ] [λ] = [   0   ],

(elastic forces, gravity, point loads): where the yarns would go.
Πa = Γ(ΓᵀMΓ)⁻¹ΓᵀMa is the part of it the bounding volume can carry (the
M-orthogonal projection on range(Γ)); the remainder r = a − Πa is what the
reduced space cannot represent. Patch p of the volume gets its RMS in the
lumped M-norm,

    η_p = ( Σ_{i∈p} w_i |r_i|² / Σ_{i∈p} w_i )^½   [m/s²],   w = m 1,

over the yarn control points i whose rest parameters fall in p. With the
contact reactions in a, the loops' tension that their contacts hold (large,
everywhere) drops out. A yarn-level patch near its equilibrium has a ≈ 0
whether or not the volume could hold it, so coarsening asks the state
instead: the distance of ε from its mass-weighted projection
ε_c = Γ(ΓᵀMΓ)⁻¹ΓᵀMε on the volume,

    δ_p = ( Σ_{i∈p} w_i |ε_i − ε_c,i|² / Σ_{i∈p} w_i )^½ / r   [yarn radii],

what coarsening p would move its yarns by. Cost: one force evaluation, the
saddle point [M Cᵀ; C 0] at ε factorised (C depends on ε: the contacts are
frame-indifferent), three solves with ΓᵀMΓ (factorised once).

Adaptation. At the start and every ``every`` steps, a volume patch with
η_p > ``refine`` · median_p(η) becomes yarn level, and a yarn-level patch
that has been so for ``dwell`` checks at least and has δ_p < ``coarsen``
goes back to the volume. The threshold is relative: the stiff yarns turn
any shape the volume imposes into large accelerations everywhere (on the
pulled 15x30 swatch in a 13x8 volume η is 0.2–3e3 m/s² at rest, the pull
standing out by 800 times the median; after one step of 0.01 s it is
2e3–3e4 m/s² everywhere, the volume's stiff response to gravity, and the
pull stands out by less than 2), so the rule refines where η stands out. On a change the mixed
model is rebuilt (its volume part re-sampled for the new split, the set
read from the cache when the split was seen before) and the state carried over
by constrained mass-weighted least squares: q₂ minimises |Γ₂q − ε|²_M
under g₂(q) = 0, by Gauss–Newton from the unconstrained fit, and q̇₂ the
same for ε̇ under C₂(q₂) q̇ = 0,

    [M₂ C₂ᵀ] [δq]   [Γ₂ᵀ M (ε − Γ₂q₂)]      [M₂ C₂ᵀ] [q̇₂]   [Γ₂ᵀ M ε̇]
    [C₂ 0  ] [μ ] = [    −g₂(q₂)      ],     [C₂ 0  ] [μ ] = [   0    ],

exact when the new space contains the old one and the state satisfies the
new constraints (refinement away from the border). Contacts are internal
forces (C₂ T = 0 for a translation T ∈ range(Γ₂)), so linear momentum
1ᵀMε̇ is kept exactly; fixed points are external and take what they hold.
"""

import json
import os

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from solvers.saddle import SaddlePoint, saddle_ksp, solve_saddle

from knitfem.lod.mixed import MixedModel, MixedSpace

__all__ = ["Indicator", "Adaptation", "transfer", "adaptation_from_options"]

EV_INDICATOR = PETSc.Log.Event("knitIndicator")
EV_ADAPT = PETSc.Log.Event("knitAdapt")


def defaults(prefix, **values):
    """Option defaults for a prefix, unless the user gave them."""
    opts = PETSc.Options(prefix)
    for name, value in values.items():
        if not opts.hasName(name):
            opts.setValue(name, value)


def mumps_workspace(prefix, percent=300):
    """Default MUMPS ICNTL(14) (extra workspace, %) for a prefix: parallel
    factorisations of these small, dense-ish matrices run out of the
    default estimate (INFOG(1) = −9)."""
    defaults(prefix, mat_mumps_icntl_14=percent)


def cholesky(A, prefix):
    """A direct KSP (MUMPS Cholesky) on the SPD matrix A, then the options."""
    mumps_workspace(prefix)
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("cholesky")
    ksp.getPC().setFactorSolverType("mumps")
    ksp.setFromOptions()
    return ksp


class Indicator:
    """η_p for every patch of the volume of ``embedding`` (a reduced-model
    ``Embedding``). Collective."""

    def __init__(self, full, embedding, weights):
        self.full, self.G = full, embedding.Gamma
        self.MV = full.M.PtAP(self.G)
        self.solve_MV = cholesky(self.MV, "indicator_MV_")
        full.constraint_jacobian(full.start_state())
        self.saddle = SaddlePoint(full.M, full.C)
        mumps_workspace("indicator_")
        self.solve_a = saddle_ksp(self.saddle, "indicator_")
        self.z, self.sol = self.saddle.createVec(), self.saddle.createVec()
        lo, hi = full.layout.cp_start, full.layout.cp_end
        n1, _ = self.shape = weights.npatch
        self.patch = weights.patch[lo:hi, 0] + n1 * weights.patch[lo:hi, 1]
        one = full.m.createVecRight()
        one.set(1.0)
        w = full.m.createVecLeft()
        full.m.mult(one, w)
        self.w = w.getArray().copy()
        self.mass = self._patch_sum(self.w)
        self.alpha, self.rhs = self.MV.createVecRight(), self.MV.createVecRight()
        self.ec, self.zero = full.M.createVecLeft(), full.M.createVecLeft()
        self.Q, self.a, self.b = (full.M.createVecLeft() for _ in range(3))

    def _patch_sum(self, values):
        """Σ over the points of each patch, all ranks (collective)."""
        local = np.bincount(self.patch, weights=values, minlength=np.prod(self.shape))
        return self.full.comm.tompi4py().allreduce(local)

    def __call__(self, eps):
        """(η [m/s²], δ [yarn radii]), each (n1 − 3, n2 − 3), at the
        yarn-level state ``eps`` (Vec). Collective."""
        with EV_INDICATOR:
            self.full.M.mult(eps, self.a)
            self.G.multTranspose(self.a, self.rhs)
            self.solve_MV.solve(self.rhs, self.alpha)
            self.G.mult(self.alpha, self.ec)                  # ε_c = Γ α_c
            d = (eps.getArray(readonly=True)
                 - self.ec.getArray(readonly=True)).reshape(-1, 3)
            dist = self._patch_rms(d) / self.full.fabric.radius
            self.full.forces(eps, self.zero, self.Q)
            self.acceleration(eps, self.Q, self.a)
            self.full.M.mult(self.a, self.b)
            self.G.multTranspose(self.b, self.rhs)
            self.solve_MV.solve(self.rhs, self.alpha)
            self.G.mult(self.alpha, self.b)                   # Π a
            r = (self.a.getArray(readonly=True)
                 - self.b.getArray(readonly=True)).reshape(-1, 3)
            eta = self._patch_rms(r)
        return eta, dist

    def _patch_rms(self, r):
        """(Σ_{i∈p} w_i |r_i|² / Σ_{i∈p} w_i)^½ for every patch, (n1−3, n2−3)."""
        num = self._patch_sum(self.w * np.einsum("ij,ij->i", r, r))
        rms = np.sqrt(num / np.maximum(self.mass, 1e-300))
        return rms.reshape(self.shape[::-1]).T

    def acceleration(self, eps, Q, a):
        """a from [M Cᵀ; C 0][a; λ] = [Q; 0], C = C(ε) (collective)."""
        if self.full.nonlinear_constraints:
            self.full.constraint_jacobian(eps)
            self.saddle.update(constraints=True)
        zu, zl = self.saddle.split(self.z)
        zu[:], zl[:] = Q.getArray(readonly=True), 0.0
        solve_saddle(lambda: self.solve_a.solve(self.z, self.sol), self.solve_a)
        a.getArray()[:] = self.saddle.split(self.sol)[0]

    def destroy(self):
        for obj in (self.MV, self.solve_MV, self.solve_a, self.z, self.sol,
                    self.alpha, self.rhs, self.ec, self.zero, self.Q, self.a,
                    self.b):
            obj.destroy()
        self.saddle.destroy()


def transfer(old, new, x, v, prefix="adapt_transfer_", iterations=20):
    """(q₂, q̇₂) on the system ``new`` from (x, v) on ``old`` by constrained
    mass-weighted least squares (module docstring). Collective."""
    full = old.full
    target, eps, Me = (full.M.createVecLeft() for _ in range(3))
    q, qdot, b = (new.M.createVecRight() for _ in range(3))
    g = new.C.createVecLeft()
    old.full_state(x, target)
    new.project(target, q)                             # unconstrained fit
    saddle = SaddlePoint(new.M, new.constraint_jacobian(q))
    mumps_workspace(prefix)
    # M₂'s volume block is ill-conditioned (1e8 on a 15x30 jersey): FGMRES on
    # the factorisation recovers the digits that keep momentum to round-off
    # (GMRES's recursive residual parts from the true one at 1e-14 on 2 ranks)
    defaults(prefix, ksp_type="fgmres", ksp_rtol=1e-14, ksp_atol=0)
    ksp = saddle_ksp(saddle, prefix)
    rhs, sol = saddle.createVec(), saddle.createVec()

    def correct(out, constraint):
        """out += δ: [M₂ C₂ᵀ; C₂ 0][δ; μ] = [Γ₂ᵀM(target − Γ₂ out); constraint];
        returns max |δ| (collective)."""
        new.full_state(out, eps)
        eps.aypx(-1.0, target)
        full.M.mult(eps, Me)
        new.Gamma.multTranspose(Me, b)
        ru, rl = saddle.split(rhs)
        ru[:], rl[:] = b.getArray(readonly=True), constraint
        solve_saddle(lambda: ksp.solve(rhs, sol), ksp)
        step = saddle.split(sol)[0]
        out.getArray()[:] += step
        return new.comm.tompi4py().allreduce(np.abs(step).max() if step.size
                                             else 0.0, op=MPI.MAX)

    for _ in range(iterations):
        new.constraint_residual(q, g)
        if correct(q, -g.getArray(readonly=True)) <= 1e-12 * full.fabric.radius \
                or not new.nonlinear_constraints:
            break
        new.constraint_jacobian(q)
        saddle.update(constraints=True)
    old.full_state(v, target)
    correct(qdot, 0.0)
    for obj in (ksp, target, eps, Me, rhs, sol, b, g):
        obj.destroy()
    saddle.destroy()
    return q, qdot


class Adaptation:
    """The indicators every ``every`` steps and, when ``adapt``, the mixed
    model's patches refined and coarsened by the rule of the module
    docstring. Called by ``Simulation`` after each step."""

    def __init__(self, system, embedding, every=5, refine=np.inf, coarsen=0.0,
                 dwell=4, adapt=False):
        self.full, self.weights = system.full, system.space.weights
        self.indicator = Indicator(system.full, embedding, self.weights)
        self.every, self.refine, self.coarsen = every, refine, coarsen
        self.dwell, self.adapt = dwell, adapt
        self.patches = self.weights.patches_of(system.space.full)
        self.age = np.where(self.patches, dwell, 0)       # checks at yarn level
        self.history, self.events = [], []
        self.eps = system.full.M.createVecLeft()

    def check(self, t, system, x):
        """Record η and δ at t; return the patches the rule asks for."""
        eta, dist = self.indicator(system.full_state(x, self.eps))
        self.age = np.where(self.patches, self.age + 1, 0)
        want = self.patches.copy()
        if self.adapt:
            want |= eta > self.refine * np.median(eta)
            want &= ~(self.patches & (self.age > self.dwell) & (dist < self.coarsen))
        self.history.append(dict(t=t, eta=eta, dist=dist,
                                 patches=self.patches.copy(),
                                 unknowns=system.M.getSize()[0]
                                 + system.C.getSize()[0]))
        return want

    def __call__(self, sim):
        if sim.step_count % self.every:
            return
        want = self.check(sim.t, sim.system, sim.x)
        if np.array_equal(want, self.patches):
            return
        with EV_ADAPT:
            self.switch(sim, want)

    def switch(self, sim, patches):
        """Rebuild the mixed model on ``patches``, carry the state over, and
        give ``sim`` the new system, integrator and state."""
        old = sim.system
        space = MixedSpace(old.comm, old.layout, self.weights,
                           self.weights.patch_mask(patches))
        new = MixedModel(old.full, space, old.reduced, old.rule)   # V re-sampled
        x, v = transfer(old, new, sim.x, sim.v)
        integrator = sim.integrator.like(new)
        refined = np.argwhere(patches & ~self.patches).tolist()
        coarsened = np.argwhere(~patches & self.patches).tolist()
        n_old = old.M.getSize()[0] + old.C.getSize()[0]
        n_new = new.M.getSize()[0] + new.C.getSize()[0]
        self.events.append(dict(t=sim.t, step=sim.step_count, refined=refined,
                                coarsened=coarsened, unknowns=[n_old, n_new]))
        PETSc.Sys.Print(f"adapt: t {sim.t:.4f} s, step {sim.step_count}: refined "
                        f"{refined}, coarsened {coarsened} (patches j1,j2); "
                        f"unknowns {n_old} -> {n_new}", comm=old.comm)
        for obj in (sim.x, sim.v, sim.r, sim.Mv):
            obj.destroy()
        sim.system, sim.integrator, sim.x, sim.v = new, integrator, x, v
        sim.r, sim.Mv = new.C.createVecLeft(), new.M.createVecLeft()
        old.space.destroy()
        old.destroy()
        self.patches = patches.copy()
        self.history[-1].update(patches=patches.copy(), unknowns=n_new)

    # -- report ----------------------------------------------------------------
    def record(self):
        """What summary.json gets: the last indicator, the patches, the
        changes and the unknowns over time."""
        last = self.history[-1] if self.history else None
        unknowns = [h["unknowns"] for h in self.history]
        return dict(
            indicator_patches=list(self.patches.shape),
            indicator_last=dict(t=last["t"], eta=last["eta"].tolist(),
                                distance=last["dist"].tolist(),
                                full_patches=np.argwhere(last["patches"]).tolist())
            if last else None,
            indicator_max=float(max(h["eta"].max() for h in self.history))
            if last else None,
            adapt=dict(enabled=self.adapt, every=self.every, refine=self.refine,
                       coarsen=self.coarsen, dwell=self.dwell, events=self.events,
                       unknowns_min=min(unknowns, default=None),
                       unknowns_max=max(unknowns, default=None),
                       unknowns_mean=float(np.mean(unknowns)) if unknowns else None))

    def report(self, sim, out):
        """Add ``record`` to out/summary.json and draw out/indicator.png
        (rank 0)."""
        if self.history == [] or sim.t > self.history[-1]["t"] + 1e-12:
            self.check(sim.t, sim.system, sim.x)
        rec = self.record()
        if sim.comm.rank or not out:
            return rec
        path = os.path.join(out, "summary.json")
        summary = json.load(open(path)) if os.path.exists(path) else {}
        summary.update(rec)
        with open(path, "w") as f:
            json.dump(summary, f, indent=1)
        draw_history(os.path.join(out, "indicator.png"), self.full.fabric,
                     self.weights, self.history, self.refine, self.coarsen)
        return rec


def draw_history(path, fabric, weights, history, refine, coarsen, panels=4):
    """log₁₀ η per patch over the swatch at rest, yarn-level patches outlined,
    at ``panels`` times of the history, and the unknowns against time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from knitfem import io

    pick = np.unique(np.linspace(0, len(history) - 1, panels).round().astype(int))
    fig, axes = plt.subplots(1, len(pick) + 1, figsize=(4.2 * (len(pick) + 1), 3.2),
                             layout="constrained")
    vol, (n1, n2) = weights.volume, weights.npatch
    s1, s2 = np.meshgrid(np.arange(n1 + 1), np.arange(n2 + 1), indexing="ij")
    corners = vol.points(s1, s2, 0.5)
    etas = np.concatenate([h["eta"].ravel() for h in history])
    positive = etas[etas > 0]
    norm = LogNorm(vmin=max(positive.min(), 1e-6 * positive.max()),
                   vmax=positive.max()) if positive.size else None
    lines = io.centrelines(fabric.curves(fabric.X), 3)
    lines = np.split(lines.points, lines.start[1:-1])
    for ax, i in zip(axes, pick):
        h = history[i]
        mesh = ax.pcolormesh(corners[..., 0], corners[..., 1],
                             np.maximum(h["eta"], norm.vmin if norm else 0),
                             norm=norm, cmap="viridis", shading="flat")
        for yarn in lines:
            ax.plot(yarn[:, 0], yarn[:, 1], color="w", lw=0.3, alpha=0.6)
        for j1, j2 in np.argwhere(h["patches"]):
            box = corners[[j1, j1 + 1, j1 + 1, j1, j1], [j2, j2, j2 + 1, j2 + 1, j2]]
            ax.plot(box[:, 0], box[:, 1], color="r", lw=1.5)
        ax.set_aspect("equal")
        ax.set_title(f"t = {h['t']:.2f} s, {int(h['patches'].sum())} patches "
                     "yarn level", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(mesh, ax=axes[:len(pick)], label="η [m/s²]", shrink=0.8)
    ax = axes[-1]
    ax.plot([h["t"] for h in history], [h["unknowns"] for h in history], "k.-")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("unknowns")
    ax.set_title(f"refine: η > {refine:g} median(η), coarsen: δ < {coarsen:g} r",
                 fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def adapt_options(opts):
    """(adapt, every, refine, coarsen, dwell) from -knit_adapt and
    -knit_adapt_every, _refine, _coarsen, _dwell."""
    adapt = opts.getBool("adapt", False, "mixed model: refine volume patches to "
                         "yarn level and coarsen them back by the indicator")
    every = opts.getInt("adapt_every", 5, "steps between indicator evaluations", 1)
    refine = opts.getReal("adapt_refine", 20.0, "refine a patch when its indicator "
                          "eta exceeds this times the median over the patches",
                          positive=True)
    coarsen = opts.getReal("adapt_coarsen", 0.1, "coarsen a yarn-level patch when "
                           "its yarns lie within this of the volume [yarn radii]",
                           nonnegative=True)
    dwell = opts.getInt("adapt_dwell", 4, "indicator evaluations a patch stays "
                        "yarn level before it may be coarsened", 0)
    return adapt, every, refine, coarsen, dwell


def adaptation_from_options(opts, system):
    """The indicator (and, with -knit_adapt, adaptation) of a mixed model;
    None for the other models."""
    adapt, every, refine, coarsen, dwell = adapt_options(opts)
    from knitfem.errors import KnitError

    if system.kind != "mixed":
        if adapt:
            raise KnitError(f"-knit_adapt needs -knit_model mixed (got "
                            f"-knit_model {system.kind})")
        return None
    return Adaptation(system, system.reduced, every, refine, coarsen, dwell, adapt)
