"""Yarn elements: mass, strain, curvature, and the exact gradient and Hessian.

The rest yarns are perturbed helices (curved and torsioned, so that κ₀ > 0 and
both energies matter); the current configuration is a random perturbation of
the rest. Gradients are checked against central differences of the energy,
Hessians against central differences of the gradient, for both kernels
(``knitfem.yarn.kernels``: the numpy reference and the compiled loops).
"""

import numpy as np
import pytest

from knitfem.yarn import bspline
from knitfem.yarn.kernels import KINDS, yarn_kernels
from knitfem.yarn.elements import YarnElements, chain_rule, stretch_terms

RHO, EA, EI = 0.3, 10.0, 1e-2
NCP = 10
ENERGIES = {"stretch": (EA, 0.0), "bend": (0.0, EI), "both": (EA, EI)}


def chain(ncp, nyarn=1):
    """Connectivity of nyarn concatenated yarns of ncp control points each."""
    first = np.arange(nyarn)[:, None] * ncp + np.arange(ncp - 3)
    return (first[..., None] + np.arange(4)).reshape(-1, 4)


def helix(ncp, seed, nyarn=1):
    """Rest control points of nyarn noisy helices (radius 1, pitch 1.9)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 3.0 * np.pi, ncp)
    one = np.c_[np.cos(t), np.sin(t), 0.3 * t]
    X = np.concatenate([one + [0.0, 3.0 * k, 0.0] for k in range(nyarn)])
    return X + 0.05 * rng.normal(size=X.shape)


def deformed(X, seed, amount=0.1):
    return X + amount * np.random.default_rng(seed).normal(size=X.shape)


def yarn(energy="both", nyarn=2, seed=0):
    X = helix(NCP, seed, nyarn)
    return YarnElements(X, chain(NCP, nyarn), RHO, *ENERGIES[energy])


def dense_hessian(y, x, kind="numpy", xref=None):
    """Assembled ∂²E/∂p² (3 ncp, 3 ncp) from the element Hessians (with
    ``xref``, the MIP Newton matrix linearised from xref)."""
    K = np.zeros((3 * y.ncp, 3 * y.ncp))
    np.add.at(K, (y.dof[:, :, None], y.dof[:, None, :]),
              yarn_kernels(y, kind).element_hessian(x, xref))
    return K


def gradient(y, kind="numpy"):
    """x ↦ assembled ∂E/∂p (ncp, 3) by the kernels of ``kind``."""
    kernels = yarn_kernels(y, kind)

    def g(x):
        out = np.zeros((y.ncp, 3))
        kernels.add_gradient(x, out)
        return out

    return g


def central_differences(f, x, h):
    """Columns (f(x + h e_k) − f(x − h e_k)) / 2h over every coordinate k."""
    cols = []
    for k in range(x.size):
        d = np.zeros(x.size)
        d[k] = h
        d = d.reshape(x.shape)
        cols.append((np.asarray(f(x + d)) - np.asarray(f(x - d))).ravel() / (2 * h))
    return np.array(cols).T


def rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.sign(np.linalg.det(q))


def relative(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


# -- mass ---------------------------------------------------------------------
def test_mass_sums_to_density_times_rest_length():
    y = yarn()
    m = y.mass_elements()
    assert m.shape == (y.ne, 4, 4)
    assert np.isclose(m.sum(), RHO * y.rest_length(), rtol=1e-15, atol=0)  # measured 0
    # entries up to 0.07: measured 6.9e-18
    assert np.allclose(m, m.transpose(0, 2, 1), rtol=0, atol=5e-17)
    assert np.linalg.eigvalsh(m).min() > 0


def test_straight_yarn_total_mass():
    h, ncp = 0.2, 12
    direction = np.array([1.0, 2.0, -2.0]) / 3.0
    X = np.arange(ncp)[:, None] * h * direction + [0.5, -1.0, 2.0]
    y = YarnElements(X, chain(ncp), RHO, EA, EI)
    L = (ncp - 3) * h
    assert np.isclose(y.rest_length(), L, rtol=1e-15, atol=0)  # measured 1.2e-16
    # assembled scalar mass m_ij: every entry lands in some row, total ρL
    rows = np.broadcast_to(y.conn[:, :, None], (y.ne, 4, 4))
    row_sums = np.bincount(rows.ravel(), weights=y.mass_elements().ravel(),
                           minlength=ncp)
    assert np.isclose(row_sums.sum(), RHO * L, rtol=2e-15, atol=0)  # measured 2.1e-16
    # the end control points carry less mass than the interior ones
    assert row_sums[0] < row_sums[1] < row_sums[2] < row_sums[3]


@pytest.mark.parametrize("nseg,closed", [(1, False), (2, False), (3, False),
                                         (40, False), (8, True), (9, True)])
def test_mass_is_positive_definite_from_the_fewest_gauss_points(nseg, closed):
    """The assembled scalar mass m is positive definite for every accepted
    Gauss point count and singular for one fewer (but on an odd closed yarn,
    where one point a segment happens to suffice)."""
    fewest = bspline.fewest_gauss_points(nseg, closed)
    ncp = nseg if closed else nseg + 3
    X, conn = helix(ncp, 0), bspline.span(np.arange(nseg), ncp, closed)

    def conditioning(nq):
        m = np.zeros((ncp, ncp))
        np.add.at(m, (conn[:, :, None], conn[:, None, :]),
                  YarnElements(X, conn, RHO, EA, EI, nq=nq).mass_elements())
        lam = np.linalg.eigvalsh(m)
        return lam[0] / lam[-1]

    # measured: λ_min/λ_max ≥ 9.6e-5 (three segments, two points), and
    # |λ_min/λ_max| ≤ 1.6e-16 one point fewer
    assert min(conditioning(nq) for nq in range(fewest, 9)) > 2e-5
    if not (closed and nseg % 2):
        assert abs(conditioning(fewest - 1)) < 1e-15


# -- strain and curvature ------------------------------------------------------
@pytest.mark.parametrize("lam", [0.7, 1.0, 1.3])
def test_uniform_stretch(lam):
    ncp = 8
    spacing = np.array([0.0, 0.1, 0.3, 0.4, 0.7, 0.8, 1.0, 1.05])  # non-uniform
    X = spacing[:, None] * [0.0, 0.6, 0.8]
    y = YarnElements(X, chain(ncp), RHO, EA, EI)
    assert np.allclose(y.strain(lam * X), 0.5 * (lam**2 - 1), rtol=0, atol=1e-14)
    assert np.isclose(y.stretch_energy(lam * X),
                      0.5 * EA * (0.5 * (lam**2 - 1)) ** 2 * y.rest_length(),
                      rtol=6e-15, atol=0)  # measured 6e-16
    # on a curved yarn x = λX scales the strain the same way and κ by 1/λ
    yh = yarn()
    # measured 1.8e-15
    assert np.allclose(yh.strain(lam * yh.X), 0.5 * (lam**2 - 1), atol=0, rtol=2e-14)
    # measured 1.3e-15
    assert np.allclose(yh.curvature(lam * yh.X), yh.kappa0 / lam, rtol=2e-14, atol=0)


def circle(n, R):
    th = 2 * np.pi / n * np.arange(n + 3)
    return R * np.c_[np.cos(th), np.sin(th), np.zeros_like(th)]


def test_circle_curvature():
    R = 2.0
    err = []
    for n in (32, 64):
        X = circle(n, R)
        err.append(np.abs(YarnElements(X, chain(n + 3), RHO, EA, EI).kappa0 * R - 1))
    assert err[0].max() < 0.01
    # second-order convergence in the control-point spacing
    assert 3.5 < err[0].max() / err[1].max() < 4.5


# -- the exact gradient and Hessian --------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("energy", ["stretch", "bend"])
def test_gradient_matches_finite_differences(energy, kind):
    y = yarn(energy)
    x = deformed(y.X, 1)
    g = gradient(y, kind)(x)
    assert g.shape == (y.ncp, 3)
    assert yarn_kernels(y, kind).element_gradient(x).shape == (y.ne, 12)
    fd = central_differences(y.energy, x, 1e-6).ravel()
    assert relative(g.ravel(), fd) < 2e-9  # measured 1.4e-10


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("energy", ["stretch", "bend"])
def test_hessian_matches_finite_differences(energy, kind):
    y = yarn(energy)
    x = deformed(y.X, 2)
    Ke = yarn_kernels(y, kind).element_hessian(x)
    assert Ke.shape == (y.ne, 12, 12)
    assert np.array_equal(Ke, Ke.transpose(0, 2, 1))
    fd = central_differences(gradient(y, kind), x, 1e-6)
    assert relative(dense_hessian(y, x, kind), fd) < 2e-9  # measured 1.2e-10


def test_energy_is_sum_of_parts():
    y = yarn()
    x = deformed(y.X, 3)
    parts = (yarn("stretch").energy(x), yarn("bend").energy(x))
    # exactly: E = E_s + E_b, and a part with its stiffness zero adds 0.0
    assert y.stretch_energy(x) == parts[0] and y.bend_energy(x) == parts[1]
    assert y.energy(x) == sum(parts)
    assert min(parts) > 1e-3 * max(parts)  # both energies matter here


# -- rest state and rigid motions ----------------------------------------------
def test_rest_is_stress_free():
    y = yarn()
    assert y.energy(y.X) == 0.0
    assert np.abs(y.gradient(y.X)).max() < 2e-17  # measured 1.5e-18
    assert y.energy(deformed(y.X, 4)) > 0.0


@pytest.mark.parametrize("kind", KINDS)
def test_rigid_motion_invariance(kind):
    y = yarn()
    x = deformed(y.X, 5)
    Q, t = rotation(6), np.array([0.3, -2.0, 1.5])
    xm = x @ Q.T + t
    assert np.isclose(y.energy(xm), y.energy(x), rtol=1e-15, atol=0)  # measured 1.5e-16
    g = gradient(y, kind)(x)
    assert relative(gradient(y, kind)(xm), g @ Q.T) < 3e-14  # measured 2.4e-15
    K = dense_hessian(y, x, kind)
    Qb = np.kron(np.eye(y.ncp), Q)
    # measured 6.2e-16
    assert relative(dense_hessian(y, xm, kind), Qb @ K @ Qb.T) < 7e-15


def test_gradient_orthogonal_to_rigid_modes():
    y = yarn()
    x = deformed(y.X, 7)
    f = -y.gradient(x)
    scale = np.linalg.norm(f) * np.linalg.norm(x)
    assert np.linalg.norm(f.sum(axis=0)) < 1e-15 * np.linalg.norm(f)  # measured 1.2e-16
    # measured 3.4e-17
    assert np.linalg.norm(np.cross(x, f).sum(axis=0)) < 3e-16 * scale


@pytest.mark.parametrize("kind", KINDS)
def test_hessian_annihilates_rigid_modes_at_rest(kind):
    y = yarn()
    K = dense_hessian(y, y.X, kind)
    modes = [np.tile(np.eye(3)[i], y.ncp) for i in range(3)]
    modes += [np.cross(np.eye(3)[i], y.X).ravel() for i in range(3)]
    for r in modes:
        # measured 2.3e-17; round-off is ~1e-16
        assert np.linalg.norm(K @ r) < 2e-16 * np.linalg.norm(K) * np.linalg.norm(r)
    # and at rest the Hessian is positive semi-definite
    assert np.linalg.eigvalsh(K).min() > -1e-12 * np.linalg.norm(K)


# -- straight yarns: bending smooth where κ = κ₀ = 0 ------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_bending_smooth_at_straight_configuration(kind):
    s = np.array([0.0, 0.1, 0.3, 0.4, 0.7, 0.8, 1.0, 1.05, 1.3, 1.4])
    X = s[:, None] * [1.0, 0.0, 0.0]
    y = YarnElements(X, chain(len(s)), RHO, 0.0, EI)
    assert np.all(y.kappa0 == 0.0)
    # current: straight along another line, re-spaced so that x'' ∥ x' ≠ 0
    x = (1.2 * s + 0.3 * s**2)[:, None] * np.array([2.0, -1.0, 2.0]) / 3.0
    assert np.all(y.curvature(x) < 1e-12)
    K = dense_hessian(y, x, kind)
    assert np.all(np.isfinite(K))
    assert np.linalg.norm(K) > 0
    assert np.abs(gradient(y, kind)(x)).max() < 2e-15 * np.linalg.norm(K)  # measured 0
    assert np.linalg.eigvalsh(K).min() > -1e-10 * np.linalg.norm(K)  # a minimum
    fd = central_differences(gradient(y, kind), x, 1e-6)
    assert relative(K, fd) < 5e-10  # measured 4.2e-11


# -- the mixed integration point (MIP) Newton matrix ----------------------------
def mixed_residual(y, x, n):
    """The stretch with its axial force n (ne, nq) an unknown of its own:
    R_x = Σ_q W n ∂e/∂p, R_n = W (e(x) − n/EA), stacked."""
    _, f2, g, H = stretch_terms(y.tangents(x), y.Xp2, y.W, y.EA, hessian=False)
    Rx = y.assemble_vector(chain_rule(y.D, [(y.W * n, f2, g, H)], hessian=False)[0])
    return np.concatenate([Rx.ravel(), (y.W * (y.strain(x) - n / y.EA)).ravel()])


@pytest.mark.parametrize("kind", KINDS)
def test_mip_matrix_is_the_condensed_jacobian_of_the_mixed_stretch(kind):
    """With the axial force n = EA ē, ē = e(r) + ∂e(r)·(x − r) (where Newton
    puts it after a step from r), the MIP matrix is J_xx − J_xn J_nn⁻¹ J_nx of
    the mixed system's Jacobian, here by central differences."""
    y = yarn("stretch")
    r = deformed(y.X, 3, 0.05)
    x = deformed(r, 4, 0.05)
    dr = y.tangents(x)[:, :, 0] - y.tangents(r)[:, :, 0]
    n = y.EA * (y.strain(x) - 0.5 * np.einsum("eqi,eqi->eq", dr, dr) / y.Xp2)
    m = 3 * y.ncp
    J = central_differences(
        lambda z: mixed_residual(y, z[:m].reshape(-1, 3), z[m:].reshape(n.shape)),
        np.concatenate([x.ravel(), n.ravel()]), 1e-6)
    condensed = J[:m, :m] - J[:m, m:] @ np.linalg.solve(J[m:, m:], J[m:, :m])
    K = dense_hessian(y, x, kind, xref=r)
    assert relative(K, condensed) < 2e-9  # measured 1.2e-10
    assert relative(K, dense_hessian(y, x, kind)) > 1e-3      # not the exact one


@pytest.mark.parametrize("kind", KINDS)
def test_mip_matrix_linearised_from_x_itself_is_the_hessian(kind):
    y = yarn("both")
    x = deformed(y.X, 5)
    assert relative(dense_hessian(y, x, kind, xref=x), dense_hessian(y, x, kind)) < 2e-15  # 0
