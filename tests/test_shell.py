"""The reduced model whose stretch reads the bounding volume as a shell
(``knitfem.lod.shell``): derivatives, invariants, and the reason it exists."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import jersey
from knitfem.knit.pattern import Jersey, jersey_fabric
from knitfem.model.full import FullModel, Material
from knitfem.lod.reduced import Embedding, ReducedModel
from knitfem.lod.shell import ShellStretch
from knitfem.lod.volume import BoundingVolume

COMM = PETSc.COMM_WORLD


def rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def reduced_pair(fab, volume):
    """Reduced models of ``fab`` in ``volume``: the yarn curves' stretch, and
    the shell's."""
    own = FullModel(COMM, fab, Material())
    bent = FullModel(COMM, fab, Material(), stretch=False)
    shell = Embedding(COMM, bent.layout, fab, volume)
    return (ReducedModel(own, Embedding(COMM, own.layout, fab, volume)),
            ReducedModel(bent, shell, shell=ShellStretch(bent, shell)))


@pytest.fixture(scope="module")
def pair():
    """A 3 × 3 jersey in a 4 × 4 box."""
    fab = jersey(3, 3)
    return reduced_pair(fab, BoundingVolume.around(fab.X.reshape(-1, 3), 4, 4,
                                                   margin=fab.radius))


@pytest.fixture(scope="module")
def tube():
    """A tube of 3 courses × 5 stitches round in a periodic volume (its
    seam inside elements and stitches)."""
    fab = jersey_fabric(Jersey(3, 5, knit="tube"))
    return reduced_pair(fab, BoundingVolume.tube(fab.X.reshape(-1, 3), 6, 4,
                                                 margin=fab.radius))


@pytest.fixture(params=["flat", "tube"])
def shell(request, pair, tube):
    return (pair if request.param == "flat" else tube)[1]


def perturbed(red, seed, size=3e-5):
    a = red.rest_state()
    a.getArray()[:] += size * np.random.default_rng(seed).standard_normal(a.getLocalSize())
    return a


def forces(red, a):
    Q = a.duplicate()
    red.forces(a, a.duplicate(), Q)
    Q.axpy(-1.0, red.Qg)                  # the elastic part only
    return Q


def shifted(a, d, h):
    b = a.copy()
    b.axpy(h, d)
    return b


def test_forces_derive_from_the_energy(shell):
    red = shell
    a = perturbed(red, 0)
    d = perturbed(red, 1, 1.0)
    d.axpy(-1.0, red.rest_state())
    def central(h):
        return (red.elastic_energy(shifted(a, d, h))
                - red.elastic_energy(shifted(a, d, -h))) / (2 * h)

    # Richardson's (4 D(h/2) − D(h))/3 at h = 1e-7: no h² term, and E's
    # round-off over h small (at h = 1e-9 it was 1.1e-8 on 2 ranks)
    fd = (4 * central(5e-8) - central(1e-7)) / 3
    # measured 3.5e-13 to 3.7e-12 serially, 1.0e-11 on 2 ranks
    assert np.isclose(-forces(red, a).dot(d), fd, rtol=1e-10, atol=0)


@pytest.mark.parametrize("mip", [False, True])
def test_tangent_is_the_force_derivative(shell, mip):
    """Γᵀ K_b Γ + ∂²E_s/∂α² = −∂Q^V/∂α by central differences; the MIP
    matrix linearised from the state itself is the same matrix."""
    red = shell
    a = perturbed(red, 2)
    K = red.stiffness(a, xref=a if mip else None)
    d = perturbed(red, 3, 1.0)
    d.axpy(-1.0, red.rest_state())
    Kd = K.createVecLeft()
    K.mult(d, Kd)
    h = 1e-9
    fd = forces(red, shifted(a, d, -h))
    fd.axpy(-1.0, forces(red, shifted(a, d, h)))
    fd.scale(1 / (2 * h))
    # measured 2.3e-10 of the largest (2 ranks 5.4e-9)
    assert np.allclose(Kd.getArray(), fd.getArray(), rtol=0,
                       atol=5e-8 * fd.norm(PETSc.NormType.INFINITY))


def test_rigid_motions_cost_nothing(shell):
    red = shell
    a = red.rest_state()
    P = a.getArray().reshape(-1, 3)
    P[:] = P @ rotation([1, 2, 3], 0.7).T + [0.1, -0.2, 0.3]
    assert abs(red.elastic_energy(a)) < 5e-28  # measured 4e-29
    EA = red.material.EA                          # round-off: EA × 1e-14 strain
    assert forces(red, a).norm(PETSc.NormType.INFINITY) < 1e-14 * EA


