"""The static path (solvers/statics.py) against closed forms and dynamics.

Every test solves −Q(ε, 0) + Cᵀμ = 0, C ε = d with ``StaticSolver`` from the
stress-free rest state: Newton with pseudo-transient continuation.
"""

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc
from scipy.integrate import solve_bvp
from scipy.optimize import brentq

from helpers import COMM, gather, jersey, run
from knitfem.yarn import bspline
from knitfem.model.full import FullModel, Material
from knitfem.knit.pattern import Jersey
from knitfem.cli.scenes import make_fabric
from solvers.integrators import BackwardEuler
from solvers.statics import StaticSolver

SELF = PETSc.COMM_SELF
L, G = 0.1, 9.81


def static(fabric, material, comm=SELF):
    """Solve; return the model, the control points (N, 3) (all, on every rank), the
    solver and, for every Newton iteration (the SNES monitor), |F| and the
    max norm of the coordinates' update."""
    model = FullModel(comm, fabric, material)
    solver = StaticSolver(model)
    norms = []

    def monitor(snes, it, fnorm):
        du = solver.saddle.split(snes.getSolutionUpdate())[0] if it else [0.0]
        norms.append((fnorm, COMM.tompi4py().allreduce(np.abs(du).max(),
                                                       op=MPI.MAX)))

    solver.snes.setMonitor(monitor)
    x = model.rest_state()
    solver.solve(x)
    assert solver.snes.getConvergedReason() > 0
    return model, gather(comm, x).reshape(-1, 3), solver, norms


def centreline(P, n=2001):
    return bspline.curve_points(P, np.linspace(0, len(P) - 3, n))


def cantilever(EI, rho=1e-3, nseg=40):
    return static(make_fabric("cantilever", length=L, segments=nseg),
                  Material(rho=rho, EA=1e4, EI=EI, gravity=G))


def catenary_sag(length, span):
    a = brentq(lambda a: 2 * a * np.sinh(span / (2 * a)) - length, span / 50, 1e3)
    return a * (np.cosh(span / (2 * a)) - 1)


def catenary():
    """The issue's catenary: L = 0.1, span 0.08, EI 1e-10, EA 1e4, ρ 1e-3."""
    return static(make_fabric("catenary", length=L, span=0.08, segments=40),
                  Material(rho=1e-3, EA=1e4, EI=1e-10, gravity=G))


@pytest.mark.parametrize("case", ["cantilever", "catenary"])
def test_newton_ends_quadratically_on_the_issue_cases(case):
    """The bt line search stalled here (|F| 2.880e-5 → 2.710e-5 in 50 its at
    a fifth of the load). Now: converged in a few tens of iterations, and the
    last update above round-off, δ_k, is followed by δ_(k+1) ≤ C δ_k² with
    C L ≤ 1e4 (quadratic; a linear rate keeps δ_(k+1)/δ_k near a constant);
    |F| drops to its round-off floor (EA × machine epsilon) in that step."""
    _, _, solver, norms = cantilever(1.962e-4) if case == "cantilever" \
        else catenary()
    assert len(norms) <= 30
    f, du = np.array(norms).T
    k = np.nonzero(du > 1e-8 * L)[0][-1]
    assert du[k + 1] <= 1e4 * du[k] ** 2 / L
    assert du[k + 1] <= 0.005 * du[k]  # measured 0.0004
    assert f[k + 1] <= 10 * f[-1] and f[k - 1] > 100 * f[-1]
    assert solver.sigma <= 2e-7 * solver.sigma0  # Newton's own steps: 1.8e-8


@pytest.mark.parametrize("nseg", [40, 160])
def test_small_deflection_cantilever_tip(nseg):
    """Euler–Bernoulli: tip drop q L⁴ / (8 EI), q = ρ g (q L³/EI = 0.05).
    At 160 segments |F| ends at its round-off floor (4.8e-10 N), above 1e-6
    of the load (1.1e-10 N): the solve accepts it as converged."""
    EI, rho = 1.962e-4, 1e-3
    _, P, _, _ = cantilever(EI, rho, nseg)
    tip = bspline.curve_points(P, np.array([float(nseg)]))[0]
    # measured 3.1e-5 at both (the linear theory's error, not the segments')
    assert -tip[1] == pytest.approx(rho * G * L**4 / (8 * EI), rel=4e-4)


def test_catenary_sag():
    _, P, _, _ = catenary()
    sag = -centreline(P)[:, 1].min()
    assert sag == pytest.approx(catenary_sag(L, 0.08), rel=0.01)


def elastica(alpha):
    """Inextensible cantilever under its weight, q L³/EI = alpha, s in units
    of L: θ'' = alpha (1 − s) cos θ, θ(0) = 0, θ'(1) = 0; x' = cos θ,
    y' = sin θ from the origin. Returns (tip drop, pull-in) over L."""
    def rhs(s, u):
        th, w, x, y = u
        return np.vstack([w, alpha * (1 - s) * np.cos(th), np.cos(th), np.sin(th)])

    def bc(a, b):
        return np.array([a[0], b[1], a[2], a[3]])

    s = np.linspace(0, 1, 101)
    guess = np.vstack([-alpha * s / 6, -alpha * (1 - s) ** 2 / 2, s, 0 * s])
    sol = solve_bvp(rhs, bc, s, guess, tol=1e-10, max_nodes=100000)
    assert sol.success
    th, _, x, y = sol.sol(1.0)
    return -y, 1 - x


