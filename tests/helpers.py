"""Small builders shared by the tests (no assertions here)."""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from knitfem.lod.mixed import MixedModel, MixedSpace, VolumeWeights, stitch_mask
from knitfem.model.full import FullModel, Material
from knitfem.knit.pattern import Jersey, jersey_fabric
from knitfem.lod.reduced import Embedding, ReducedModel
from knitfem.lod.volume import BoundingVolume


def jersey(rows=2, cols=2, hold=None):
    return jersey_fabric(Jersey(rows, cols), hold=hold)


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


def hanging_simulation(fabric, out, **options):
    """A backward-Euler (1e-3 s) hanging run of ``fabric``'s full model into
    ``out``, quiet, with the ``Simulation`` options given (output_every,
    checkpoint_every, snapshots, …)."""
    from knitfem.run.simulation import Simulation
    from solvers.integrators import BackwardEuler

    model = FullModel(PETSc.COMM_SELF, fabric, Material())
    return Simulation(model, BackwardEuler(model, 1e-3), out=str(out),
                      scene="hanging", verbose=False, **options)


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
