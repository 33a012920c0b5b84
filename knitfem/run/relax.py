"""A knit relaxed from its geometric template: a naturally straight yarn.

A real yarn is straight at rest: the loops of a knit are bent, and held so
by the yarns they interlock with. The knit's shape is the equilibrium of
that bending against the crossings (and, where they touch, the yarns'
contact), not the template's. ``natural_fabric`` makes the template's
fabric a natural one: its rest X is the template scaled uniformly so that
the yarn length a stitch is ℓ (``-knit_loop_length``; X then only gives the
rest line element |X'| and the mass), its natural curvature is zero, its
crossings hold the two centrelines 2r apart (touching), and it starts from
the template scaled by (s_x, s_y, s_z) along its course, wale and thickness
directions (``-knit_template_scale``). ``relax`` finds its static
equilibrium, free and without gravity, by Newton with pseudo-transient
continuation (``solvers.statics``).

A relaxed knit is written as ``relaxed.h5`` (``save`` / ``load``): the rest
X, the relaxed control points, the crossings' parameters and separation,
the yarn radius, the knit's size and shape and its loop length. A scene
started from it (``-knit_rest FILE``) builds the same jersey with the
relaxed knit as its start state (``RelaxedKnit.apply``); the full model keeps
the natural yarn, so the start is in equilibrium up to the relaxation's
residual, prestress included. A reduced or mixed model drops the crossings
(the embedding holds the stitches), which alone balance that prestress: it
takes the relaxed knit as its stress-free rest instead (``stress_free``).
"""

from dataclasses import dataclass, replace

import h5py
import numpy as np

from knitfem.knit.measure import (curl, loop_length, munden, spacings,
                                  surface_normals)
from knitfem.yarn import bspline

__all__ = ["RelaxedKnit", "natural_fabric", "yarn_lengths", "stitch_length",
           "shortest_loop",
           "knit_measures", "Ramp", "Relaxation",
           "stress_free", "VERSION"]

VERSION = 2
"""Layout of relaxed.h5."""
FIRST = 0.1
"""The first load step's residual acceleration, a fraction of the last's."""
QUANTUM = 1e-9
"""The grid [m] the first load step's minimum is rounded to."""


def yarn_lengths(fabric, P=None, nq=8):
    """Length ∫|P'| ds (nyarn,) of every yarn of ``fabric`` with control
    points P (N, 3; default its rest X), by nq-point Gauss a segment."""
    P = fabric.X if P is None else np.asarray(P, dtype=float).reshape(-1, 3)
    yarn = fabric.segments(0, fabric.nyarn)[0]
    conn = fabric.connectivity(0, fabric.nyarn)
    uq, wq = bspline.gauss(nq)
    d = np.einsum("qa,sad->sqd", bspline.basis(uq, 1), P[conn])
    return np.bincount(yarn, np.linalg.norm(d, axis=-1) @ wq,
                       minlength=fabric.nyarn)


def stitch_length(jersey, fabric, P=None):
    """Yarn length a stitch ℓ [m] of the jersey's ``fabric`` at control points
    P (default: its rest X)."""
    return loop_length(yarn_lengths(fabric, P), np.full(fabric.nyarn, jersey.cols))


def shortest_loop(jersey, fabric, samples=8):
    """The shortest loop length [m] the template ``fabric`` of the jersey
    can be scaled to with no two yarns closer than 2r: ℓ₀ 2r / d, ℓ₀ its
    own loop length and d the smallest distance between its yarns (or
    parts of one yarn more than 8 r apart along it; ``gaps.YarnGaps``),
    its crossings' 1.042 × 2r included. Below it the natural knit's rest
    X, the spring a relaxation starts with, has yarns through one
    another."""
    from knitfem.contact.gaps import YarnGaps

    S = fabric.curves(fabric.X).samples(samples)
    r = fabric.radius
    d = YarnGaps(S, r).pairs(S.points, 4.0 * r)[2]
    return stitch_length(jersey, fabric) * 2 * r / (d.min() if len(d) else 2 * r)


