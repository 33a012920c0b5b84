"""Saddle points [A Cᵀ; C 0]: one analysis a run, the regularised
preconditioner solves K exactly, solver failures become one line."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import to_scipy
from knitfem.model.full import FullModel, Material
from knitfem.knit.pattern import Jersey, jersey_fabric
from solvers.saddle import (WORKSPACE_RAISED, SaddlePoint, SolverFailure, negative_pivots,
                            saddle_ksp, solve_saddle)

COMM = PETSc.COMM_WORLD
PETSc.Log.begin()                 # event counts


@pytest.fixture
def options():
    """Set PETSc options for one test; removed afterwards."""
    db, names = PETSc.Options(), []

    def put(**values):
        for k, v in values.items():
            db.setValue(k, v)
            names.append(k)

    yield put
    for k in names:
        db.delValue(k)


@pytest.fixture(scope="module")
def model():
    m = FullModel(COMM, jersey_fabric(Jersey(5, 8), hold="top"), Material())
    yield m
    m.destroy()


def jacobian(model, h=1e-2, scale=1.0):
    """A = h² K(ε) + M at the rest state stretched by ``scale``."""
    x = model.rest_state()
    x.scale(scale)
    A = model.stiffness(x).duplicate(copy=True)
    A.scale(h * h)
    A.axpy(1.0, model.M, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
    return A


def solve(saddle, ksp, seed=0):
    b, z = saddle.createVec(), saddle.createVec()
    b.setRandom(PETSc.Random().create(comm=COMM).setSeed(seed) or None)
    solve_saddle(lambda: ksp.solve(b, z), ksp)
    r = b.duplicate()
    saddle.K.mult(z, r)
    r.axpy(-1.0, b)
    return z, r.norm() / b.norm()


def test_values_in_place_keep_one_analysis(model, options):
    """Updating A's values three times refactorises three times but analyses
    once (MUMPS symbolic phase), and each solve is exact."""
    A = jacobian(model)
    saddle = SaddlePoint(A, model.C)
    ksp = saddle_ksp(saddle, "t_inplace_")
    sym = PETSc.Log.Event("MatCholFctrSym")
    num = PETSc.Log.Event("MatCholFctrNum")
    n0, m0 = sym.getPerfInfo()["count"], num.getPerfInfo()["count"]
    for scale in (1.0, 1.001, 1.002):
        jacobian(model, scale=scale).copy(A, PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        saddle.update()
        _, res = solve(saddle, ksp)
        assert res < 3e-7    # measured 1.3e-8, 2 ranks 3.0e-8 (K's condition number is ~1e10)
    assert sym.getPerfInfo()["count"] - n0 == 1
    assert num.getPerfInfo()["count"] - m0 == 3
    saddle.destroy()


def test_update_writes_A_C_and_Ct_where_they_belong(model, options):
    """After A and C change, K (and the regularised P) equal [A Cᵀ; C 0]
    (P: −δ on the multipliers' diagonal) built afresh from the blocks."""
    options(t_upd_saddle_regularization=1.0)
    A = jacobian(model)
    saddle = SaddlePoint(A, model.C, prefix="t_upd_")
    x = model.rest_state()
    x.scale(1.01)
    C = model.constraint_jacobian(x)
    jacobian(model, scale=1.01).copy(A, PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
    saddle.update(constraints=True)
    Ct = C.transpose(PETSc.Mat())
    fresh = PETSc.Mat().createNest([[A, Ct], [C, None]], comm=COMM).convert("aij")
    start = saddle.K.getOwnershipRange()[0]
    shift = np.zeros((saddle.nu + saddle.nl, saddle.K.getSize()[1]))
    lam = np.arange(saddle.nu, saddle.nu + saddle.nl)
    shift[lam, start + lam] = saddle.delta
    expect = to_scipy(fresh).toarray()
    for M, s in ((saddle.K, 0.0), (saddle.P, 1.0)):
        D = to_scipy(M).toarray() - expect + s * shift
        assert np.abs(D).max() == 0.0        # values copied, not computed: exact
    model.constraint_jacobian(model.rest_state())
    saddle.destroy()


def test_regularized_preconditioner_solves_K(model, options):
    """GMRES on K preconditioned by the pivot-free LDLᵀ of [A Cᵀ; C −δI]
    gives K's solution (not P's) in a few iterations."""
    options(t_reg_saddle_regularization=1.0, t_reg_ksp_type="gmres")
    A = jacobian(model, scale=1.001)
    direct, reg = SaddlePoint(A, model.C), SaddlePoint(A, model.C, prefix="t_reg_")
    assert direct.P is direct.K and reg.P is not reg.K and reg.delta > 0
    D = reg.P.createVecLeft()
    reg.P.getDiagonal(D)
    assert np.all(reg.split(D)[1] == -reg.delta)
    k1 = saddle_ksp(direct, "t_dir_")
    k2 = saddle_ksp(reg, "t_reg_")
    k2.setTolerances(rtol=1e-12)
    z1, r1 = solve(direct, k1)
    z2, r2 = solve(reg, k2)
    assert r1 < 1e-6 and r2 < 1e-8
    assert k2.getType() == "gmres" and k2.getIterationNumber() <= 8
    z2.axpy(-1.0, z1)
    assert z2.norm() <= 1e-10 * z1.norm()  # measured 2.3e-12, 2 ranks 3.0e-11
    for s in (direct, reg):
        s.destroy()


def test_failure_is_one_line(model, options):
    """A Krylov solve that cannot converge ends as SolverFailure: one line
    naming the solver, its reason and the option to change."""
    options(t_fail_saddle_regularization=1.0, t_fail_ksp_type="gmres",
            t_fail_ksp_max_it=2,
            t_fail_ksp_rtol=1e-30, t_fail_pc_type="jacobi")
    saddle = SaddlePoint(jacobian(model), model.C, prefix="t_fail_")
    ksp = saddle_ksp(saddle, "t_fail_")
    with pytest.raises(SolverFailure) as err:
        solve(saddle, ksp)
    line = str(err.value)
    assert "\n" not in line
    assert "KSP gmres with PC jacobi" in line and "DIVERGED_MAX_IT" in line
    assert "-t_fail_ksp_max_it" in line and err.value.curable
    saddle.destroy()


@pytest.mark.skipif(COMM.size > 1, reason="ILU is serial")
def test_a_zero_pivot_is_named_and_not_curable(model, options):
    """A Schur split with ILU on the zero multiplier block fails in its set-up:
    the failure names the block, the zero pivot and the Schur preconditioner
    that cures it, and says a shorter step would not; the KSP solves again
    afterwards (no PETSc error is left inside it)."""
    options(t_zp_ksp_type="gmres", t_zp_pc_type="fieldsplit",
            t_zp_pc_fieldsplit_type="schur")
    saddle = SaddlePoint(jacobian(model), model.C)
    ksp = saddle_ksp(saddle, "t_zp_")
    for _ in range(3):
        with pytest.raises(SolverFailure) as err:
            solve(saddle, ksp)
        line = str(err.value)
        assert "block 'l'" in line and "zero pivot" in line and "PCPreSolve" not in line
        assert "-t_zp_pc_fieldsplit_schur_precondition selfp" in line
        assert not err.value.curable
    saddle.destroy()


def test_default_workspace_is_what_the_demo_needs(model):
    """MUMPS gets 200 % extra workspace unless told otherwise: the demo's
    hanging 7x7 ran out at 100 (t = 0.27 s of 3 s) and fits at 200."""
    from solvers.saddle import WORKSPACE

    saddle = SaddlePoint(jacobian(model, scale=1.01), model.C)
    ksp = saddle_ksp(saddle, "t_default_ws_")
    ksp.setUp()
    assert WORKSPACE == 200
    assert ksp.getPC().getFactorMatrix().getMumpsIcntl(14) == WORKSPACE
    PETSc.Options().delValue("t_default_ws_mat_mumps_icntl_14")
    ksp.destroy()
    saddle.destroy()


def test_the_ordering_is_qamd_on_one_rank_unless_told(model, options):
    """MUMPS orders by QAMD (INFOG(7) = 6) on one rank, by its own choice
    across ranks (AMF here, 2), and by the ordering the user gives."""
    from solvers.saddle import ORDERING

    def ordering(prefix):
        saddle = SaddlePoint(jacobian(model, scale=1.01), model.C)
        ksp = saddle_ksp(saddle, prefix)
        z, rel = solve(saddle, ksp)
        used = ksp.getPC().getFactorMatrix().getMumpsInfog(7)
        for obj in (z, ksp, saddle):
            obj.destroy()
        assert rel < 5e-11                   # measured 3.9e-12, 2 ranks 7.8e-12
        return used

    assert ordering("t_ord_") == (ORDERING if COMM.size == 1 else 2) == \
        (6 if COMM.size == 1 else 2)
    options(t_user_ord_mat_mumps_icntl_7=0)
    assert ordering("t_user_ord_") == 0                      # AMD, as asked
    if COMM.size == 1:
        PETSc.Options().delValue("t_ord_mat_mumps_icntl_7")


@pytest.mark.skipif(COMM.size > 1, reason="the 2-rank factorisation of this "
                    "saddle point fits its estimate")
def test_workspace_retried(model, options):
    """MUMPS with no extra workspace runs out of it (INFOG(1) = −9) on this
    saddle point; the solve is repeated with more and succeeds. (Last: PETSc
    3.18's KSPSolve leaves its nesting level raised after an error, and then
    no longer raises DIVERGED_ITS.)"""
    from solvers import progress

    options(t_ws_mat_mumps_icntl_14=0)
    saddle = SaddlePoint(jacobian(model, scale=1.01), model.C)
    ksp = saddle_ksp(saddle, "t_ws_")
    heard = []
    before = progress.listen(lambda message, always: heard.append((message, always)))
    try:
        _, res = solve(saddle, ksp)
    finally:
        progress.listen(before)
    assert res < 2e-11  # measured 1.1e-12
    assert PETSc.Options().getInt("t_ws_mat_mumps_icntl_14") >= 100
    assert WORKSPACE_RAISED["t_ws_"] >= 100         # said at the run's end
    assert heard and all(always for _, always in heard)     # and at once
    raised = WORKSPACE_RAISED["t_ws_"]
    assert heard[-1][0].endswith(f"-t_ws_mat_mumps_icntl_14 {raised}")
    saddle.destroy()


def test_course_blocks_hold_their_own_constraints(model):
    """Whole-course Schwarz blocks: each holds every coordinate of its
    courses and exactly the constraints among them (a contact of course k
    when k + 1 is in too), and together they cover this rank's courses and
    constraints."""
    first, cons_asm = model.fabric.yarn_start, model.constraints
    yarn_of_row = np.repeat(cons_asm.owner, 3)
    contact = np.repeat(cons_asm.kind == "contact", 3)
    lay = model.layout
    covered, rows_seen = set(), set()
    for coords, rows in model.yarn_blocks(2, 1):
        courses = np.unique(np.searchsorted(first, coords // 3, side="right") - 1)
        assert len(coords) == 3 * (first[courses[-1] + 1] - first[courses[0]])
        assert np.all(np.diff(courses) == 1) and len(courses) <= 4
        lo, hi = courses[0], courses[-1] + 1
        inside = (yarn_of_row >= lo) & (yarn_of_row + contact < hi)
        assert np.array_equal(rows, np.flatnonzero(inside))
        covered |= set(courses.tolist())
        rows_seen |= set(rows.tolist())
    assert set(lay.local_yarns) <= covered
    mine = np.flatnonzero((yarn_of_row >= lay.yarn_start) & (yarn_of_row < lay.yarn_end))
    assert set(mine.tolist()) <= rows_seen


@pytest.mark.parametrize("courses,overlap", [(5, 0), (1, 1), (2, 2)])
def test_course_schwarz_solves_K(model, options, courses, overlap):
    """FGMRES with additive Schwarz on whole courses solves K to the direct
    solution; one subdomain of every course is the direct solve itself."""
    options(t_asm_ksp_type="fgmres", t_asm_pc_type="asm", t_asm_ksp_rtol=1e-12,
            t_asm_saddle_asm_courses=courses, t_asm_saddle_asm_overlap=overlap)
    A = jacobian(model, scale=1.001)
    schwarz = SaddlePoint(A, model.C, blocks=model.yarn_blocks)
    direct = SaddlePoint(A, model.C)
    ksp = saddle_ksp(schwarz, "t_asm_")
    assert ksp.getPC().getType() == "asm"
    z1, r1 = solve(direct, saddle_ksp(direct, "t_asm_direct_"))
    z2, r2 = solve(schwarz, ksp)
    assert r2 < 2e-11  # measured 1.5e-12
    if COMM.size == 1 and courses == 5:
        assert ksp.getIterationNumber() <= 2           # round-off of K (κ ~ 1e10)
    else:
        assert 1 < ksp.getIterationNumber() < 300        # random b, rtol 1e-12
    z2.axpy(-1.0, z1)
    assert z2.norm() <= 1e-10 * z1.norm()  # measured 2.4e-12, 2 ranks 3.0e-11
    for s in (direct, schwarz):
        s.destroy()


@pytest.mark.parametrize("pc_type", ["cholesky", "lu"])
def test_negative_pivots_are_the_negative_eigenvalues(pc_type):
    """MUMPS's LDLᵀ counts the negative eigenvalues of a symmetric matrix
    (a rotated diag(−3, −1, 2, 4, 5)); an LU does not tell."""
    Q, _ = np.linalg.qr(np.random.default_rng(0).standard_normal((5, 5)))
    S = Q @ np.diag([-3.0, -1.0, 2.0, 4.0, 5.0]) @ Q.T
    A = PETSc.Mat().createAIJ((5, 5), nnz=5, comm=PETSc.COMM_SELF)
    A.setValues(range(5), range(5), S.ravel())
    A.assemble()
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType(pc_type)
    ksp.getPC().setFactorSolverType("mumps")
    assert negative_pivots(ksp) == (2 if pc_type == "cholesky" else None)
    b, x = A.createVecs()
    b.set(1.0)
    ksp.solve(b, x)                                  # the factors serve the solve
    assert np.allclose(S @ x.getArray(), 1.0)
