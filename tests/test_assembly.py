"""The full model's constant blocks assembled in PETSc: the mass."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import to_scipy
from knitfem.yarn import bspline
from knitfem.knit.fabric import Fabric
from knitfem.model.full import FullModel, Material
from knitfem.knit.pattern import Jersey, jersey_fabric

COMM = PETSc.COMM_SELF


@pytest.fixture(scope="module")
def jersey_model():
    fab = jersey_fabric(Jersey(3, 2, radius=1e-3), hold="top")
    model = FullModel(COMM, fab, Material(rho=2e-5))
    yield fab, model
    model.destroy()


def test_total_mass_is_rho_times_rest_length(jersey_model):
    fab, model = jersey_model
    m = to_scipy(model.m)
    total = m.sum()
    # partition of unity: Σ_ij m_ij = ρ Σ_q w_q |X'| exactly
    # measured 0
    assert np.isclose(total, 2e-5 * model.elements.rest_length(), rtol=5e-15, atol=0)
    # and the quadrature length is the arc length of the rest splines
    u, w = bspline.gauss(12)
    length = 0.0
    for f, nseg in enumerate(fab.yarn_nseg):
        P = fab.yarn(f)
        s = (np.arange(nseg)[:, None] + u).ravel()
        length += np.sum(np.tile(w, nseg)
                         * np.linalg.norm(bspline.curve_points(P, s, 1), axis=-1))
    assert np.isclose(total, 2e-5 * length, rtol=3e-5, atol=0)  # measured 2.7e-6


def test_straight_yarn_mass_exact():
    L, n = 0.3, 20
    X = np.zeros((1, n, 3))
    X[0, :, 0] = np.linspace(0, L, n)          # equally spaced: |X'| constant
    model = FullModel(COMM, Fabric(X, 1e-3), Material(rho=0.5))
    length = L * (n - 3) / (n - 1)              # the spline spans s ∈ [0, n − 3]
    # measured 2.1e-16
    assert np.isclose(to_scipy(model.m).sum(), 0.5 * length, rtol=2e-15, atol=0)
    model.destroy()


def test_mass_symmetric_positive_definite_and_banded(jersey_model):
    fab, model = jersey_model
    m = to_scipy(model.m).toarray()
    assert np.allclose(m, m.T, rtol=0, atol=3e-15 * np.abs(m).max())  # measured 6.6e-24
    assert np.linalg.eigvalsh(m).min() > 0
    i, j = np.nonzero(m)
    assert np.abs(i - j).max() == 3             # 7 diagonals a yarn
    M = to_scipy(model.M).toarray()
    assert np.array_equal(M, np.kron(m, np.eye(3)))
    assert model.M.getBlockSize() == 3


def test_diagonal_block_slots_are_the_full_slots_diagonal_components():
    """``blocks3(diagonal=...)`` gives, for those element sets, the slots of
    entries (3a + d, 3b + d) that the full 3×3 slots give, −1 kept where a
    row is not local."""
    from knitfem.model.assembly import ElementPattern

    rng = np.random.default_rng(3)
    conns = [np.sort(rng.choice(20, (6, 4)), axis=1), rng.choice(20, (5, 8))]
    pattern = ElementPattern(conns, 5, 10)               # rows 5..14 local
    _, _, (yarn, contacts) = pattern.blocks3()
    ptr, ind, (yarn_d, contacts_d) = pattern.blocks3(diagonal=(1,))
    assert np.array_equal(yarn_d, yarn) and contacts_d.shape == (5, 3, 8, 8)
    d = np.arange(3)
    full = contacts.reshape(5, 8, 3, 8, 3)[:, :, d, :, d].transpose(1, 0, 2, 3)
    assert np.array_equal(contacts_d, full)
    assert (contacts_d == -1).any() and (contacts_d >= 0).any()
    rows = np.repeat(np.arange(len(ptr) - 1), np.diff(ptr))
    kept = contacts_d >= 0
    # a kept slot of (3a + d, 3b + d): row 3·(conn[a] − 5) + d, column 3·conn[b] + d
    c = conns[1]
    row = 3 * (c[:, None, :, None] - 5) + d[None, :, None, None]
    col = 3 * c[:, None, None, :] + d[None, :, None, None]
    at = contacts_d[kept]
    assert np.array_equal(rows[at], np.broadcast_to(row, kept.shape)[kept])
    assert np.array_equal(ind[at], np.broadcast_to(col, kept.shape)[kept])


def test_curvature_adds_each_contacts_hessian_sum_at_its_diagonal_slots():
    """``Curvature.add``: entry (3k + d, 3l + d) of contact c gets
    w Σ_j μ_cj h_cjkl at its slot, summed where contacts share a slot and
    left out where the slot is −1."""
    from knitfem.contact.constraint_assembly import Curvature

    rng = np.random.default_rng(5)
    n, nnz = 4, 300
    h = rng.standard_normal((n, 3, 8, 8))
    slots = rng.integers(0, nnz, (n, 3, 8, 8))
    slots[rng.random(slots.shape) < 0.2] = -1
    mu, w = rng.standard_normal(3 * n), 0.7
    values = rng.standard_normal(nnz)
    expect = values.copy()
    m = np.einsum("cj,cjkl->ckl", mu.reshape(n, 3), h)
    keep = slots >= 0
    np.add.at(expect, slots[keep], w * np.broadcast_to(m[:, None], slots.shape)[keep])
    Curvature(h, slots, nnz).add(mu, w, values)
    assert np.allclose(values, expect, rtol=0, atol=5e-15)  # measured 8.9e-16
