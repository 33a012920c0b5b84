"""Exact identities of the uniform cubic B-spline basis and quadrature."""

import numpy as np
import pytest

from knitfem.yarn import bspline

U = np.linspace(0, 1, 17)


def test_partition_of_unity():
    assert np.allclose(bspline.basis(U).sum(-1), 1, rtol=0, atol=1e-15)
    for nu in (1, 2, 3):
        # measured 0
        assert np.allclose(bspline.basis(U, nu).sum(-1), 0, atol=0, rtol=5e-15)


def test_basis_nonnegative_and_reproduces_linear():
    B = bspline.basis(U)
    assert B.min() >= 0
    # Σ b_a(u) (k + a − 1) = k + u: the control point index minus one.
    # measured 1.8e-16
    assert np.allclose(B @ (np.arange(4) - 1.0), U, atol=0, rtol=1e-15)
    # measured 0
    assert np.allclose(bspline.basis(U, 1) @ (np.arange(4) - 1.0), 1, atol=0,
                       rtol=1e-15)


@pytest.mark.parametrize("nu", [0, 1, 2])
def test_derivatives_match_finite_differences(nu):
    h = 1e-6
    u = np.linspace(0.1, 0.9, 9)
    fd = (bspline.basis(u + h, nu) - bspline.basis(u - h, nu)) / (2 * h)
    # measured 1.4e-10
    assert np.allclose(fd, bspline.basis(u, nu + 1), rtol=0, atol=2e-9)


def test_c2_continuity_at_junctions():
    # segment k at u = 1 and segment k + 1 at u = 0 share value and derivatives
    P = np.random.default_rng(0).normal(size=(9, 3))
    for nu in (0, 1, 2):
        left = bspline.basis(1.0, nu) @ P[2:6]
        right = bspline.basis(0.0, nu) @ P[3:7]
        assert np.allclose(left, right, atol=0, rtol=5e-15)  # measured 1.6e-16


def test_gauss_exact_to_degree():
    for nq in (1, 2, 3, 4):
        u, w = bspline.gauss(nq)
        for p in range(2 * nq):
            # measured 7.8e-16
            assert np.isclose(np.sum(w * u**p), 1 / (p + 1), rtol=8e-15, atol=0)


def test_junction_symbol_interpolates_harmonic():
    om = 0.7
    i = np.arange(40)
    p = np.cos(om * (i - 1)) / bspline.junction_symbol(om)
    junction = (p[:-2] + 4 * p[1:-1] + p[2:]) / 6      # value at s = k, k = 0…
    # measured 4.4e-15
    assert np.allclose(junction, np.cos(om * np.arange(38)), atol=0, rtol=5e-14)
