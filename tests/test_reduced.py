"""The reduced model: PtAP, mass, affine reproduction, exactness in range(Γ)."""

import numpy as np
import pytest
from scipy import sparse as sp
from petsc4py import PETSc

from helpers import COMM, gather, jersey, models, run, step_potential_slopes, to_scipy
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
    # measured 1.8e-16 (3.6e-16 before)
    assert to_scipy(red.m).sum() == pytest.approx(to_scipy(full.m).sum(), rel=1.5e-15, abs=0)
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


@pytest.mark.parametrize("integrator,dt,tol,move", [(SymplecticEuler, 5e-7, 3e-13, 1e-9),
                                                    (BackwardEuler, 1e-3, 1e-11, 1e-8)])
def test_free_fall_and_translation_identical_in_both_models(integrator, dt, tol, move):
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
    # round-off (explicit) or within Newton's tolerance, 1e-9 radii a step
    # (implicit): measured 4.2e-14 r and 1.1e-12 r
    assert np.allclose(ef, er, rtol=0, atol=tol * fab.radius)
    assert np.abs(ef - fab.X.ravel()).max() > move  # it did move


# -- the sparse reduced tangent, the shell on sampled stitches, bodies on an
# -- active set ---------------------------------------------------------------
def bodied(per_patch=None, sampled=True, friction=0.3):
    """A reduced model of a 4 × 3 jersey pressed onto a sphere, its stretch
    the shell's (on ``per_patch`` stitches a patch), the yarn elements
    sampled (every one at weight 1) with the contact on its active set, or
    exact."""
    from knitfem.contact.colliders import Sphere
    from knitfem.lod.body_contact import ActiveContact
    from knitfem.lod.reduced import Embedding, ReducedModel
    from knitfem.lod.sampling import SampledElements
    from knitfem.lod.shell import ShellStretch
    from knitfem.lod.volume import BoundingVolume
    from knitfem.model.full import FullModel

    fab = jersey(4, 3)
    X = fab.X.reshape(-1, 3)
    corner = X[np.argmin(X[:, 0] + X[:, 1] + X[:, 2])]        # under a corner
    fab.bodies = (Sphere(corner - [0, 0, 0.004 + fab.radius * 1.05], 0.004),)
    fab.friction = friction
    full = FullModel(SELF, fab, Material(), stretch=False)
    emb = Embedding(SELF, full.layout, fab,
                    BoundingVolume.around(X, 5, 5, margin=fab.radius))
    shell = ShellStretch(full, emb, per_patch=per_patch)
    if not sampled:
        return ReducedModel(full, emb, shell=shell)
    every = np.arange(full.elements.ne)
    return ReducedModel(full, emb, SampledElements(full, emb, every, np.ones(len(every))),
                        shell=shell, contact=ActiveContact(full, emb))


def pressed_state(red, seed=4):
    """α pushed 3 r down (z), into the sphere, and jiggled, the contact
    set and friction lagged from rest."""
    a0 = red.rest_state()
    red.begin_step(a0, 0.0)
    red.move_bodies(0.0, 0.01)
    a = a0.copy()
    arr = a.getArray().reshape(-1, 3)
    arr[:, 2] -= 3.0 * red.fabric.radius
    arr += 2e-5 * np.random.default_rng(seed).standard_normal(arr.shape)
    if red.contact is not None:
        assert red.contact.energy(arr) > 0
    return a


def tangent_of(red, a, sparse):
    """red's tangent at a, on the dense path or on the sparse one."""
    from knitfem.lod.reduced import DENSE_LIMIT
    from knitfem.lod.sparse_tangent import SparseTangent, scalar_pattern

    if sparse and red.sparse is None:
        pattern = scalar_pattern(red.m) + red.shell.pattern()
        red.sparse = SparseTangent(red.comm, pattern, red.M.getOwnershipRange())
    assert (red.sparse is not None) == sparse or red.embedding.volume.size > DENSE_LIMIT
    if not sparse:
        red.sparse = None
    red.K = None
    return to_scipy(red.stiffness(a)).toarray()