def test_large_deflection_cantilever_against_elastica():
    alpha, rho = 4.0, 1e-3
    drop, pull = elastica(alpha)
    assert drop > 0.3 and pull > 0.05                  # far from linear
    _, P, _, _ = cantilever(rho * G * L**3 / alpha, rho)
    tip = bspline.curve_points(P, np.array([40.0]))[0]
    assert -tip[1] / L == pytest.approx(drop, rel=4e-4)  # measured 3.5e-5
    assert (L - tip[0]) / L == pytest.approx(pull, rel=6e-4)  # measured 5.4e-5


def test_hanging_knit_mechanism_matches_damped_dynamics():
    """A jersey hanging from its top course is a mechanism at rest (K is
    singular on the constraint space): the static drape equals the end of a
    long damped dynamic run, and it is a minimum (K ≥ 0 on null(C))."""
    fab = jersey(3, 2, hold="top")
    model, P, _, _ = static(fab, Material(), COMM)
    dyn = FullModel(COMM, fab, Material(damping=20.0))
    _, x, v = run(dyn, BackwardEuler, 1e-2, 300)
    Pd = gather(COMM, x).reshape(P.shape)
    X = fab.X
    sag = X[..., 1].min() - Pd[..., 1].min()
    assert sag > 1e-5                                            # it did sag
    assert abs(P[..., 1].min() - Pd[..., 1].min()) < 2e-13 * sag  # measured 1.2e-14
    # measured 1.5e-13 (2 ranks 2.8e-13)
    assert np.abs(P - Pd).max() < 2e-12 * np.abs(Pd - X).max()
    # on null(C), K has zero modes at rest and is positive definite at the drape
    rest = np.linalg.eigvalsh(reduced_stiffness(model, model.rest_state()))
    assert abs(rest[0]) < 6e-13 * rest[-1]  # measured 5.5e-14
    xs = model.rest_state()
    lo, hi = xs.getOwnershipRange()
    xs.getArray()[:] = P.ravel()[lo:hi]
    drape = np.linalg.eigvalsh(reduced_stiffness(model, xs))
    assert drape[0] > 1e-9 * drape[-1]


def reduced_stiffness(model, x):
    """Zᵀ K Z with Z an orthonormal basis of null(C) (dense, small systems)."""
    from scipy.linalg import null_space

    from helpers import to_scipy

    K = np.vstack(COMM.tompi4py().allgather(to_scipy(model.stiffness(x)).toarray()))
    C = np.vstack(COMM.tompi4py().allgather(to_scipy(model.C).toarray()))
    Z = null_space(C)
    return Z.T @ K @ Z


def test_failed_linear_solve_is_named():
    """A KSP that stops unconverged ends the solve with its reason by name."""
    from solvers.integrators import SimulationError

    opts = PETSc.Options()
    given = dict(static_ksp_type="gmres", static_pc_type="none",
                 static_ksp_max_it="2")
    for k, v in given.items():
        opts.setValue(k, v)
    try:
        model = FullModel(SELF, make_fabric("cantilever", length=L, segments=10),
                          Material(rho=1e-3, EA=1e4, EI=1.962e-4))
        with pytest.raises(SimulationError, match=r"DIVERGED_MAX_IT, 2 iterations"):
            StaticSolver(model).solve(model.rest_state())
    finally:
        for k in given:
            opts.delValue(k)


def test_knit_resting_on_a_body_is_in_equilibrium_against_it():
    """A 4 x 4 swatch held by its top course, started lifted 30° out, with a
    sphere behind where it would hang: the static solve ends pressed on the
    sphere (pushed out to +z, no yarn surface inside) at |F| ~ round-off."""
    from knitfem.contact.colliders import Sphere

    fab = make_fabric("hanging", jersey=Jersey(4, 4), tilt=30.0)
    X = fab.X.reshape(-1, 3)
    centre = np.array([X[:, 0].mean(), X[:, 1].mean(), -0.006])
    fab.bodies = (Sphere(centre, 0.0065),)            # its top 0.5 mm in front
    model, P, solver, norms = static(fab, Material())
    x = model.rest_state()
    x.getArray()[:] = P.ravel()
    assert model.min_collider_distance(x) > 0
    assert P[..., 2].mean() > 5e-4
    assert norms[-1][0] < 1e-7 * model.Qg.norm()


def test_a_knit_with_no_equilibrium_is_said_to_have_none():
    """A swatch on a sphere without friction slides off: the static solve
    stops with |F| far above the load and says there is no equilibrium."""
    from solvers.integrators import SimulationError

    model = FullModel(SELF, make_fabric("drape", jersey=Jersey(6, 6)), Material())
    with pytest.raises(SimulationError, match="no equilibrium near this state"):
        StaticSolver(model).solve(model.start_state())
