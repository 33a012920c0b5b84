"""A constrained energy minimum by Newton's method with a shift and a line
search on the energy: the relaxed state of a free knit.

The system's total energy Π(ε) = E(ε) − Q_gᵀε (elastic, barriers and
gravity) is minimised subject to its constraints g(ε) = 0. Iteration k,
with K = ∂²E/∂ε² + Σ_i μ_i ∇²g_i and C at ε_k, solves

    [K + σ M  Cᵀ] [δ ]   [ Q(ε_k)]
    [C        0 ] [μ⁺] = [−g(ε_k)],

i.e. (K + σM) δ + Cᵀμ⁺ = Q = −∇Π and C δ = −g, and moves ε_k + t δ with
μ ← μ + t (μ⁺ − μ). The shift σ M (M the mass matrix: a pseudo-time step
1/σ of the gradient flow M ε̇ = Q − Cᵀμ, measured in kilograms, so that
heavy and light coordinates move alike) makes every step a descent
direction of the merit

    L(ε) = Π(ε) + μ⁺ᵀ g(ε),   dL/dt = −δᵀ(K + σM)δ   at t = 0,

where K alone is indefinite (a knit far from its rest buckles) or
singular (a free knit's rigid motions; its courses' hinges). t is the
largest of t₀, t₀/2, … with Armijo's decrease L(ε + tδ) ≤ L(ε) + 10⁻⁴ t
dL/dt at a state where no two yarn surfaces are closer than 2r
(``min_yarn_distance``), from t₀ = min(1, r / max_i |δ_i − δ̄|): a step
that moves no control point by more than r relative to the mean cannot
carry one yarn through another unseen (``_reach``). The yarn contact's own
step filter (``step_fraction``, a conservative bound on every pair's
relative move) was tried as t₀ first: it counts a slide of two touching
yarns along each other as an approach and cut the steps of the relaxed
5×5 jersey to t ≈ 0.01–0.1 (1 000 iterations a load step, σ never at its
floor). σ is Levenberg–Marquardt's: divided by 4 after a step taken at t₀,
doubled after a cut one, multiplied by 10 (the step taken again) when δ is
no descent direction or no t in 10 halvings decreases L; it never falls
below ``floor`` = 10⁻¹² max diag K / max diag M, which holds the rigid
motions and leaves the last iterations Newton's. And it is multiplied by 8
(the step solved again) while the LDLᵀ's inertia says K + σM is not
positive definite on the constraints' null space (``_convex``), where
the step would head for a saddle or a maximum of the quadratic model (the
6×6 jersey: 1 393 iterations without, 1 264 with; 2 371 and 1 865 with
the yarn contact off).

Why not the residual |F|: after a bending step the residual of a stiff
yarn is dominated by its membrane part, EA ≈ 10⁴ times its bending scale,
so a line search or a pseudo-time schedule on |F| (``statics``) crawls or
stalls (``statics.StaticSolver`` on the 5×5 natural jersey: |F| still
0.05 after 500 iterations); the energy weighs each part by what it costs.
Near the minimum L changes by less than its round-off; a step then counts
as a decrease when L grew by no more than 10⁻¹³ |L|.

It stops when the residual force over the lumped mass, max_i |Q − Cᵀμ|_i /
m_i, is below a given acceleration and |g| below 10⁻⁹ yarn radii. The last
iterations converge linearly (about 0.7 an iteration on the 5×5 jersey):
the barrier's pair Hessians are projected to positive semi-definite.

``guide_to`` adds a spring ½ c |ε − ε̂|²_M to Π (its Hessian c M joins
the shift), to steer the path of a minimisation that has more than one
minimum (``run.relax.Relaxation``).
"""

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .integrators import SimulationError
from .saddle import SaddlePoint, SolverFailure, saddle_ksp, solve_saddle

__all__ = ["ConstrainedDescent"]

ARMIJO = 1e-4
HALVINGS = 10
ROUND_OFF = 1e-13


