"""The reduced model: PtAP, mass, affine reproduction, exactness in range(Γ)."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import COMM, gather, jersey, models, run, to_scipy
from knitfem.model.full import Material
from solvers.integrators import BackwardEuler, SymplecticEuler

SELF = PETSc.COMM_SELF


@pytest.fixture(scope="module")
def pair():
    full, red = models(SELF, jersey(3, 3, hold="top"))
    yield full, red
    red.destroy()
    full.destroy()


def test_ptap_equals_explicit_product(pair):
    full, red = pair
    G, M = to_scipy(red.embedding.Gamma), to_scipy(full.M)
    MV = to_scipy(red.M)
    ref = (G.T @ M @ G).toarray()
    # measured 2.1e-22
    assert np.allclose(MV.toarray(), ref, rtol=0, atol=3e-15 * np.abs(ref).max())
    Gs, m = to_scipy(red.embedding.Gamma_scalar), to_scipy(full.m)
    assert np.allclose(to_scipy(red.m).toarray(), (Gs.T @ m @ Gs).toarray(),
                       rtol=0, atol=3e-15 * np.abs(ref).max())  # measured 2.1e-22
    assert np.array_equal(G.toarray(), np.kron(Gs.toarray(), np.eye(3)))


@pytest.mark.parametrize("dense", [True, False])
def test_reduced_tangent_equals_explicit_product(pair, dense):
    """Γᵀ K Γ, dense (DenseTangent) or by PtAP, at a deformed state."""
    full, red = pair
    alpha = red.rest_state()
    alpha.getArray()[:] += 1e-4 * np.random.default_rng(1).standard_normal(
        alpha.getLocalSize())
    eps = red.full_state(alpha)
    G = to_scipy(red.embedding.Gamma)
    ref = (G.T @ to_scipy(full.stiffness(eps)) @ G).toarray()
    saved, red.K = (red.dense, red.K), None
    if not dense:
        red.dense = None
    K = to_scipy(red.stiffness(alpha)).toarray()
    red.dense, red.K = saved
    # measured 1.1e-11
    assert np.allclose(K, ref, rtol=0, atol=4e-15 * np.abs(ref).max())


@pytest.mark.parametrize("lod", [(5, 5), (6, 7)])
def test_grouped_tangent_equals_ptap(lod):
    """The compiled Γᵀ K Γ (``GroupedTangent``: points grouped by patch, some
    with neighbours in other patches) equals MatPtAP to 1e-12."""
    full, red = models(SELF, jersey(4, 3, hold="top"), lod=lod)
    groups = red.dense.args[5]
    assert len(groups) - 1 > (lod[0] - 3) * (lod[1] - 3)   # boundary groups too
    alpha = red.rest_state()
    alpha.getArray()[:] += 2e-4 * np.random.default_rng(3).standard_normal(
        alpha.getLocalSize())
    K = to_scipy(red.stiffness(alpha)).toarray()
    ref = red.full.stiffness(red.full_state(alpha)).PtAP(red.embedding.Gamma)
    ref = to_scipy(ref).toarray()
    assert np.abs(K - ref).max() <= 9e-15 * np.abs(ref).max()  # measured 8.5e-16
    red.destroy()
    full.destroy()


def test_reduced_forces_equal_projected_full_forces():
    """Q^V = Γᵀ Q(Γα, Γα̇), with damping: the applied forces formed on the
    reduced side (Γᵀ Q_g − c_d M^V α̇) equal the projected full ones."""
    full, red = models(SELF, jersey(3, 3, hold="top"), Material(damping=3.0))
    rng = np.random.default_rng(4)
    alpha, alphadot = red.rest_state(), red.rest_state()
    alpha.getArray()[:] += 1e-4 * rng.standard_normal(alpha.getLocalSize())
    alphadot.getArray()[:] = 1e-2 * rng.standard_normal(alpha.getLocalSize())
    Q, Qf, ref = alpha.duplicate(), full.M.createVecLeft(), alpha.duplicate()
    red.forces(alpha, alphadot, Q)
    full.forces(red.full_state(alpha), red.full_state(alphadot), Qf)
    red.embedding.Gamma.multTranspose(Qf, ref)
    assert np.allclose(Q.getArray(), ref.getArray(), rtol=0,
                       atol=5e-15 * np.abs(ref.getArray()).max())  # measured 5.3e-15
    red.destroy()
    full.destroy()


def test_total_mass_kept(pair):
    full, red = pair
    # measured 3.6e-16
    assert to_scipy(red.m).sum() == pytest.approx(to_scipy(full.m).sum(), rel=5e-15)
    # measured 4.4e-16
    assert np.allclose(to_scipy(red.embedding.Gamma_scalar).sum(1), 1, atol=0,
                       rtol=5e-15)


def test_gamma_reproduces_affine_maps_of_rest_fabric(pair):
    full, red = pair
    A = np.array([[1.1, 0.2, -0.1], [0.05, 0.9, 0.3], [0.0, -0.2, 1.2]])
    b = np.array([1e-3, -2e-3, 5e-4])
    alpha = red.rest_state()
    q = alpha.getArray().reshape(-1, 3)
    eps0 = red.full_state(alpha).getArray().reshape(-1, 3).copy()
    # measured 8.7e-18
    assert np.allclose(eps0, full.fabric.X.reshape(-1, 3), rtol=0, atol=9e-17)
    q[:] = q @ A.T + b
    eps = red.full_state(alpha).getArray().reshape(-1, 3)
    assert np.allclose(eps, eps0 @ A.T + b, rtol=0, atol=6e-17)  # measured 5.2e-18


def test_projection_inverts_embedding(pair):
    full, red = pair
    alpha = red.rest_state()
    alpha.getArray()[:] += 1e-4 * np.random.default_rng(0).normal(size=alpha.getLocalSize())
    back = alpha.duplicate()
    eps = red.full_state(alpha)
    red.project(eps, back)
    # ε = Γα is recovered to round-off (α itself up to M^V's conditioning)
    again = red.full_state(back)
    assert np.allclose(again.getArray(), eps.getArray(), rtol=0,
                       atol=1e-8 * full.fabric.radius)


def test_world_constraints_reduced_to_independent_rows(pair):
    _, red = pair
    # 3 fixed heads on one course: independent in α, and satisfied at rest
    assert red.world_rank <= red.world_rows
    r = red.C.createVecLeft()
    red.C.mult(red.rest_state(), r)
    r.axpy(-1.0, red.d)
    assert r.norm() < 1e-15


@pytest.mark.parametrize("integrator,dt,tol", [(SymplecticEuler, 5e-7, 1e-10),
                                               (BackwardEuler, 1e-3, 1e-8)])
def test_free_fall_and_translation_identical_in_both_models(integrator, dt, tol):
    """A motion in range(Γ) is reproduced exactly by the reduced model.

    Γ must have full column rank (ΓᵀMΓ invertible): a 4×4×2 volume around
    a 3×3 jersey; a 5×5×2 one around 2×2 has more control points than the
    yarns determine, and round-off then grows in the null space."""
    fab = jersey(3, 3)
    full, red = models(COMM, fab, Material(EA=5.0, EI=1e-6), lod=(4, 4))
    n = 3 * fab.npoints
    v0 = np.tile([0.01, 0.02, -0.005], n // 3)              # rigid translation
    _, xf, vf = run(full, integrator, dt, 15, v0)
    nv = 3 * red.embedding.volume.size
    _, xr, vr = run(red, integrator, dt, 15, np.tile([0.01, 0.02, -0.005], nv // 3))
    ef = gather(COMM, xf)
    er = gather(COMM, red.full_state(xr))
    # round-off (explicit) or Newton's tolerance, 1e-9 radii a step (implicit)
    assert np.allclose(ef, er, rtol=0, atol=tol * fab.radius)
    assert np.abs(ef - fab.X.ravel()).max() > 1e-4 * tol ** 0.5  # it did move