@pytest.mark.parametrize("sampled", [True, False])
def test_sparse_reduced_tangent_equals_the_dense_one(sampled):
    """Γᵀ K Γ on the fixed sparse pattern (the sampled elements', the shell's
    and the contact set's parts) equals the dense tangent to round-off, and
    nothing falls outside the pattern."""
    red = bodied(sampled=sampled)
    a = pressed_state(red)
    dense = tangent_of(red, a, sparse=False)
    sparse = tangent_of(red, a, sparse=True)
    assert red.sparse.outside == 0
    # measured 1.3e-16 of the largest entry
    assert np.allclose(sparse, dense, rtol=0, atol=1e-15 * np.abs(dense).max())
    assert red.contact is None or len(red.contact.active) > 0


def test_parts_side_by_side_give_the_same_bits_as_one_after_the_other():
    """The sampled model's energy, forces and sparse tangent formed on two
    threads (``lod.parts``) equal, to the bit, those formed on one: each
    part into its own output, added in a fixed order."""
    from knitfem.lod.parts import Parts

    red = bodied()
    a = pressed_state(red)
    out = {}
    for threads in (1, 2):
        red.parts = Parts(threads)
        Q, v = a.duplicate(), a.duplicate()
        v.zeroEntries()
        red.forces(a, v, Q)
        out[threads] = (red.potential(a), Q.getArray().copy(),
                        tangent_of(red, a, sparse=True))
        red.parts.close()
    (E1, Q1, K1), (E2, Q2, K2) = out[1], out[2]
    assert np.abs(K1).max() > 0 and np.abs(Q1).max() > 0
    assert E1 == E2 and np.array_equal(Q1, Q2) and np.array_equal(K1, K2)


def test_a_rank_alone_on_its_machine_takes_the_cores_it_may_run_on():
    """``-knit_threads``'s default: the process's cores over the ranks on
    its machine (here one rank of COMM_SELF)."""
    import os

    from knitfem.lod.parts import default_threads

    assert default_threads(SELF) == max(1, len(os.sched_getaffinity(0)))


def test_the_convex_tangent_after_the_exact_one_is_assembled_afresh_s():
    """The convex sparse tangent at the state of the exact one just formed
    (that one's values less the shell's compressed stitches' part) equals
    the convex one assembled from scratch, on a squeezed, pressed knit."""
    red = bodied()
    a = pressed_state(red)
    arr = a.getArray().reshape(-1, 3)
    arr[:] = arr.mean(axis=0) + 0.98 * (arr - arr.mean(axis=0))
    exact = tangent_of(red, a, sparse=True)
    after = to_scipy(red.stiffness(a, convex=True)).toarray()
    assert red.exact_kept is not None
    red.exact_kept = None
    afresh = to_scipy(red.stiffness(a, convex=True)).toarray()
    big = np.abs(afresh).max()
    assert np.abs(exact - afresh).max() > 1e-3 * big             # stitches compressed
    # measured 1.4e-16 of the largest
    assert np.allclose(after, afresh, rtol=0, atol=1e-15 * big)


def test_placed_parts_equal_the_explicit_products():
    """The sampled elements' placed products (the compiled
    ``GroupedTangent.add_into`` and numpy's ``PatchProduct``) and the
    shell's placed parts equal Γ_Sᵀ K_S Γ_S by scipy's products and the
    shell's ``hessian_parts`` (the binary-search placement) to round-off."""
    from knitfem.lod.sparse_tangent import PatchProduct

    red = bodied()
    a = pressed_state(red)
    tangent_of(red, a, sparse=True)
    T, A, s = red.sparse, red._all(a).copy(), red.sampled
    by_patch = PatchProduct(T, s.indptr3, s.indices3, red.embedding.cols[s.points],
                            red.embedding.vals[s.points])
    assert s.grouped is not None
    for new, old in ((lambda: s.grouped.add_into(s.hessian_values(A, None), T),
                      lambda: T.add(s.sparse_tangent(A))),
                     (lambda: by_patch.add(s.hessian_values(A, None)),
                      lambda: T.add(s.sparse_tangent(A))),
                     (lambda: red.shell.add_tangent(A, T),
                      lambda: [T.add(part) for part in red.shell.hessian_parts(A)])):
        T.zero()
        new()
        placed = T.values.copy()
        T.zero()
        old()
        assert np.abs(T.values).max() > 0
        # measured 4.8e-16 (yarns, either product) and 2.6e-16 (shell) of the largest
        assert np.allclose(placed, T.values, rtol=0, atol=3e-15 * np.abs(T.values).max())
    assert T.outside == 0


