"""Convergence in space: segments a yarn and Gauss points a segment
(Richardson), and the reduced model against the full one as its volume is
refined on the hanging swatch."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import jersey, run
from knitfem.cli.scenes import make_fabric
from knitfem.knit.pattern import Jersey
from knitfem.lod.reduced import Embedding, ReducedModel
from knitfem.lod.volume import BoundingVolume
from knitfem.model.full import FullModel, Material
from knitfem.yarn import bspline
from solvers.integrators import BackwardEuler
from solvers.statics import StaticSolver

SELF = PETSc.COMM_SELF


def test_cantilever_tip_converges_in_segments():
    """The static tip deflection of a cantilever (3.7 mm, 10 to 80
    segments): successive differences shrink with a Richardson order
    log₂(d_n / d_2n) of 5.6 and then 3.7 (measured; the cubic spline holds
    the quartic small-deflection line nearly exactly, so round-off enters)."""
    tips = []
    for n in (10, 20, 40, 80):
        fab = make_fabric("cantilever", length=0.1, segments=n)
        model = FullModel(SELF, fab, Material(rho=3e-3, EA=1e3, EI=1e-4))
        x = model.rest_state()
        StaticSolver(model, steps=1).solve(x)
        tips.append(-bspline.curve_points(x.getArray().reshape(-1, 3),
                                          np.array([float(n)]))[0, 1])
        model.destroy()
    d = np.abs(np.diff(tips))
    assert np.all(np.log2(d[:-1] / d[1:]) > 3)
    # the linear theory's ρgL⁴/8EI, 1.1e-3 above the large-deflection tip
    assert tips[-1] == pytest.approx(3e-3 * 9.81 * 0.1**4 / 8e-4, rel=5e-3)


def test_elastic_energy_converges_in_gauss_points():
    """E of a perturbed jersey with n Gauss points a segment, against 8:
    the error falls with every point from 3 on (|X'| is not polynomial, so
    no rule is exact); 4, the default, is within 2.2e-4."""
    fab = jersey(2, 2)
    dx = 2e-4 * np.random.default_rng(0).standard_normal(fab.X.size)
    energy = {}
    for nq in (2, 3, 4, 5, 6, 8):
        model = FullModel(SELF, fab, Material(), nq=nq)
        x = model.rest_state()
        x.getArray()[:] += dx
        energy[nq] = model.elastic_energy(x)
        model.destroy()
    errors = np.array([abs(energy[n] / energy[8] - 1) for n in (3, 4, 5, 6)])
    assert np.all(np.diff(errors) < 0)       # measured 1.1e-3, 2.2e-4, 1.4e-5, 1.8e-6
    assert errors[1] < 1e-3


def test_reduced_model_error_does_not_grow_as_the_volume_is_refined():
    """The hanging 3 x 3 swatch after 30 ms, full against reduced at 4 x 4
    to 6 x 6 volume control points: the largest control point error
    stays at 27 % of the motion instead of converging, as a
    volume linear through the thickness cannot bend the stitches the way
    the yarns do; it must not grow."""
    fab = make_fabric("hanging", Jersey(3, 3), tilt=90.0)
    full = FullModel(SELF, fab, Material())
    _, x, _ = run(full, BackwardEuler, 2e-3, 15)
    eps = x.getArray().copy()
    errors = []
    for lod in ((4, 4), (5, 5), (6, 6)):
        volume = BoundingVolume.around(fab.X.reshape(-1, 3), *lod, margin=fab.radius)
        red = ReducedModel(full, Embedding(SELF, full.layout, fab, volume))
        _, q, _ = run(red, BackwardEuler, 2e-3, 15)
        errors.append(np.abs(red.full_state(q).getArray() - eps).max())
    motion = np.abs(eps - fab.X.ravel()).max()
    assert np.all(np.diff(errors) <= 1e-2 * errors[0])     # measured ≤ 2e-4
    assert 0.1 * motion < errors[-1] < 0.5 * motion        # measured 0.27
