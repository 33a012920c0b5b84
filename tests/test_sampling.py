"""The sampled reduced model (ECSW): exact with every element at weight 1,
its tangent the Hessian of its energy, force-free at rest and under rigid
motions, trained to its tolerance, cached under a key that changes with
the problem."""

import os

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import jersey, models, to_scipy
from knitfem.lod import sampling
from knitfem.model.full import Material
from knitfem.lod.reduced import ReducedModel
from knitfem.lod.sampling import SampledElements, greedy_nnls, sampled_set

SELF = PETSc.COMM_SELF


@pytest.fixture(scope="module")
def pair():
    full, red = models(SELF, jersey(4, 3, hold="top"))
    yield full, red
    red.destroy()
    full.destroy()


def sampled(full, red, elements, weights):
    return ReducedModel(full, red.embedding,
                        SampledElements(full, red.embedding, elements, weights))


def deformed(red, seed=1, size=2e-4):
    alpha = red.rest_state()
    alpha.getArray()[:] += size * np.random.default_rng(seed).standard_normal(
        alpha.getLocalSize())
    return alpha


def forces(model, alpha):
    Q, v = alpha.duplicate(), alpha.duplicate()
    v.zeroEntries()
    model.forces(alpha, v, Q)
    return Q.getArray().copy()


@pytest.mark.parametrize("kernels,fill", [("compiled", 0.0), ("numpy", 0.0),
                                          ("compiled", 1.1)])
def test_every_element_at_weight_one_is_the_exact_model(kernels, fill, monkeypatch):
    """(Γ̃_S dense, and sparse with a fill no matrix reaches.)"""
    monkeypatch.setattr(sampling, "DENSE_FILL", fill)
    full, red = models(SELF, jersey(3, 3, hold="top"))
    full.kernels = __import__("knitfem.yarn.kernels", fromlist=["yarn_kernels"]).yarn_kernels(
        full.elements, kernels)
    ne = full.elements.ne
    s = sampled(full, red, np.arange(ne), np.ones(ne))
    assert isinstance(s.sampled.rows, np.ndarray) == (fill < 1)
    alpha = deformed(red)
    f, ref = forces(s, alpha), forces(red, alpha)
    # measured 1.9e-16 and 1.5e-15 on two machines (their BLAS sum in other orders)
    assert np.abs(f - ref).max() <= 6e-15 * np.abs(ref).max()
    K = to_scipy(s.stiffness(alpha)).toarray()
    G = to_scipy(red.embedding.Gamma)
    Kref = (G.T @ to_scipy(full.stiffness(red.full_state(alpha))) @ G).toarray()
    assert np.abs(K - Kref).max() <= 5e-15 * np.abs(Kref).max()  # measured 3.1e-16


def test_sampled_tangent_is_the_hessian_of_the_sampled_energy(pair):
    """K^V = −∂Q^V/∂α by central differences, for an arbitrary sampled set
    and weights (the sampled forces are a gradient: K symmetric)."""
    full, red = pair
    rng = np.random.default_rng(2)
    elements = rng.choice(full.elements.ne, 25, replace=False)
    s = sampled(full, red, elements, rng.uniform(0.5, 3.0, 25))
    alpha = deformed(red)
    K = to_scipy(s.stiffness(alpha)).toarray()
    assert np.abs(K - K.T).max() <= 1e-15 * np.abs(K).max()  # measured 0
    d = rng.standard_normal(alpha.getLocalSize())
    h = 1e-7
    plus, minus = alpha.copy(), alpha.copy()
    plus.getArray()[:] += h * d
    minus.getArray()[:] -= h * d
    fd = -(forces(s, plus) - forces(s, minus)) / (2 * h)
    # measured 8.6e-10
    assert np.linalg.norm(fd - K @ d) <= 9e-9 * np.linalg.norm(K @ d)


def test_rest_and_rigid_motions_are_force_free():
    """Whatever S and ξ: every element is stress-free at rest and turned."""
    full, red = models(SELF, jersey(4, 3), Material(gravity=0.0))
    rng = np.random.default_rng(3)
    s = sampled(full, red, rng.choice(full.elements.ne, 20, replace=False),
                rng.uniform(1, 50, 20))
    alpha = red.rest_state()
    a = alpha.getArray().reshape(-1, 3)
    scale = np.abs(forces(s, deformed(red))).max()
    assert np.abs(forces(s, alpha)).max() <= 8e-14 * scale  # measured 7e-15
    c, t = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -t, 0], [t, c, 0], [0, 0, 1]]) @ np.array(
        [[1, 0, 0], [0, c, t], [0, -t, c]])
    a[:] = a @ R.T + [0.01, -0.02, 0.03]
    assert np.abs(forces(s, alpha)).max() <= 3e-13 * scale  # measured 2.4e-14
    red.destroy()
    full.destroy()


def test_greedy_nnls_finds_a_sparse_exact_fit():
    rng = np.random.default_rng(4)
    A = np.abs(rng.standard_normal((60, 200)))
    xi = np.zeros(200)
    xi[[3, 50, 120]] = [1.0, 2.0, 0.5]
    x, err = greedy_nnls(A, A @ xi, 1e-10)
    assert err <= 1e-10 and (x >= 0).all()
    assert np.count_nonzero(x) <= 10


