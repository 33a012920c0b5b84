"""Frame-indifferent contacts: g(ε) = 0 under every rigid motion, and the
exact tangent: C = ∂g/∂ε and Σ μ_i ∇²g_i against finite differences. The
model tests run serial and under mpirun (COMM_WORLD)."""

import numpy as np
import pytest

from helpers import COMM, central, curvature_and_force, gather, jersey, state
from knitfem.contact import constraints as cons
from knitfem.model.full import FullModel, Material
from knitfem.cli.scenes import rotation

TURNS = [(90, 0, 0), (0, 45, 0), (0, 0, 45), (30, -60, 120)]


@pytest.fixture(scope="module")
def model():
    m = FullModel(COMM, jersey(4, 3, hold="top"), Material())
    yield m
    m.destroy()


def residual(model, x):
    g = model.C.createVecLeft()
    model.constraint_residual(x, g)
    return gather(COMM, g).reshape(-1, 3)


def test_contacts_hold_at_rest_and_under_rigid_motions(model):
    fab = model.fabric
    contact = model.constraint_kind == "contact"
    assert contact.sum() == 2 * 3 * (4 - 1)
    # measured 5.8e-21 m (1 and 2 ranks)
    assert np.abs(residual(model, model.rest_state())).max() < 5e-20
    centre = fab.X.reshape(-1, 3).mean(axis=0)
    for turn in TURNS:
        R = rotation(turn)
        X = (fab.X - centre) @ R.T + centre + np.array([0.3, -0.1, 0.2])
        g = residual(model, state(model, X))
        # contacts do not care; the fixed points (world holds) do
        assert np.abs(g[contact]).max() < 1e-15
        assert np.abs(g[~contact]).max() > 1e-3


def test_contacts_resist_relative_motion(model):
    """Yarn 1 shifted: its contacts with yarns 0 and 2 open by about the
    shift, all others stay closed."""
    fab = model.fabric
    X = fab.X.copy()
    shift = np.array([1e-4, -2e-4, 5e-5])
    X[fab.yarn_of == 1] += shift
    g = residual(model, state(model, X))
    ya, _, yb, _ = fab.contacts
    touched = np.concatenate([(ya == 1) | (yb == 1), np.zeros(len(g) - len(ya), bool)])
    assert np.abs(g[~touched]).max() < 5e-20  # measured 5.4e-21 m (1 and 2 ranks)
    assert np.all(np.linalg.norm(g[touched], axis=1) > 0.1 * np.linalg.norm(shift))


def random_state(model, seed, amplitude=2e-4):
    rng = np.random.default_rng(seed)
    X = model.fabric.X + amplitude * rng.standard_normal(model.fabric.X.shape)
    return state(model, X)


def test_jacobian_is_the_derivative_of_g(model):
    x = random_state(model, 1)
    dx = random_state(model, 2)
    dx.axpy(-1.0, model.rest_state())
    Cdx = model.C.createVecLeft()
    model.constraint_jacobian(x).mult(dx, Cdx)
    # g is quadratic: the central difference is exact up to round-off
    fd = central(lambda y: residual(model, y).ravel(), x, dx)
    exact = gather(COMM, Cdx)
    assert np.abs(fd - exact).max() <= 2e-14 * np.abs(exact).max()  # measured 2e-15


def test_curvature_is_the_derivative_of_the_constraint_force(model):
    """K(x, μ) − K(x) = Σ μ_i ∇²g_i = ∂(C(x)ᵀμ)/∂x, exactly (C is linear)."""
    x = random_state(model, 3)
    dx = random_state(model, 4)
    dx.axpy(-1.0, model.rest_state())
    exact, force = curvature_and_force(model, x, dx, 5)
    fd = central(force, x, dx)
    assert np.abs(fd - exact).max() <= 3e-14 * np.abs(exact).max()  # measured 2.4e-15
    assert np.abs(exact).max() > 0


def test_jacobian_keeps_its_pattern(model):
    """One nonzero pattern for the run: MUMPS analyses once."""
    model.constraint_jacobian(model.rest_state())
    state0 = model.C.getInfo()["nz_used"]
    model.constraint_jacobian(random_state(model, 6))
    assert model.C.getInfo()["nz_used"] == state0


def test_contact_invariants_numpy_reference():
    """``Contacts`` on its own: gradients and Hessians against central
    differences of values, on random points."""
    fab = jersey(3, 2)
    contacts, _ = cons.build(fab)
    rng = np.random.default_rng(7)
    P = fab.X.reshape(-1, 3)[contacts.cols] + 1e-4 * rng.standard_normal(
        contacts.cols.shape + (3,))
    dP = rng.standard_normal(P.shape)
    h = 1e-3
    fd = (contacts.values(P + h * dP) - contacts.values(P - h * dP)) / (2 * h)
    grad = contacts.gradients(P)
    # measured 8.2e-15
    assert np.allclose(fd, np.einsum("njkd,nkd->nj", grad, dP), rtol=9e-14, atol=0)
    fdg = (contacts.gradients(P + h * dP) - contacts.gradients(P - h * dP)) / (2 * h)
    hess = contacts.hessians()
    # g quadratic: exact up to round-off (measured 5.3e-16 of the largest)
    assert np.allclose(fdg, np.einsum("njkl,nld->njkd", hess, dP), rtol=0,
                       atol=5e-15 * np.abs(fdg).max())


def test_jacobian_rows_are_independent(model):
    """C at rest has full row rank (no zero pivot in the saddle point)."""
    if COMM.size > 1:
        pytest.skip("dense rank on one process")
    C = model.constraint_jacobian(model.rest_state())
    from helpers import to_scipy

    s = np.linalg.svd(to_scipy(C).toarray(), compute_uv=False)
    assert s.min() > 1e-6 * s.max()