def natural_fabric(jersey, fabric, length=None, scale=(1.0, 1.0, 1.0)):
    """``fabric`` (the jersey's template) as a naturally straight yarn of
    ``length`` a stitch (default: the template's): its rest X the template
    scaled uniformly to that length, its start that rest scaled by
    ``scale`` along the fabric's course, wale and thickness directions about
    its centroid (the yarn at its rest length where ``scale`` is 1: the
    template at its own size, 14 % short of a seed's loop length, started a
    jersey with 3 J of compression, and its first load step buckled it into
    contact with no descent direction); crossings held 2r apart; the yarn
    contact's rest gaps the template's at its own size
    (``Fabric.contact_X``: scaled down to a shorter loop, its gaps would
    close and the contact leave those pairs out)."""
    ell = stitch_length(jersey, fabric)
    centre = fabric.X.mean(axis=0)
    F = fabric.frame
    X = (fabric.X - centre) * ((length or ell) / ell) + centre
    S = F @ np.diag(scale) @ F.T
    return replace(fabric, X=X, start_X=(X - centre) @ S.T + centre,
                   natural=True, separation=2 * fabric.radius, contact_X=fabric.X)


class Ramp:
    """The natural knit's rest quantities taken to its own (λ = 1) linearly
    in λ: the rest line element |X'| at every quadrature point from the
    start state x0's (λ = 0: the start is stretch-free, whatever its
    template scale or loop length), and every crossing's held separation
    (and, for a fixed crossing, its two tangential invariants) from the
    natural rest X's, the template's at the loop length (λ = 0: X keeps its
    crossings exactly). The crossings' path does not depend on the start's
    geometry: a scaled start is drawn onto them (``Relaxation``). The mass
    stays the rest's."""

    def __init__(self, system, x0):
        el, X0 = system.elements, system.fabric.X
        self.el, self.sets = el, []
        start = np.linalg.norm(el.tangents(system.yarn_points(x0))[:, :, 0], axis=-1)
        self.jac = (start, el.jac.copy())
        self.end = el.Xp2.copy(), el.W.copy()
        cons = system.constraints
        for part in (cons.local, cons.reaching):
            g = part.values(X0[part.cols])
            if hasattr(part, "rest"):            # fixed: g = s (u·v − c)
                self.sets.append((part.rest, g / part.scale + part.rest,
                                  part.rest.copy()))
            else:                                # sliding: g = (|r|² − δ²)/2δ
                d = part.delta
                self.sets.append((d, np.sqrt(2 * d * g[:, 0] + d * d), d.copy()))

    def set(self, lam, lengths=None):
        """Rest quantities at λ, the line elements at ``lengths`` (default λ)
        (written into the model's arrays in place: the kernels and
        constraints read them there)."""
        el = self.el
        mu = lam if lengths is None else lengths
        jac = (1 - mu) * self.jac[0] + mu * self.jac[1]
        el.jac[:] = jac
        el.Xp2[:], el.W[:] = (jac * jac, el.weights * jac) if mu < 1 else self.end
        for target, start, end in self.sets:
            target[:] = (1 - lam) * start + lam * end