@pytest.mark.parametrize("axis", [0, 1])
def test_bending_the_volume_does_not_stretch_the_shell(pair, axis):
    """The volume rolled on a cylinder of radius 500 × the knit's width (its
    mid-surface isometric), about either in-plane axis: the yarn curves
    stretch by κ z, the shell's yarns 100 times less."""
    own, mid = pair
    flat = own.embedding.volume.flat
    R = 500 * np.ptp(flat[:, axis])
    bent = flat.copy()
    t = flat[:, axis] / R
    bent[:, axis] = (R - flat[:, 2]) * np.sin(t)
    bent[:, 2] = R - (R - flat[:, 2]) * np.cos(t)
    E = []
    for red in pair:
        a = red.rest_state()
        lo, hi = a.getOwnershipRange()
        a.getArray()[:] = bent.ravel()[lo:hi]
        E.append(red.elastic_energy(a) - red.elastic_energy(red.rest_state()))
    assert 0 < E[1] < 0.01 * E[0]


def test_shearing_a_stitch_keeps_its_yarn_length(pair):
    """An in-plane shear of the volume by 1e-3 stretches a loop's legs and
    shortens its heads: per element it costs, over a stitch next to nothing
    (1e-6 of it)."""
    own, red = pair
    flat = red.embedding.volume.flat
    sheared = flat + 1e-3 * np.c_[flat[:, 1], np.zeros(len(flat)), np.zeros(len(flat))]
    stitch = red.shell
    element = ShellStretch(red.full, red.embedding, window=1)
    assert max(stitch.energy(flat), element.energy(flat)) < 1e-30
    assert stitch.energy(sheared) < 2e-5 * element.energy(sheared)  # measured 1.2e-6


def test_a_turned_problem_gives_turned_forces_and_the_same_energy(shell):
    """A strained state turned and moved rigidly: the same energy, its
    forces turned with it."""
    red = shell
    a = perturbed(red, 4)
    R = rotation([2, -1, 3], 1.1)
    b = a.copy()
    P = b.getArray().reshape(-1, 3)
    P[:] = P @ R.T + [0.05, 0.2, -0.1]
    # measured 1.8e-12
    assert np.isclose(red.elastic_energy(b), red.elastic_energy(a), rtol=2e-11, atol=0)
    Qa = forces(red, a).getArray().reshape(-1, 3)
    Qb = forces(red, b).getArray().reshape(-1, 3)
    # measured 1.1e-12 of the largest (2 ranks 4.9e-13)
    assert np.allclose(Qb, Qa @ R.T, rtol=0, atol=1e-11 * np.abs(Qa).max())


def test_shell_tangent_is_the_yarns_own_where_the_volume_is_affine(pair):
    """The shell reading leaves out only what a bend adds: under any affine
    map of the volume every t_q is the yarn curve's x'_q (round-off)."""
    own, red = pair
    F = np.array([[1.1, 0.2, 0.05], [-0.1, 0.9, 0.3], [0.02, 0.1, 1.2]])
    A = red.embedding.volume.flat @ F.T + [0.1, 0.0, -0.2]
    x = red.embedding.scalar_dense() @ A
    t = red.shell.D @ A
    xp = red.full.elements.tangents(x)[:, :, 0].reshape(-1, 3)
    assert np.abs(t - xp).max() < 3e-13 * np.abs(xp).max()  # measured 4.0e-14


def test_the_convex_tangent_drops_only_the_compressed_stitches(shell):
    """``convex``: the shell's tangent less Σ f_q D_qᵀ D_q ⊗ I₃ over the
    points of compressed stitches (f_q < 0) — positive semi-definite where
    the exact one is not (the volume squeezed 2 %), and the exact one where
    no stitch is compressed (stretched 2 %)."""
    red = shell
    s = red.shell
    rest = red._all(red.rest_state()).copy()
    centre = rest.mean(axis=0)
    N = 3 * len(rest)
    for scale in (0.98, 1.02):
        A = centre + scale * (rest - centre)
        exact, convex = np.zeros((N, N)), np.zeros((N, N))
        s.add_hessian(A, exact)
        s.add_hessian(A, convex, convex=True)
        t, f = s._forces(A)
        neg = np.minimum(f, 0.0)[:, None] * s.D.tocsr().toarray()
        dropped = np.kron(s.D.tocsr().toarray().T @ neg, np.eye(3))
        big = np.abs(exact).max()
        # measured 1.9e-16 of the largest
        assert np.abs(convex - (exact - dropped)).max() < 1e-15 * big
        low_exact, low_convex = (np.linalg.eigvalsh(H)[0] / big for H in (exact, convex))
        if scale < 1:
            assert (f < 0).all() and low_exact < -0.1            # measured −0.90, −0.50
            assert low_convex > -1e-14                           # measured −2.8e-15
        else:
            assert (f > 0).all() and np.array_equal(convex, exact)
