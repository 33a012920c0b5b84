"""A relaxed knit stretched quasi-statically (``knitfem.run.tensile``): the
energy against the work of the clamps' multipliers, the response's
linearity at small strain, and the errors of bad input."""

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from knitfem.knit.pattern import Jersey
from knitfem.run.relax import RelaxedKnit
from knitfem.run.tensile import stretch

from test_relax import relaxed

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="runs knitfem in subprocesses")


@pytest.fixture(scope="module")
def knit(tmp_path_factory):
    """A 3×3 jersey relaxed without yarn contact (3 s)."""
    out, _ = relaxed(tmp_path_factory.mktemp("tensile"), "relax")
    rest = RelaxedKnit.load(str(out / "relaxed.h5"))
    return Jersey(3, 3, rest.radius, rest=rest)


@pytest.mark.parametrize("along", ["wales", "courses"])
def test_the_energy_is_the_work_of_the_clamps_pull(knit, along):
    """The energy stored between two strains is the work of the moving
    clamp's pull R = −Σ μ_i·e along its path, Π(ε₂) − Π(ε₀) = ∫ R L dε, by
    Simpson's rule on equal steps (exact for a cubic R): rel 2e-6 (measured
    2.3e-8 along the wales, 2.9e-7 along the courses, whose knit stiffens
    6 % from 0.5 to 2 %). The pull is 0 at ε = 0 (the relaxed knit is in
    equilibrium) and grows with the strain."""
    rec = stretch(PETSc.COMM_SELF, knit, along, [0.005, 0.01, 0.015])
    R, E = np.array(rec["reaction_N"]), np.array(rec["energy_J"])
    step = 0.005 * rec["length_m"]
    for k in (0, 1):
        work = step / 3 * (R[k] + 4 * R[k + 1] + R[k + 2])
        assert E[k + 2] - E[k] == pytest.approx(work, rel=2e-6, abs=0)
    assert R[0] == 0 and np.all(np.diff(R) > 0)
    assert rec["stiffness_N_per_m"] == pytest.approx(rec["stiffness_N"] / rec["width_m"],
                                                     rel=1e-14)
    assert max(rec["newton"]) < 100


def test_a_knit_answers_a_small_stretch_linearly(knit):
    """At small strains the pull is proportional to the strain: R / ε at
    0.1 %, 0.2 % and 0.4 % within 1 % of each other (measured 0.08 % along
    the wales)."""
    rec = stretch(PETSc.COMM_SELF, knit, "wales", [0.001, 0.002, 0.004])
    R = np.array(rec["reaction_N"][1:]) / np.array(rec["strain"][1:])
    assert np.ptp(R) < 0.01 * R.mean()


def test_bad_input_is_refused(knit):
    with pytest.raises(ValueError, match="increasing and positive"):
        stretch(PETSc.COMM_SELF, knit, "wales", [0.01, 0.005])
    with pytest.raises(ValueError, match="use one of wales, courses"):
        stretch(PETSc.COMM_SELF, knit, "bias", [0.01])
    with pytest.raises(ValueError, match="give the jersey its rest"):
        stretch(PETSc.COMM_SELF, Jersey(3, 3), "wales", [0.01])