def test_the_shell_tangent_adds_into_a_dense_array_as_its_explicit_products():
    """The shell's tangent laid out for a dense array (``DenseValues``, the
    small volumes' path) equals the sum of ``hessian_parts``, and a second
    call adds it again in the same places."""
    red = bodied(sampled=False)
    A = red._all(pressed_state(red)).copy()
    ref = red.shell.hessian(A).toarray()
    R = np.zeros_like(ref)
    red.shell.add_hessian(A, R)
    # measured 2.6e-16 of the largest entry
    assert np.allclose(R, ref, rtol=0, atol=1e-14 * np.abs(ref).max())
    red.shell.add_hessian(A, R)
    assert np.allclose(R, 2 * ref, rtol=0, atol=2e-14 * np.abs(ref).max())


def tangent_by_differences(red, a, d, h=1e-9):
    """−∂Q/∂α d at the state a by central differences of the forces Q."""
    def Q(t):
        b = a.copy()
        b.getArray()[:] += t * d
        out, v = b.duplicate(), b.duplicate()
        v.zeroEntries()
        red.forces(b, v, out)
        return out.getArray().copy()

    return (Q(-h) - Q(h)) / (2 * h)


def test_sparse_reduced_tangent_is_the_force_derivative():
    """The sparse tangent (barrier, lagged friction and shell on the active
    set and sampled stitches) against central differences of the forces."""
    red = bodied(per_patch=3)
    a = pressed_state(red, 5)
    K = tangent_of(red, a, sparse=True)
    d = np.random.default_rng(6).standard_normal(a.getLocalSize())
    fd = tangent_by_differences(red, a, d)
    # measured 8.2e-10 of the largest
    assert np.allclose(K @ d, fd, rtol=0, atol=5e-9 * np.abs(fd).max())


def sleeve_model(kernels="compiled"):
    """A tube in its periodic volume (a stitch's columns wrap round) round
    an arm whose forearm turns, the yarns sampled by quadrature."""
    from knitfem.cli.scenes import make_fabric
    from knitfem.knit.pattern import Jersey
    from knitfem.lod.body_contact import ActiveContact
    from knitfem.lod.reduced import Embedding, ReducedModel
    from knitfem.lod.sampling import SampledElements, quadrature_set
    from knitfem.lod.shell import ShellStretch
    from knitfem.lod.volume import BoundingVolume
    from knitfem.model.full import FullModel

    fab = make_fabric("sleeve", Jersey(4, 12), elbow_angle=60.0, elbow_time=0.1)
    full = FullModel(SELF, fab, Material(), stretch=False, kernels=kernels)
    emb = Embedding(SELF, full.layout, fab, BoundingVolume.tube(
        fab.X, 6, 5, margin=fab.radius, frame=fab.frame))
    elements, weights, _ = quadrature_set(full, emb)
    red = ReducedModel(full, emb, SampledElements(full, emb, elements, weights),
                       shell=ShellStretch(full, emb, per_patch=3),
                       contact=ActiveContact(full, emb))
    return red


def landed_sleeve(kernels="compiled"):
    """``sleeve_model`` landed on the turning forearm: the model and its
    state."""
    red = sleeve_model(kernels)
    a = red.rest_state()
    red.begin_step(a, 0.05)
    red.move_bodies(0.05, 0.06)
    arr = a.getArray().reshape(-1, 3)
    arr[:, 1] -= 0.3 * np.ptp(arr[:, 1])              # onto the arm
    arr += 1e-5 * np.random.default_rng(1).standard_normal(arr.shape)
    assert red.contact.energy(arr) > 0
    return red, a