class ConstrainedDescent:
    """Minimise Π(ε) subject to g(ε) = 0 (module docstring). Collective.

    ``system`` a ``FullModel``; ``prefix`` of its KSP's options (a direct
    LDLᵀ of the saddle point by default, ``saddle.saddle_ksp``); ``length``
    the largest move of the first iteration (default: the yarn radius).
    ``stats`` counts Newton iterations (``newton``: linear solves),
    ``rejected`` trial steps and ``relayouts`` of the tangent's pattern.
    """

    def __init__(self, system, prefix="relax_", length=None):
        self.system, self.prefix = system, prefix
        self.length = length or system.fabric.radius
        self.x, self.Q = system.M.createVecLeft(), system.M.createVecLeft()
        self.zero, self.tmp = system.M.createVecLeft(), system.M.createVecLeft()
        self.g, self.gt = system.C.createVecLeft(), system.C.createVecLeft()
        self.mu = system.C.createVecLeft()
        self.lumped = system.M.getRowSum()
        self.Mx, self.target, self.guide = system.M.createVecLeft(), None, 0.0
        self.ksp = self.saddle = self.A = None
        self._layout(system.start_state())
        self.rhs, self.z = self.saddle.createVec(), self.saddle.createVec()
        self._set_floor()
        self.sigma = None
        self.stats = dict(newton=0, rejected=0, relayouts=0, ksp=0, inertia=0)

    # -- the linear system ---------------------------------------------------
    def _layout(self, x):
        """A = K + M on the tangent's pattern at x, its saddle point, KSP."""
        s = self.system
        for obj in (self.ksp, self.saddle, self.A):
            if obj is not None:
                obj.destroy()
        self.A = s.stiffness(x).duplicate(copy=True)
        self.A.axpy(1.0, s.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
        self.saddle = SaddlePoint(self.A, s.constraint_jacobian(x), prefix=self.prefix,
                                  blocks=getattr(s, "yarn_blocks", None))
        self.ksp = saddle_ksp(self.saddle, self.prefix)
        if self.saddle.delta and not PETSc.Options(self.prefix).hasName("ksp_type"):
            # the regularised factorisation preconditions K itself: the step
            # must solve K (C δ = −g) for dL/dt to be the descent it says
            self.ksp.setType("gmres")
            self.ksp.setTolerances(rtol=1e-12, atol=0.0, max_it=30)

    def _set_floor(self):
        """σ's floor, 10⁻¹² max diag K / max diag M, from the Newton matrix
        as last laid out."""
        diag = self.A.getDiagonal()
        self.floor = 1e-12 * diag.max()[1] / self.lumped.max()[1]
        diag.destroy()

    def _solve(self, K):
        """δ and μ⁺ (into self.z) from the residual in self.rhs, with the
        matrix K + σM (K the tangent, kept), σ raised (×8) until the LDLᵀ's
        inertia says K + σM is positive definite on the constraints' null
        space (``_convex``)."""
        while True:
            K.copy(self.A, PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
            self.A.axpy(self.sigma + self.guide, self.system.M,
                        PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
            self.saddle.update(constraints=True)
            try:
                solve_saddle(lambda: self.ksp.solve(self.rhs, self.z), self.ksp)
            except SolverFailure as err:
                raise SimulationError(f"relaxation: {err}", curable=False) from None
            self.stats["newton"] += 1
            self.stats["ksp"] += self.ksp.getIterationNumber()
            if self._convex():
                return
            self.stats["inertia"] += 1
            self.sigma *= 8.0

    def _convex(self):
        """Whether the last factorisation of [K + σM, Cᵀ; C, 0] had no more
        negative pivots than C has rows: its inertia when K + σM is positive
        definite on C's null space (Nocedal & Wright, Thm 16.3; IPOPT's
        inertia correction, Wächter & Biegler 2006). With a regularised
        preconditioner (``saddle.delta``, several ranks) it is that
        factorisation's, whose −δ I block asks K + σM to be positive
        definite outright. True when MUMPS's LDLᵀ, which alone reports it,
        is not the factorisation."""
        pc = self.ksp.getPC()
        if pc.getType() != "cholesky" or pc.getFactorSolverType() != "mumps":
            return True
        negative = pc.getFactorMatrix().getMumpsInfog(12)
        return negative <= self.system.C.getSize()[0]

    # -- merit -----------------------------------------------------------------
    def _residual(self, x):
        """Q = −∇Π into self.Q and g into self.g, at x (a Vec)."""
        s = self.system
        s.forces(x, self.zero, self.Q)
        s.constraint_residual(x, self.g)
        if self.guide:
            self.tmp.waxpy(-1.0, self.target, x)
            s.M.mult(self.tmp, self.Mx)
            self.Q.axpy(-self.guide, self.Mx)

    def _merit(self, x, mu):
        """L = E − Q_gᵀε + ½ c |ε − ε̂|²_M + μᵀg at x (collective)."""
        s = self.system
        s.constraint_residual(x, self.gt)
        L = s.elastic_energy(x) - s.Qg.dot(x) + self.gt.dot(mu)
        if self.guide:
            self.tmp.waxpy(-1.0, self.target, x)
            s.M.mult(self.tmp, self.Mx)
            L += 0.5 * self.guide * self.tmp.dot(self.Mx)
        return L

    # -- the iteration -------------------------------------------------------
    def start_afresh(self, x):
        """Forget the iterations so far, as a solver made at x would: no
        multipliers, the shift chosen again by the next step and its floor
        taken at x, the Newton matrix laid out at x."""
        self.mu.zeroEntries()
        self.sigma = None
        self._layout(x)
        self._set_floor()

    def guide_to(self, target, c):
        """Add ½ c |ε − ε̂|²_M to Π (c [1/s²] ≥ 0, ε̂ = ``target``, a Vec kept):
        a spring to a given shape, to steer the path to a minimum."""
        self.target, self.guide = target, float(c)

    def minimize(self, x, accel, max_it=2000):
        """Move x (a Vec) to the constrained minimum, to a residual whose
        acceleration max_i |Q − Cᵀμ|_i / m_i is at most ``accel`` [m/s²]
        with |g| at most 10⁻⁹ yarn radii. The multipliers μ are kept from one
        call to the next (``mu``). Returns the iterations taken;
        SimulationError when max_it do not get there."""
        s = self.system
        mu_new, trial = self.mu.duplicate(), x.duplicate()
        step = x.duplicate()
        held = 1e-9 * s.fabric.radius
        try:
            for it in range(max_it + 1):
                if s.begin_step(x):
                    self._layout(x)
                    self.stats["relayouts"] += 1
                self.acceleration = self._acceleration(x)
                if self.acceleration <= accel and \
                        self.g.norm(PETSc.NormType.INFINITY) <= held:
                    return it
                if it == max_it:
                    break
                K = s.stiffness(x, self.mu)
                s.constraint_jacobian(x)
                while True:
                    self._residual(x)
                    if self.sigma is None:   # the first step moves by ``length``
                        self.tmp.pointwiseDivide(self.Q, self.lumped)
                        self.sigma = max(self.tmp.norm(PETSc.NormType.INFINITY)
                                         / self.length, self.floor)
                    u, lam = self.saddle.split(self.rhs)
                    u[:] = self.Q.getArray(readonly=True)
                    lam[:] = -self.g.getArray(readonly=True)
                    self._solve(K)
                    d, m = self.saddle.split(self.z)
                    step.getArray()[:] = d
                    mu_new.getArray()[:] = m
                    slope = -self.Q.dot(step) - mu_new.dot(self.g)
                    t, full = self._line_search(x, step, mu_new, slope, trial) \
                        if slope < 0 else (0.0, False)
                    if t > 0:
                        break
                    self.stats["rejected"] += 1
                    self.sigma *= 10.0
                    if self.sigma > 1e30:
                        raise SimulationError("relaxation: no descent direction "
                                              "however small the step", curable=False)
                x.axpy(t, step)
                self.mu.scale(1.0 - t)
                self.mu.axpy(t, mu_new)
                self.sigma = max(self.sigma / 4, self.floor) if full else 2 * self.sigma
            raise SimulationError(f"relaxation: no minimum within {max_it} Newton "
                                  f"iterations (residual acceleration "
                                  f"{self.acceleration:.3g} m/s², shift σ = "
                                  f"{self.sigma:.3g})", curable=False)
        finally:
            for v in (mu_new, trial, step):
                v.destroy()

    def _line_search(self, x, step, mu_new, slope, trial):
        """(t, whether t = t₀): the step length (0: none found) by Armijo's
        rule on L with μ⁺, from t₀ = min(1, r / max_i |δ_i − δ̄|)
        (``_reach``), halved while the trial state brings two yarn surfaces
        closer than 2r or does not decrease L enough."""
        s = self.system
        t = self._t0 = self._reach(step)
        L0 = self._merit(x, mu_new)
        slack = ROUND_OFF * abs(L0)
        touch = 2 * s.fabric.radius
        for k in range(HALVINGS):
            x.copy(trial)
            trial.axpy(t, step)
            if s.min_yarn_distance(trial) > touch and self._merit(trial, mu_new) <= \
                    L0 + ARMIJO * t * slope + slack:
                return t, k == 0
            t *= 0.5
        return 0.0, False

    def _reach(self, step):
        """min(1, r / max_i |δ_i − δ̄|), δ̄ the mean of the control points'
        updates δ_i: a step that moves no yarn point by more than r relative
        to the mean brings no two of them closer by more than 2r, so no yarn
        passes through another unseen when every surface stays apart at its
        end (two surfaces 2r apart or more at both ends of a straight move
        whose relative motion passes through must move 4r relative to each
        other) (collective)."""
        s = self.system
        d = step.getArray(readonly=True).reshape(-1, 3)
        mpi = s.comm.tompi4py()
        n = mpi.allreduce(len(d))
        mean = mpi.allreduce(d.sum(axis=0)) / max(n, 1)
        dev = np.sqrt(np.max(np.sum((d - mean) ** 2, axis=1))) if len(d) else 0.0
        dev = mpi.allreduce(dev, op=MPI.MAX)
        return min(1.0, s.fabric.radius / dev) if dev > 0 else 1.0

    def _acceleration(self, x):
        """max_i |Q − Cᵀμ|_i / m_i at x [m/s²], m_i the lumped mass
        (collective); Q and g are left at x."""
        s = self.system
        self._residual(x)
        s.constraint_jacobian(x).multTranspose(self.mu, self.tmp)
        self.tmp.aypx(-1.0, self.Q)
        self.tmp.pointwiseDivide(self.tmp, self.lumped)
        return self.tmp.norm(PETSc.NormType.INFINITY)

    def destroy(self):
        for obj in (self.ksp, self.saddle, self.A, self.x, self.Q, self.zero,
                    self.tmp, self.g, self.gt, self.mu, self.Mx, self.lumped, self.rhs, self.z):
            obj.destroy()
