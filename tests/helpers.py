"""Small builders shared by the tests (no assertions here)."""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from knitfem.knit.fabric import Fabric
from knitfem.lod.mixed import MixedModel, MixedSpace, VolumeWeights, stitch_mask
from knitfem.model.full import FullModel, Material
from knitfem.knit.pattern import Jersey, jersey_fabric
from knitfem.lod.reduced import Embedding, ReducedModel
from knitfem.lod.volume import BoundingVolume


def jersey(rows=2, cols=2, hold=None):
    return jersey_fabric(Jersey(rows, cols), hold=hold)


def shaped(stitches, hold=None):
    """A jersey whose course f has ``stitches[f]`` stitches, left-aligned (a
    shaped piece: yarns of their own lengths). Course f is the first
    8 c_f + 3 control points of the widest course's curve, and keeps the
    interlocks of the stitches both its neighbours have; "top" holds the
    heads of the top course."""
    c = np.asarray(stitches)
    j = Jersey(len(c), c.max())
    ya, sa, yb, sb = jersey_fabric(j).contacts
    keep = (sa < 8 * c[ya]) & (sb < 8 * c[yb])
    fab = Fabric([j.control_points(f)[:8 * n + 3] for f, n in enumerate(c)],
                 j.radius, contacts=(ya[keep], sa[keep], yb[keep], sb[keep]))
    if hold == "top":
        fab.fixed = (np.full(c[-1], len(c) - 1), j.heads(len(c) - 1)[:c[-1]])
    return fab


def two_courses_one_yarn(cols, hold=None):
    """A three-course jersey whose courses 0 and 1 are one yarn, as a flat
    knitting machine's carrier lays them: course 0, a turn at the right
    selvedge, course 1 knitted back (its control points reversed: the same
    curve run backwards, s ↦ n − 3 − s); course 2 is a yarn of its own.
    "top" holds the heads of course 2."""
    j = Jersey(3, cols)
    P = [j.control_points(f) for f in range(3)]
    n = len(P[0])
    ya, sa, yb, sb = jersey_fabric(j).contacts

    def joined(course, s):
        back = course == 1
        return np.where(course == 2, 1, 0), np.where(back, 2 * n - 3 - s, s)

    fab = Fabric([np.concatenate([P[0], P[1][::-1]]), P[2]], j.radius,
                 course=np.repeat([0, 1, 2], n),
                 contacts=(*joined(ya, sa), *joined(yb, sb)))
    if hold == "top":
        fab.fixed = (np.ones(cols, int), j.heads(2))
    return fab


def models(comm, fabric, material=None, lod=(5, 5)):
    """(full, reduced) models of a fabric; the volume is a box around it."""
    full = FullModel(comm, fabric, material or Material())
    volume = BoundingVolume.around(fabric.X.reshape(-1, 3), *lod, margin=fabric.radius)
    return full, ReducedModel(full, Embedding(comm, full.layout, fabric, volume))


def mixed(full, red, mask):
    """The mixed model of (full, reduced) with the full points ``mask``."""
    weights = VolumeWeights(full.fabric, red.embedding.volume)
    return MixedModel(full, MixedSpace(full.comm, full.layout, weights, mask))


def region(full, red, regions):
    """Full points of stitch regions, widened to whole volume patches."""
    w = VolumeWeights(full.fabric, red.embedding.volume)
    return w.patch_mask(w.patches_of(stitch_mask(full.fabric, regions)))


def gather(comm, vec):
    """The whole vector on every rank, as a numpy array."""
    return np.concatenate(comm.tompi4py().allgather(vec.getArray(readonly=True)))


def run(system, integrator_cls, dt, nsteps, v0=None):
    """Integrate from rest (or from the velocity v0, a numpy array of all
    coordinates); returns the integrator, the final state and velocity Vecs."""
    integ = integrator_cls(system, dt)
    x, v = system.rest_state(), system.rest_state()
    v.zeroEntries()
    if v0 is not None:
        lo, hi = v.getOwnershipRange()
        v.getArray()[:] = v0[lo:hi]
    for n in range(nsteps):
        integ.step(n * dt, x, v)
    return integ, x, v


COMM = PETSc.COMM_WORLD


def steps_from_start(system, nsteps=5, dt=1e-3):
    """``nsteps`` backward-Euler steps from the start state at rest: the
    state, E_el there and max |g| (0 without constraints)."""
    from solvers.integrators import BackwardEuler

    x = system.start_state()
    v = x.duplicate()
    v.zeroEntries()
    integ = BackwardEuler(system, dt)
    for n in range(nsteps):
        integ.step(n * dt, x, v)
    g = system.C.createVecLeft()
    system.constraint_residual(x, g)
    worst = g.norm(PETSc.NormType.INFINITY) if g.getSize() else 0.0
    return x, system.elastic_energy(x), worst


def to_scipy(A):
    """The local rows of a PETSc AIJ matrix as a scipy CSR matrix."""
    indptr, indices, values = A.getValuesCSR()
    return sp.csr_matrix((values, indices, indptr),
                         shape=(len(indptr) - 1, A.getSize()[1]))