def test_sparse_tangent_of_a_sleeve_on_a_moving_arm_is_the_force_derivative():
    """The same on a sleeve landed on the turning forearm."""
    red, a = landed_sleeve()
    K = tangent_of(red, a, sparse=True)
    d = np.random.default_rng(2).standard_normal(a.getLocalSize())
    fd = tangent_by_differences(red, a, d)
    # measured 2.0e-9 of the largest
    assert np.allclose(K @ d, fd, rtol=0, atol=1e-8 * np.abs(fd).max())


def test_a_sleeves_forces_and_tangent_are_the_numpy_references():
    """The compiled rows of Γ̃ and of the shell's D, and the compiled
    scatter into the tangent's values, against scipy's products and
    numpy's bincount (``-knit_kernels numpy``) on the landed sleeve."""
    out = {}
    for kind in ("compiled", "numpy"):
        red, a = landed_sleeve(kind)
        assert red.contact.G.compiled == red.shell.D.compiled == (kind == "compiled")
        f, v = a.duplicate(), a.duplicate()
        v.zeroEntries()
        red.forces(a, v, f)
        out[kind] = f.getArray().copy(), tangent_of(red, a, sparse=True)
    (f1, K1), (f0, K0) = out["compiled"], out["numpy"]
    # measured 1.4e-20 and 2.3e-19 of the largest (the same sums, reordered)
    assert np.abs(f1 - f0).max() < 1e-15 * np.abs(f0).max()
    assert np.abs(K1 - K0).max() < 1e-15 * np.abs(K0).max()


def test_contact_tangent_of_a_sleeve_sums_its_patches_as_the_explicit_product():
    """On the sleeve, whose contact region spans many patches and elements
    that straddle two (their columns the union of both), Σ_q (c_q c_qᵀ) ⊗
    H_q into the sparse pattern equals Γ_Eᵀ K_E Γ_E by scipy's products, K_E
    the 12 × 12 blocks of the same elements."""
    red, a = landed_sleeve()
    tangent_of(red, a, sparse=True)
    c, T, A = red.contact, red.sparse, red._all(a).copy()
    e, blocks = c.barrier.element_hessian(c._x(A))
    assert len(np.unique(c.product.patch[c.view.points_index[c.view.conn[e, 0]]])) >= 5
    pts = c.view.points_index[c.view.conn[e]]
    rows = (3 * np.arange(4 * len(e)).reshape(-1, 4, 1) + np.arange(3)).reshape(-1, 12)
    K = sp.csr_matrix((blocks.ravel(), (np.repeat(rows, 12, axis=1).ravel(),
                                        np.tile(rows, 12).ravel())))
    G3 = sp.kron(c.G.tocsr()[pts.ravel()], sp.identity(3), format="csr")
    T.zero()
    T.add(G3.T @ (K @ G3))
    ref = T.values.copy()
    for compiled in (True, False):              # quadrature_product, numpy's loop
        T.compiled = compiled
        T.zero()
        c.add_hessian(A, T)
        assert np.abs(ref).max() > 0 and T.outside == 0
        # measured 1.0e-15 of the largest (either)
        assert np.allclose(T.values, ref, rtol=0, atol=3e-15 * np.abs(ref).max())


