"""The compiled yarn kernels equal the numpy reference (``knitfem.yarn.kernels``).

Element gradients and Hessians, the assembled gradient and the CSR values of
K agree to round-off (2e-15 relative) on curved, torsioned yarns (κ₀ > 0), on
yarns without bending stiffness and on straight yarns (κ = κ₀ = 0); and the
full model's forces and stiffness matrix agree whichever kernels it runs. The
finite-difference checks of both kernels are in ``test_yarn.py``.
"""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import jersey, to_scipy
from knitfem.model.assembly import ElementPattern
from knitfem.yarn.kernels import KINDS, yarn_kernels
from knitfem.model.full import FullModel, Material
from knitfem.errors import KnitError
from knitfem.yarn.elements import YarnElements
from test_yarn import chain, deformed, helix, relative

TOL = 2e-15          # measured at most 2.8e-16 (relative, 1 and 2 ranks)


def elements(case):
    """Yarn elements and a deformed state for each case."""
    if case == "straight":
        s = np.array([0.0, 0.1, 0.3, 0.4, 0.7, 0.8, 1.0, 1.05, 1.3, 1.4])
        X = s[:, None] * [1.0, 0.0, 0.0]
        x = (1.2 * s + 0.3 * s**2)[:, None] * np.array([2.0, -1.0, 2.0]) / 3.0
        return YarnElements(X, chain(len(s)), 0.3, 10.0, 1e-2), x
    EI = 0.0 if case == "no bending" else 1e-2
    X = helix(12, 3, nyarn=3)
    return YarnElements(X, chain(12, 3), 0.3, 10.0, EI), deformed(X, 4)


@pytest.mark.parametrize("case", ["helices", "no bending", "straight"])
def test_element_gradient_and_hessian_equal_reference(case):
    y, x = elements(case)
    ref, fast = yarn_kernels(y, "numpy"), yarn_kernels(y, "compiled")
    assert relative(fast.element_gradient(x), ref.element_gradient(x)) < TOL
    H = fast.element_hessian(x)
    assert relative(H, ref.element_hessian(x)) < TOL
    assert np.array_equal(H, H.transpose(0, 2, 1))
    xref = x + 0.05 * np.random.default_rng(6).normal(size=x.shape)   # MIP
    assert relative(fast.element_hessian(x, xref), ref.element_hessian(x, xref)) < TOL


@pytest.mark.parametrize("case", ["helices", "no bending"])
def test_assembled_gradient_and_values_equal_reference(case):
    y, x = elements(case)
    start = np.random.default_rng(5).normal(size=(y.ncp, 3))
    _, indices3, (slot,) = ElementPattern(y.conn, 0, y.ncp).blocks3()
    out, values = {}, {}
    for kind in KINDS:
        k = yarn_kernels(y, kind)
        out[kind] = start.copy()
        k.add_gradient(x, out[kind], -2.5)
        values[kind] = np.full(len(indices3), np.nan)
        k.hessian_values(x, slot, values[kind])
        values[kind, "mip"] = np.full(len(indices3), np.nan)
        k.hessian_values(x, slot, values[kind, "mip"], 0.9 * x)
    assert relative(out["compiled"], out["numpy"]) < TOL
    assert relative(values["compiled", "mip"], values["numpy", "mip"]) < TOL
    assert np.array_equal(out["numpy"], start - 2.5 * y.gradient(x))  # its definition
    assert relative(values["compiled"], values["numpy"]) < TOL


def test_block_slots_refuse_other_layouts():
    y, _ = elements("helices")
    slot = np.random.default_rng(0).permutation(y.ne * 144).reshape(y.ne, 12, 12)
    with pytest.raises(ValueError, match="3 x 3 blocks"):
        yarn_kernels(y, "compiled").hessian_values(y.X, slot, np.zeros(y.ne * 144))


def test_unknown_kind_is_refused():
    y, _ = elements("helices")
    with pytest.raises(KnitError, match="expected one of compiled, numpy"):
        yarn_kernels(y, "fortran")


@pytest.fixture(scope="module")
def full_models():
    fab = jersey(3, 2, hold="top")
    models = {kind: FullModel(PETSc.COMM_WORLD, fab, Material(), kernels=kind)
              for kind in KINDS}
    yield models
    for m in models.values():
        m.destroy()


def test_full_model_forces_and_stiffness_equal_reference(full_models):
    """Q and K of the full model, compiled vs numpy, at two states: the
    second call's K must hold the new values (on one rank K shares the
    kernel's value array)."""
    rng = np.random.default_rng(7)
    ref = full_models["numpy"]
    x, v = ref.rest_state(), ref.rest_state()
    v.getArray()[:] = rng.normal(size=v.getLocalSize())
    Q = {kind: x.duplicate() for kind in KINDS}
    for step in range(2):
        x.getArray()[:] += 1e-4 * rng.normal(size=x.getLocalSize())
        K = {}
        for kind, model in full_models.items():
            model.forces(x, v, Q[kind])
            K[kind] = to_scipy(model.stiffness(x)).toarray()
        # measured 8.0e-16 (2 ranks 8.7e-16)
        assert relative(Q["compiled"].getArray(), Q["numpy"].getArray()) < 5e-15
        assert relative(K["compiled"], K["numpy"]) < TOL
        if step == 0:
            first = K["compiled"]
    assert relative(K["compiled"], first) > 1e-6          # the state did change