class Relaxation:
    """A relaxation in ``steps`` load steps, for ``run.simulation.Simulation``
    as its integrator over the pseudo-time t ∈ [0, 1]: the step to t takes the
    rest quantities to λ = t (``Ramp``) and the knit to its constrained
    energy minimum there (``solvers.statics_descent``), to a residual
    acceleration of ``accel`` [m/s²] at λ = 1 and of 10³ accel before. The
    steps before the last add a spring ½ c_k |ε − X|²_M to the natural rest
    X (the template at the loop length asked), c_k = c₀ 100^(−k) for step
    k = 0, 1, …, c₀ = 10 EI / (ρ r⁴) (ten times the bending stiffness of a
    wavelength of a yarn radius): the first step's minimum, X's shape with
    the crossings X holds, is unique, so that a start far from X (a
    stretched template) is drawn to the state the template's own reaches
    there and then let go along the same path, to the same minimum (the
    yarn contact makes the knit's more than one: the 5×5 jersey started
    stretched 20 % along its wales ended with k_w 4.1 % off the template's
    when the crossings started from the start's own, and 8 % with c₀ 100
    times weaker too; now they agree to round-off). The velocity stays
    zero.

    Once the spring is weak the knit has many equilibria and the path to
    them branches: a 12×12 jersey started from the template and from the
    template stretched 20 % were 2·10⁻⁴ r apart after the third step and 61 r
    apart at the end (k_w 24 % apart). So the path after the first step is
    made a function of that step's minimum alone: it is converged to
    ``FIRST`` × accel (10⁻⁵ m/s², ten times the round-off of the residual;
    Newton's last steps, quadratic under c₀'s spring, leave the state
    within ~10⁻¹⁶ m of its minimum), rounded to a grid of ``QUANTUM`` =
    10⁻⁹ m (2·10⁻⁶ r, far below any figure a relaxation reports), and the
    solver and the yarn contact start afresh from it (``forget_start``):
    two starts then share every bit of the path after it, unless one of the
    ~10⁴ coordinates lies within round-off of a grid line (a chance of about
    10⁻⁷ each)."""

    name = "relax"

    def __init__(self, system, steps=5, accel=1e-4):
        from solvers.statics_descent import ConstrainedDescent

        self.system, self.dt, self.accel = system, 1.0 / steps, accel
        x0 = system.start_state()
        self.ramp = Ramp(system, x0)
        x0.destroy()
        self.solver = ConstrainedDescent(system)
        m, r = system.material, system.fabric.radius
        self.guide = 10.0 * m.EI / (m.rho * r**4)
        self.target = system.rest_state()

    def step(self, t, x, v, t_stop=None):
        """Load step from t to min(t + dt, t_stop, 1); the stats of
        ``Simulation``. Without t_stop (the step from rest that a restart
        takes and throws away, for a time integrator's solver choices) it
        moves nothing."""
        if t_stop is None:
            return dict(dt=0.0, newton=0, ksp=0, rejected=0, linear_failures=0)
        lam = min(t + self.dt, t_stop, 1.0)
        if 1.0 - lam < 1e-9:
            lam = 1.0
        self.ramp.set(lam, lengths=1.0)
        k = round(t / self.dt)
        self.solver.guide_to(self.target, 0.0 if lam == 1.0 else
                             self.guide * 100.0 ** (-k))
        before = dict(self.solver.stats)
        self.solver.minimize(x, self.accel * (1.0 if lam == 1.0 else
                                              FIRST if k == 0 else 1e3))
        if k == 0 and lam < 1.0:
            self.forget_start(x)
        v.zeroEntries()
        st = {k: self.solver.stats[k] - before[k] for k in before}
        return dict(dt=lam - t, newton=st["newton"], ksp=st["ksp"],
                    rejected=st["rejected"], linear_failures=0)

    def forget_start(self, x):
        """After the first load step: x rounded to a grid of ``QUANTUM``
        metres and the solver and the yarn contact started afresh there, so
        that the rest of the path is a function of that rounded state alone
        (class docstring)."""
        a = x.getArray()
        a[:] = np.round(a / QUANTUM) * QUANTUM
        self.system.forget_path(x)
        self.solver.start_afresh(x)

    def state(self):
        """The multipliers (this rank's), the shift and its floor, for a
        checkpoint."""
        return dict(mu=self.solver.mu.getArray(readonly=True).copy(),
                    sigma=self.solver.sigma or 0.0, floor=self.solver.floor)

    def set_state(self, state):
        self.solver.mu.getArray()[:] = state["mu"]
        self.solver.sigma = float(state["sigma"]) or None
        self.solver.floor = float(state["floor"])


def stress_free(fabric):
    """The fabric with its start state as a stress-free rest (curvature
    and lengths its own): how a reduced model holds a relaxed knit."""
    if fabric.start_X is None:
        return fabric
    return replace(fabric, X=fabric.start_X, start_X=None, natural=False,
                   separation=None, contact_X=None)