def test_the_guess_carries_a_sleeve_rigidly_with_the_only_moving_body(monkeypatch):
    """A tube whose only body turns, every point of it within the carry's
    reach: the implicit step's guess (``carry``) moves the volume's control
    points rigidly, so every embedded yarn point goes rigidly with the body
    (Γ reproduces affine maps of α)."""
    import knitfem.model.full

    monkeypatch.setattr(knitfem.model.full, "CARRY_REACH", 1e6)
    from knitfem.cli.scenes import make_fabric
    from knitfem.knit.pattern import Jersey
    from knitfem.lod.reduced import Embedding, ReducedModel
    from knitfem.lod.volume import BoundingVolume
    from knitfem.model.full import FullModel

    fab = make_fabric("sleeve", Jersey(4, 12), elbow_angle=60.0, elbow_time=0.1)
    fab.bodies = (fab.bodies[1],)                       # the forearm alone
    motion = fab.bodies[0].motion
    full = FullModel(SELF, fab, Material())
    emb = Embedding(SELF, full.layout, fab, BoundingVolume.tube(
        fab.X, 6, 5, margin=fab.radius, frame=fab.frame))
    red = ReducedModel(full, emb)
    a = red.rest_state()
    v = a.duplicate()
    v.zeroEntries()
    red.carry(a, 0.03, 0.05, v, 1.0)
    eps0, eps1 = red.full_state(a), red.full_state(a + v)
    P0, P1 = eps0.getArray().reshape(-1, 3), eps1.getArray().reshape(-1, 3)
    (R0, s0), (R1, s1) = motion.pose(0.03), motion.pose(0.05)
    rigid = (P0 - s0) @ (R1 @ R0.T).T + s1
    # measured 5.2e-18 m; the points move up to 3.1 mm
    assert np.abs(P1 - P0).max() > 1e-3
    assert np.allclose(P1, rigid, rtol=0, atol=1e-15)
    full.destroy()


def test_contact_set_is_the_whole_barrier_through_gamma():
    """On the active set the barrier's and friction's forces equal the full
    model's over every yarn element, taken through Γᵀ: the set misses no
    element within the gap."""
    red = bodied()
    a = pressed_state(red, 7)
    A = a.getArray().reshape(-1, 3)
    full = red.full
    full.begin_step(red.full_state(red.rest_state()), 0.0)
    full.move_bodies(0.0, 0.01)
    x = full.yarn_points(red.full_state(a))
    g = np.zeros_like(x)
    full.barrier.add_gradient(x, g, -1.0)
    ref = red.contact.G.T @ g
    f = np.zeros_like(A)
    red.contact.add_forces(A, f)
    assert np.abs(ref).max() > 0
    # measured 0 (the same sums in the same order)
    assert np.allclose(f, ref, rtol=0, atol=1e-15 * np.abs(ref).max())
    assert len(red.contact.active) < full.elements.ne


def test_contact_hessian_on_the_points_in_the_gap_is_the_whole_set_s():
    """Σ_q (c_q c_qᵀ) ⊗ H_q over the quadrature points of the elements
    within the gap, a GEMM a patch, equals Γ_Aᵀ K Γ_A with K assembled on
    the whole active set's pattern."""
    from knitfem.lod.sparse_tangent import DenseValues
    from knitfem.model.assembly import ElementPattern

    red = bodied()
    a = pressed_state(red, 8)
    A = a.getArray().reshape(-1, 3)
    c = red.contact
    indptr3, indices3, (slot3,) = ElementPattern(
        c.view.conn, 0, len(c.view.points_index)).blocks3()
    values = np.zeros(len(indices3))
    c.barrier.add_hessian(c.Ga @ A, slot3, values)
    Ga3 = sp.kron(c.Ga.tocsr(), sp.identity(3), format="csr")
    K = sp.csr_matrix((values, indices3, indptr3), shape=(Ga3.shape[0],) * 2)
    ref = (Ga3.T @ (K @ Ga3)).toarray()
    new = np.zeros(ref.shape)
    c.add_hessian(A, DenseValues(new))
    assert np.abs(ref).max() > 0
    assert len(np.unique(c.barrier.element_hessian(c.Ga @ A)[0])) < len(c.active)
    # measured 1.9e-16 of the largest
    assert np.allclose(new, ref, rtol=0, atol=8e-16 * np.abs(ref).max())