def test_training_meets_its_tolerance_and_caches(tmp_path, monkeypatch):
    """The trained set fits the training forces to the tolerance with far
    fewer elements, holds on unseen states, is read back from the cache, and
    another material trains another set."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    full, red = models(SELF, jersey(8, 8, hold="top"))
    emb = red.embedding
    el, w, rep = sampled_set(full, emb, 1e-2)
    assert rep["training_error"] <= 1e-2 and not rep["cached"]
    assert rep["held_out_error"] <= 0.1 and len(el) < full.elements.ne / 2
    # exactly: the report's is the largest weight's float
    assert (w > 0).all() and rep["max_weight"] == w.max()
    el2, w2, rep2 = sampled_set(full, emb, 1e-2)
    assert rep2["cached"] and np.array_equal(el, el2) and np.array_equal(w, w2)
    for junk in (b"", b"PK\x03\x04 cut short"):      # a damaged cache is trained again
        with open(rep2["cache"], "wb") as f:
            f.write(junk)
        el3, w3, rep3 = sampled_set(full, emb, 1e-2)
        assert not rep3["cached"] and np.array_equal(el, el3) and np.array_equal(w, w3)
    other, _ = models(SELF, jersey(8, 8, hold="top"), Material(EA=2.0))
    assert sampling.cache_key(other, emb, 1e-2) != sampling.cache_key(full, emb, 1e-2)
    for m in (other, red, full):
        m.destroy()


def test_the_cache_is_keyed_by_the_training_code_and_states(pair, monkeypatch):
    """A change of the code that trains a set, or of its training states
    (the seed), is another key: no stale set is read after an edit."""
    full, red = pair
    key = sampling.cache_key(full, red.embedding, 1e-2)
    assert sampling.cache_key(full, red.embedding, 1e-2, seed=1) != key
    monkeypatch.setattr(sampling, "TRAINED_BY", sampling.TRAINED_BY[:-1])
    sampling.training_code.cache_clear()
    try:
        assert sampling.cache_key(full, red.embedding, 1e-2) != key
    finally:
        monkeypatch.undo()
        sampling.training_code.cache_clear()
    assert sampling.cache_key(full, red.embedding, 1e-2) == key


def test_tests_cache_outside_the_users_home():
    home = os.path.realpath(os.path.expanduser("~"))
    assert not os.path.realpath(sampling.cache_dir()).startswith(home + os.sep)


def test_sampled_forces_derive_from_the_sampled_energy(pair):
    """Q^V_el = −∂E_S/∂α with E_S = Σ ξ_e E_e (the energy a run reports)."""
    full, red = pair
    rng = np.random.default_rng(5)
    s = sampled(full, red, rng.choice(full.elements.ne, 30, replace=False),
                rng.uniform(0.5, 2.0, 30))
    alpha = deformed(red)
    d = rng.standard_normal(alpha.getLocalSize())
    h = 1e-7
    plus, minus = alpha.copy(), alpha.copy()
    plus.getArray()[:] += h * d
    minus.getArray()[:] -= h * d
    dE = (s.elastic_energy(plus) - s.elastic_energy(minus)) / (2 * h)
    Qg = s.Qg.getArray()
    assert -dE == pytest.approx((forces(s, alpha) - Qg) @ d, rel=1e-6)


def test_quadrature_baseline_weights_stand_for_every_element():
    """Two stitches a patch, weighted by the patch's elements: the weights
    sum to the number of elements (a uniform strain is integrated exactly),
    and its force error, measured, is larger than the trained set's."""
    from knitfem.lod.sampling import quadrature_set

    full, red = models(SELF, jersey(8, 8, hold="top"))
    el, w, rep = quadrature_set(full, red.embedding)
    assert w.sum() == pytest.approx(full.elements.ne, rel=5e-15)  # measured 0
    assert len(np.unique(el)) == len(el) < full.elements.ne
    assert rep["training_error"] > 1e-2 and rep["held_out_error"] > 0
    red.destroy()
    full.destroy()


def test_a_sets_force_error_is_the_dense_fits_without_its_columns(pair):
    """``relative_error`` sums the weighted elements' forces state by state;
    it equals ‖A ξ − b‖ / ‖b‖ of the dense system ``fit_system`` (whose
    columns, one an element and 3 n rows a state, the 120×240 sleeve's
    report once held in 10 GB), on the whole knit and on a subset."""
    full, red = pair
    emb = red.embedding
    states = sampling.training_states(emb.volume, full.fabric.radius, 3)
    rng = np.random.default_rng(5)
    elements = np.sort(rng.choice(full.elements.ne, 12, replace=False))
    weights = rng.uniform(0.5, 3.0, len(elements))
    for subset in (None, np.arange(0, full.elements.ne, 2)):
        A, b = sampling.fit_system(full, emb, elements, states, subset)
        dense = np.linalg.norm(A @ weights - b) / np.linalg.norm(b)
        assert sampling.relative_error(full, emb, elements, weights, states, subset) \
            == pytest.approx(dense, rel=1e-13, abs=0)            # measured 0