def energies(model, x, v):
    """(T + E + V_g, T): kinetic ½ vᵀMv, elastic E(x), gravity −Q_gᵀx."""
    Mv = v.duplicate()
    model.M.mult(v, Mv)
    kinetic = 0.5 * v.dot(Mv)
    Mv.destroy()
    return kinetic + model.elastic_energy(x) - model.Qg.dot(x), kinetic


def hanging_simulation(fabric, out, contacts="fixed", **options):
    """A backward-Euler (1e-3 s) hanging run of ``fabric``'s full model
    (with ``contacts`` crossings) into ``out``, quiet, with the
    ``Simulation`` options given (output_every, checkpoint_every,
    snapshots, …)."""
    from knitfem.run.simulation import Simulation
    from solvers.integrators import BackwardEuler

    model = FullModel(PETSc.COMM_SELF, fabric, Material(), contacts=contacts)
    return Simulation(model, BackwardEuler(model, 1e-3), out=str(out),
                      scene="hanging", verbose=False, **options)


def state(model, X):
    """The local part of all control points X (N, 3) as a Vec."""
    x = model.rest_state()
    lay = model.layout
    x.getArray()[:] = np.asarray(X).reshape(-1, 3)[lay.cp_start:lay.cp_end].ravel()
    return x


def central(f, x, dx, h=1.0):
    """(f(x + h dx) − f(x − h dx)) / 2h for a Vec-valued f."""
    xp, xm = x.duplicate(), x.duplicate()
    xp.waxpy(h, dx, x)
    xm.waxpy(-h, dx, x)
    return (f(xp) - f(xm)) / (2 * h)


def constraints_off_rest(m, shift, mu_all, weight=0.5):
    """(g, K + w Σμ∇²g) of a full model at its start state moved by ``shift``
    (all coordinates), with the multipliers ``mu_all`` (all rows); C(ε) is
    evaluated too."""
    x = m.start_state()
    lo, hi = x.getOwnershipRange()
    x.getArray()[:] += shift[lo:hi]
    g, mu = m.C.createVecLeft(), m.C.createVecLeft()
    a, b = mu.getOwnershipRange()
    mu.getArray()[:] = mu_all[a:b]
    m.constraint_residual(x, g)
    m.constraint_jacobian(x)
    return g, m.stiffness(x, mu, weight)


def step_potential_slopes(integ, x, z, seed, h=1e-4):
    """A step of the implicit ``integ`` from the state x at rest, its
    unknowns at z (a Vec): the central difference of its objective Φ along
    a random direction d, and F_uᵀ d (``NewtonStepper``)."""
    integ.xn, integ.vn = x.copy(), x.copy()
    integ.vn.scale(0.0)
    integ.coefficients(1e-2)
    F, d = z.duplicate(), z.duplicate()
    integ._residual(None, z, F)
    d.getArray()[:] = 1e-3 * np.random.default_rng(seed).standard_normal(z.getLocalSize())
    phi = []
    for sign in (1, -1):
        zs = z.copy()
        zs.axpy(sign * h, d)
        phi.append(integ._objective(None, zs))
    return (phi[0] - phi[1]) / (2 * h), F.dot(d)


def barrier_differences(model, x, rng):
    """The barrier and friction of ``model`` at the yarn points x against
    central differences along a random direction d: (dP, ∇P·d, K d, the
    gradient's difference), P = E_c + D."""
    b = model.barrier
    indptr3, indices3, _ = model.pattern.blocks3()

    def gradient(y):
        g = np.zeros_like(y)
        b.add_gradient(y, g)
        return g

    slot = model.slot3
    values = np.zeros_like(model.K_values)
    b.add_hessian(x, slot, values)
    K = sp.csr_matrix((values, indices3, indptr3))
    h, d = 1e-3 * b.eps_slip, rng.standard_normal(x.shape)
    total = lambda y: b.energy(y) + b.friction_potential(y)   # noqa: E731
    dP = (total(x + h * d) - total(x - h * d)) / (2 * h)
    fd = (gradient(x + h * d) - gradient(x - h * d)) / (2 * h)
    return dP, np.sum(gradient(x) * d), K @ d.ravel(), fd.ravel()


def curvature_and_force(model, x, dx, seed):
    """With random multipliers μ (``seed``): Σ μ_i ∇²g_i dx, gathered (from
    the tangent with and without its curvature, K(x, μ, 2) − K(x)), and the
    constraint force y ↦ C(y)ᵀμ, gathered, to difference."""
    mu = model.C.createVecLeft()
    lo, hi = mu.getOwnershipRange()
    mu.getArray()[:] = np.random.default_rng(seed).standard_normal(mu.getSize())[lo:hi]
    K0 = model.stiffness(x).copy()
    H = model.stiffness(x, mu, 2.0).copy()
    H.axpy(-1.0, K0)
    Hdx = x.duplicate()
    H.mult(dx, Hdx)
    for A in (K0, H):
        A.destroy()

    def force(y):
        out = y.duplicate()
        model.constraint_jacobian(y).multTranspose(mu, out)
        return gather(COMM, out)

    return gather(COMM, Hdx) / 2.0, force