def knit_measures(jersey, fabric, P):
    """Textile measures of the knit at control points P (N, 3):
    loop length, course and wale spacings, Munden's constants and the curl
    of each edge (``knit.measure``)."""
    P = np.asarray(P, dtype=float).reshape(-1, 3)
    ell = stitch_length(jersey, fabric, P)
    yarn = np.repeat(np.arange(fabric.nyarn), jersey.cols)
    cols, b = fabric.point_rows(yarn, np.tile(jersey.heads(0), fabric.nyarn))
    heads = np.einsum("na,nai->ni", b, P[cols]).reshape(fabric.nyarn, jersey.cols, 3)
    # in the knit's tangent plane at each head, however it curls
    cs, ws = spacings(heads, surface_normals(heads))
    kc, kw, ks = munden(ell, cs, ws)
    rec = dict(loop_length_m=ell, course_spacing_m=cs, wale_spacing_m=ws,
               k_c=kc, k_w=kw, k_s=ks)
    if not fabric.closed.any() and fabric.nyarn > 2 and jersey.cols > 2:
        rec["curl"] = curl(heads, fabric.frame[:, 2], fabric.radius)
    return rec


@dataclass
class RelaxedKnit:
    """A relaxed knit as ``relaxed.h5`` holds it (module docstring)."""

    rows: int
    cols: int
    shape: str
    radius: float
    rest: np.ndarray
    positions: np.ndarray
    contacts: tuple
    separation: float
    loop_length: float
    source: str = ""
    yarn_contact: bool = True

    def save(self, path):
        """Write relaxed.h5 (call on one rank)."""
        from knitfem.io import atomic_write, write_hdf5

        def fill(f):
            f.attrs.update(version=VERSION, rows=self.rows, cols=self.cols,
                           shape=self.shape, radius=self.radius,
                           separation=self.separation, loop_length=self.loop_length,
                           yarn_contact=self.yarn_contact)
            f["rest"], f["positions"] = self.rest, self.positions
            for name, values in zip(("yarn_a", "s_a", "yarn_b", "s_b"),
                                    self.contacts):
                f[f"contacts/{name}"] = values

        atomic_write(path, lambda tmp: write_hdf5(tmp, fill))

    @classmethod
    def load(cls, path):
        """Read relaxed.h5; ValueError with what is wrong if it is not one."""
        import os

        if not os.path.isfile(path):
            raise ValueError("no such file (knitfem relax -o DIR writes "
                             "DIR/relaxed.h5)")
        try:
            with h5py.File(path, "r") as f:
                a = f.attrs
                if a.get("version") != VERSION:
                    raise ValueError("not a relaxed knit of this version "
                                     "(knitfem relax writes one)")
                return cls(int(a["rows"]), int(a["cols"]), str(a["shape"]),
                           float(a["radius"]), f["rest"][()], f["positions"][()],
                           tuple(f[f"contacts/{n}"][()] for n in
                                 ("yarn_a", "s_a", "yarn_b", "s_b")),
                           float(a["separation"]), float(a["loop_length"]),
                           source=str(path), yarn_contact=bool(a["yarn_contact"]))
        except (OSError, KeyError) as err:
            raise ValueError(f"cannot read a relaxed knit ({err})") from None

    def check(self, jersey):
        """ValueError unless ``jersey`` is the knit this one relaxed."""
        mine = (self.rows, self.cols, self.shape, self.radius)
        theirs = (jersey.rows, jersey.cols, jersey.knit, jersey.radius)
        if mine != theirs:
            raise ValueError(
                f"the relaxed knit is {self.rows}x{self.cols} {self.shape} of radius "
                f"{self.radius:g}; the options ask for {jersey.rows}x{jersey.cols} "
                f"{jersey.knit} of radius {jersey.radius:g}: give the same "
                f"-knit_rows, -knit_cols, -knit_shape and -knit_radius")

    def apply(self, fabric):
        """The jersey's template ``fabric`` started from this relaxed knit:
        a natural yarn with the relaxed rest lengths and crossings (the
        yarn contact's rest gaps the template's, as in ``natural_fabric``)."""
        return replace(fabric, X=np.reshape(self.rest, (-1, 3)),
                       start_X=np.reshape(self.positions, (-1, 3)), natural=True,
                       contact_X=fabric.X,
                       contacts=self.contacts, separation=self.separation)
