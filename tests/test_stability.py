"""The symplectic integrator's stable step (solvers/stability.py)."""

import numpy as np
import pytest
import scipy.linalg as sl
from petsc4py import PETSc

from helpers import to_scipy
from knitfem.model.full import FullModel, Material
from knitfem.cli.scenes import make_fabric
from solvers.integrators import SymplecticEuler
from solvers.stability import stable_step

SELF = PETSc.COMM_SELF


def free_yarn():
    fab = make_fabric("catenary", length=0.05, span=0.04, segments=8)
    fab.fixed = (np.zeros(0, int), np.zeros(0))
    return FullModel(SELF, fab, Material(EA=0.5, EI=1e-7))


def test_power_iteration_finds_the_largest_eigenvalue_of_the_pencil():
    model = free_yarn()
    K = to_scipy(model.stiffness(model.rest_state())).toarray()
    M = to_scipy(model.M).toarray()
    lam = sl.eigh(K, M, eigvals_only=True)[-1]
    # measured 8.9e-6
    assert stable_step(model) == pytest.approx(2 / np.sqrt(lam), rel=9e-5)


@pytest.mark.parametrize("fraction,stable", [(0.95, True), (1.05, False)])
def test_symplectic_euler_is_stable_below_the_step_and_not_above(fraction, stable):
    model = free_yarn()
    h = fraction * stable_step(model)
    integ = SymplecticEuler(model, h)
    x, v = model.rest_state(), model.rest_state()
    v.zeroEntries()
    with np.errstate(all="ignore"):
        for n in range(500):
            integ.step(n * h, x, v)
    speed = np.abs(v.getArray()).max()
    # free fall reaches g t = 0.2 m/s; an unstable mode grows without bound
    assert (speed < 1.0) == stable