def test_the_narrow_phase_keeps_every_element_that_can_reach_the_gap():
    """After α moves from the reference by up to 2 r, the elements the
    narrow phase keeps (ℓ_e − ρ_e < ĥ) include every one with a point
    within the gap, leave out some of the set, and the barrier's energy,
    forces and step filter on them are the whole set's."""
    red, a = landed_sleeve()
    c = red.contact
    A = red._all(a).copy()
    c.near(A)                                                     # the reference
    r = red.fabric.radius
    A1 = A + 2 * r * np.random.default_rng(3).uniform(-1, 1, A.shape) / np.sqrt(3)
    near = c.near(A1)
    x = c.Ga @ A1
    delta = c.barrier.surface_distance(x)[0]
    within = np.flatnonzero((delta < c.gap).any(axis=1))
    assert len(within) > 0 and np.isin(within, near).all()
    assert len(near) < len(c.active)
    g_all, g_near = np.zeros_like(x), np.zeros_like(x)
    c.barrier.add_gradient(x, g_all)
    c.barrier.add_gradient(x, g_near, elements=near)
    # measured 0 and 0: the elements left out add exact zeros
    assert np.isclose(c.barrier.energy(x, near), c.barrier.energy(x), rtol=1e-14, atol=0)
    assert np.allclose(g_near, g_all, rtol=0, atol=1e-14 * np.abs(g_all).max())
    dx = c.Ga @ (A - A1)
    assert c.barrier.step_limit(x, dx, elements=c.near(A1, A - A1)) == \
        c.barrier.step_limit(x, dx)


def test_an_elements_reach_is_a_max_over_its_distinct_patches():
    """``element_patches``: ρ_e = max_a s_a far[patch_a] over an element's
    four points, as a max over its distinct patches (one to four of them,
    an element with none: nothing)."""
    from knitfem.lod.body_contact import element_patches

    rng = np.random.default_rng(5)
    for n in (1, 2, 7):
        patch = rng.integers(0, n, (300, 4))
        spread = rng.uniform(0.5, 1.5, (300, 4))
        far = rng.random(n)
        P, S = element_patches(patch, spread)
        assert len(P) == min(n, 4)                 # the most distinct patches of a row
        assert np.array_equal(np.max(S * far[P], axis=0), (spread * far[patch]).max(axis=1))
    P, S = element_patches(np.zeros((0, 4), dtype=int), np.zeros((0, 4)))
    assert np.max(S * far[P], axis=0, initial=0.0).shape == (0,)


def test_shell_on_sampled_stitches_weighs_what_it_stands_for():
    """Every patch's stitches sampled: exact; a few a patch: weights summing
    to the stitch count, and the rest and rigid motions still free."""
    every, some = bodied(per_patch=1000), bodied(per_patch=2)
    assert np.array_equal(every.shell.xi, np.ones(every.shell.windows))
    assert len(some.shell.L) < some.shell.windows
    # measured 0
    assert np.isclose(some.shell.xi.sum(), some.shell.windows, rtol=5e-15, atol=0)
    rest = some.rest_state().getArray().reshape(-1, 3)
    f = np.zeros_like(rest)
    some.shell.add_gradient(rest @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T
                            + 0.01, f)
    assert np.abs(f).max() < 1e-15 * some.shell.EA          # measured 1.1e-16


def test_a_sleeve_gets_a_volume_a_patch_every_few_stitches():
    """garment_lod: 12 × 15 × 2 = 360 control points for 60 × 120 stitches;
    the default 6 × 6 for a small tube."""
    from knitfem.knit.pattern import Jersey, jersey_fabric
    from knitfem.lod.reduced import garment_lod

    big = jersey_fabric(Jersey(120, 60, knit="tube"))
    small = jersey_fabric(Jersey(10, 16, knit="tube"))
    assert garment_lod(big, (6, 6)) == (12, 15)
    assert garment_lod(small, (6, 6)) == (6, 6)


@pytest.mark.parametrize("sampled", [True, False])
def test_the_step_potential_is_what_the_residual_derives_from(sampled):
    """Φ, the objective a line search may take (``NewtonStepper``), has the
    residual as its gradient: its central differences along a random
    direction equal F_uᵀ d, for a backward Euler step of a damped jersey
    pressed into a sphere, its friction lagged there, that slides it 0.3 r
    along x (the contact set's barrier and friction, or every element's)."""
    import dataclasses

    red = bodied(sampled=sampled)
    red.material = dataclasses.replace(red.material, damping=2.0)
    integ = BackwardEuler(red, 1e-2)
    a = pressed_state(red)
    red.begin_step(a, 0.0)                       # friction lagged pressed in
    red.move_bodies(0.0, 0.01)
    barrier = red.full.barrier if red.contact is None else red.contact.barrier
    assert len(barrier.lagged[0]) > 0
    z = integ.saddle.createVec()
    integ.saddle.split(z)[0].reshape(-1, 3)[:, 0] = 0.3 * red.fabric.radius / 1e-2
    fd, slope = step_potential_slopes(integ, a, z, seed=8)
    # measured 1.6e-10 (without the friction potential: 0.2)
    assert fd == pytest.approx(slope, rel=1e-8)


def test_the_contact_set_follows_each_elements_own_reach():
    """A body's carry is measured where each element is (a point on the
    axis of a turn is not carried; one at distance d by 2 d sin(θ/2)); the
    sleeve falling on the turning forearm, its set formed about each
    element's own reach and move, misses no element (no step refused) and
    lands (a yarn within the gap)."""
    from knitfem.contact.colliders import Barrier, Sphere
    from knitfem.contact.motion import Kinematic, Motion
    from solvers.integrators import BackwardEuler

    turn = Kinematic(Sphere(np.zeros(3), 0.01), Motion([0.0, 1.0], [[0, 0, 0]] * 2,
                                                       rotations=[[0, 0, 0], [0, 0, np.pi / 2]]))
    b = Barrier((turn,), None, 5e-4, 1.0)
    x = np.array([[0.0, 0.0, 0.3], [0.02, 0.0, 0.0]])
    # measured 0 and 3e-18 m
    assert np.allclose(b.carried(0.0, 1.0, x), [0.0, 0.02 * np.sqrt(2)], rtol=0, atol=1e-15)
    red = sleeve_model()
    c = red.contact
    _, a, _ = run(red, BackwardEuler, 5e-3, 8)
    assert c.refusals == 0 and c.barrier.min_distance(c._x(red._all(a))) < c.gap
    assert np.all(c.allowance >= 2 * c.radius) and np.ptp(c.allowance) > 0


def test_newton_on_a_turning_arm_convexifies_until_its_matrix_is_definite():
    """Backward Euler on the sleeve whose forearm turns, from a start whose
    volume is squeezed 3 % (every stitch compressed): a step's Newton
    matrices are the convex tangent while the exact one has negative
    pivots, the exact one from the first that has none; both ways the
    yarns end where they do with exact matrices only, to Newton's
    tolerance."""
    ends, calls = [], []
    for convexify in (True, False):
        red = sleeve_model()
        integ = BackwardEuler(red, 1e-2)
        assert integ.convexify
        integ.convexify = convexify
        integ.snes.setTolerances(rtol=1e-7)          # both paths to a tight tolerance
        seen = []
        newton_matrix = integ._newton_matrix
        integ._newton_matrix = lambda **convex: (
            seen.append((integ.definite, bool(convex))), newton_matrix(**convex))
        x, v = red.rest_state(), red.rest_state()
        v.zeroEntries()
        arr = x.getArray().reshape(-1, 3)
        arr[:] = arr.mean(axis=0) + 0.97 * (arr - arr.mean(axis=0))
        for n in range(3):
            integ.step(n * 1e-2, x, v)
        ends.append(red.full_state(x).getArray().copy())    # the yarns
        calls.append(seen)
    convexified = [c for c in calls[0] if c[1]]
    assert convexified and not any(c[1] for c in calls[1])
    assert all(not definite for definite, _ in convexified)
    r = red.fabric.radius
    # measured 5.3e-5 r (11 matrices convexified): Newton stops at |F| 1e-7
    # of its start, and a sticking point's friction amplifies what is left
    assert np.abs(ends[0] - ends[1]).max() < 3e-4 * r
