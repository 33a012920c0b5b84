"""Bodies and the barrier that keeps yarn surfaces out of them: signed
distances against closed forms, and E_c's forces and tangent against finite
differences, through the full model's own assembly."""

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import barrier_differences, jersey
from knitfem.contact.colliders import Capsule, Plane, Sphere, parse_colliders
from knitfem.model.full import FullModel, Material

SELF = PETSc.COMM_SELF
BODIES = {"sphere": Sphere(np.array([0.01, -0.002, 0.0]), 0.004),
          "capsule": Capsule(np.array([0.0, -0.002, -0.01]),
                             np.array([0.02, -0.002, 0.01]), 0.003),
          "plane": Plane(np.array([0.0, 0.003, 0.0]), np.array([0.2, -1.0, 0.1]))}


@pytest.mark.parametrize("name", BODIES)
def test_distance_normal_and_curvature(name):
    """n = ∇φ and ∇²φ = ∂n/∂x by central differences; |n| = 1; φ alone
    (``phi``) is the same φ."""
    body = BODIES[name]
    x = np.random.default_rng(0).uniform(-0.01, 0.03, (50, 3))
    phi, n, H = body.distance(x)
    assert np.array_equal(body.phi(x), phi)
    # measured 2.2e-16
    assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=0, rtol=2e-15)
    h = 1e-7
    for i in range(3):
        dx = np.zeros(3)
        dx[i] = h
        pp, npl, _ = body.distance(x + dx)
        pm, nmi, _ = body.distance(x - dx)
        # measured 2.3e-9
        assert np.allclose((pp - pm) / (2 * h), n[:, i], atol=0, rtol=3e-8)
        # measured 4.6e-9
        assert np.allclose((npl - nmi) / (2 * h), H[:, :, i], rtol=5e-8, atol=0)


@pytest.mark.parametrize("name", BODIES)
def test_compiled_distances_are_the_numpy_ones(name):
    """``signed_distance`` by the compiled loops equals each body's own φ,
    at rest and posed by a motion (a plane: its own φ, uncompiled)."""
    from knitfem.contact.colliders import BODIES_VERSION, signed_distance
    from knitfem.contact.motion import Kinematic, Motion
    from knitfem.yarn.kernels import compiled_module

    loops = compiled_module("knitfem.contact._bodies", BODIES_VERSION)
    x = np.random.default_rng(1).uniform(-0.03, 0.03, (2000, 3))
    turned = Kinematic(BODIES[name], Motion([0.0, 1.0], [[0, 0, 0], [0.001, 0.002, 0]],
                                            [[0, 0, 0], [0.3, 0.1, 0.2]]))
    for body in (BODIES[name], turned.at(0.4)):
        ref = body.phi(x)
        # measured 2.8e-16 of the largest (the numpy one's dot product is
        # BLAS's, summed in another order)
        assert np.allclose(signed_distance(body, x, loops), ref, rtol=0,
                           atol=1e-15 * np.abs(ref).max())
        assert np.array_equal(signed_distance(body, x), ref)


def test_sphere_distance_closed_form():
    s = Sphere(np.zeros(3), 2.0)
    phi, n, _ = s.distance(np.array([[3.0, 0, 0], [0, 0, 1.0]]))
    # measured 0
    assert np.allclose(phi, [1.0, -1.0], rtol=2e-15, atol=0)
    assert np.allclose(n, [[1, 0, 0], [0, 0, 1]], rtol=2e-15, atol=0)


def test_parse_colliders():
    bodies = parse_colliders("sphere:0,0,0,0.01; plane:0,-0.02,0,0,1,0")
    assert isinstance(bodies[0], Sphere) and isinstance(bodies[1], Plane)
    for bad in ("cube:1,2,3", "sphere:0,0,0", "sphere:0,0,0,-1", "plane:0,0,0,0,0,0"):
        with pytest.raises(ValueError, match="collider"):
            parse_colliders(bad)


@pytest.fixture(scope="module", params=list(BODIES))
def pressed(request):
    """A 2 x 2 jersey pushed into a body: the barrier is active."""
    fab = jersey(2, 2)
    fab.bodies = (BODIES[request.param],)
    model = FullModel(SELF, fab, Material())
    x = model.rest_state()
    rng = np.random.default_rng(1)
    x.getArray()[:] += 2e-4 * rng.standard_normal(x.getLocalSize())
    yield model, x
    model.destroy()


def test_barrier_is_active_and_pushes_out(pressed):
    model, x = pressed
    P = model.yarn_points(x)
    e, delta, *_ = model.barrier._active(P)
    assert len(e) > 0 and model.barrier.energy(P) > 0
    assert delta.min() < model.barrier.gap


def test_barrier_forces_and_tangent_match_finite_differences(pressed):
    """Q = −∂E/∂ε (E_c included) and K = ∂²E/∂ε² against central
    differences of the energy and of the forces, along random directions."""
    model, x = pressed
    rng = np.random.default_rng(2)
    Q, Qp, Qm = (model.M.createVecLeft() for _ in range(3))
    Q.zeroEntries()
    model.add_elastic_forces(x, Q)
    K = model.stiffness(x)
    h = 1e-9
    for _ in range(3):
        d = x.duplicate()
        d.getArray()[:] = rng.standard_normal(x.getLocalSize())
        xp, xm = x.copy(), x.copy()
        xp.axpy(h, d)
        xm.axpy(-h, d)
        dE = (model.elastic_energy(xp) - model.elastic_energy(xm)) / (2 * h)
        assert dE == pytest.approx(-Q.dot(d), rel=6e-9)  # measured 5.7e-10
        for v, out in ((xp, Qp), (xm, Qm)):
            out.zeroEntries()
            model.add_elastic_forces(v, out)
        Kd = x.duplicate()
        K.mult(d, Kd)
        fd = -(Qp.getArray() - Qm.getArray()) / (2 * h)
        # measured 2.7e-10 of the largest
        assert np.allclose(Kd.getArray(), fd, rtol=0, atol=2e-9 * np.abs(fd).max())


def test_jersey_dropped_on_a_floor_stays_above_it_and_rebounds():
    """A free 2 x 2 jersey falls 1 mm onto a plane (backward Euler, 0.1 s):
    no yarn surface goes into the floor by 0.1 r, it reaches the floor, and
    the floor has turned its fall round: 0.1 s after release it is not at
    rest but rebounding, its mean vertical velocity +0.016 m/s (measured; its
    fastest point 0.044 m/s), where free it would fall at −0.98 m/s and drop
    49 mm."""
    from helpers import run
    from solvers.integrators import BackwardEuler

    fab = jersey(2, 2)
    low = fab.X[..., 1].min() - fab.radius - 1e-3
    fab.bodies = (Plane(np.array([0.0, low, 0.0]), np.array([0.0, 1.0, 0.0])),)
    model = FullModel(SELF, fab, Material(damping=5.0))
    _, x, v = run(model, BackwardEuler, 1e-3, 100)
    assert model.min_collider_distance(x) > -0.1 * fab.radius
    P = model.yarn_points(x)
    assert P[:, 1].min() < low + 2 * fab.radius          # it reached the floor
    assert 0.0 < v.getArray().reshape(-1, 3)[:, 1].mean() < 0.05


@pytest.mark.parametrize("body", [Sphere(np.array([0.0, 0.01, 0.0]), 0.004),
                                  Capsule(np.zeros(3), np.array([0.01, 0.0, 0.0]), 0.002),
                                  Plane(np.zeros(3), np.array([0.0, 2.0, 0.0]))])
def test_body_surfaces_lie_on_the_bodies_and_are_written_and_drawn(tmp_path, body):
    """A body's triangles have their corners on its surface (φ = 0); they go
    to bodies.vtu (meshio reads triangles and the body index) and into the
    pictures, behind the yarns."""
    import matplotlib.pyplot as plt
    import meshio

    from knitfem import io

    pts, tri = body.surface(0.01)
    assert np.abs(body.distance(pts)[0]).max() < 9e-18  # measured 8.7e-19
    assert tri.min() >= 0 and tri.max() < len(pts)
    area = 0.5 * np.linalg.norm(np.cross(pts[tri[:, 1]] - pts[tri[:, 0]],
                                         pts[tri[:, 2]] - pts[tri[:, 0]]), axis=1).sum()
    exact = {Sphere: lambda b: 4 * np.pi * b.R**2,
             Capsule: lambda b: 4 * np.pi * b.R**2 + 2 * np.pi * b.R * np.linalg.norm(b.b - b.a),
             Plane: lambda b: 0.02**2}[type(body)](body)
    # inscribed facets: measured 0.8 % (sphere), 0.34 % (capsule); a plane's
    # exact (2.7e-16)
    assert area == pytest.approx(exact, abs=0,
                                 rel=2e-15 if isinstance(body, Plane) else 0.03)
    io.write_bodies(str(tmp_path / "bodies.vtu"), (body, body), 0.01)
    mesh = meshio.read(tmp_path / "bodies.vtu")
    assert len(mesh.cells_dict["triangle"]) == 2 * len(tri)
    assert set(mesh.point_data["body"]) == {0.0, 1.0}
    fig, ax = plt.subplots()
    fab = jersey(2, 2)
    io._draw_on(ax, fab.curves(fab.X), 5e-4, "three_quarter", None, (body,))
    z = sorted((c.get_zorder(), type(c).__name__) for c in ax.collections)
    plt.close(fig)
    assert z[0] == (0, "PolyCollection") and z[-1][1] == "LineCollection"


def test_friction_forces_and_tangent_match_finite_differences():
    """Within a step the barrier and the lagged friction are one potential
    E_c + D (colliders docstring): the gradient and the Hessian the barrier
    adds against central differences of E_c + D and of the gradient, in the
    sticking (|u| < ε) and the sliding regime."""
    fab = jersey(2, 2)
    fab.bodies = (Plane(np.array([0.0, fab.X[..., 1].min(), 0.0]),
                        np.array([0.0, 1.0, 0.0])),)
    fab.friction = 0.4
    model = FullModel(SELF, fab, Material())
    b = model.barrier
    x0 = model.yarn_points(model.rest_state()).copy()
    b.lag(x0)
    assert len(b.lagged[0]) > 0
    rng = np.random.default_rng(3)
    # K d: measured 2e-6 of the largest sticking (1/8 of what rtol 2e-5 and
    # atol 2e-7 allow), 7.5e-11 sliding
    for size, rtol, atol in ((0.3 * b.eps_slip, 2e-5, 2e-7), (30 * b.eps_slip, 0.0, 6e-10)):
        x = x0 + size * rng.standard_normal(x0.shape)
        dP, gd, Kd, fd = barrier_differences(model, x, rng)
        assert dP == pytest.approx(gd, rel=9e-7)  # measured 8.4e-8
        assert np.allclose(Kd, fd, rtol=rtol, atol=atol * np.abs(fd).max())
    model.destroy()


@pytest.mark.parametrize("mu", [0.0, 0.1, 0.5])
def test_yarn_on_an_inclined_plane_sticks_or_slides_as_coulomb_says(mu):
    """A straight free yarn lying on a plane tilted by 10° (tan = 0.18),
    backward Euler 0.1 s: without friction it slides with g sin θ, with
    μ = 0.1 with g (sin θ − μ cos θ), with μ = 0.5 it stays (within 2 % of
    the frictionless slide: below μλ a point still moves by up to ε a step)."""
    from knitfem.knit.fabric import Fabric
    from helpers import run
    from solvers.integrators import BackwardEuler

    theta, r = np.radians(10.0), 5e-4
    down = np.array([np.cos(theta), -np.sin(theta), 0.0])        # down the slope
    normal = np.array([np.sin(theta), np.cos(theta), 0.0])
    s = np.linspace(-0.01, 0.01, 12)
    X = (s[:, None] * np.array([0.0, 0.0, 1.0]) + 1.099 * r * normal)[None]  # resting
    fab = Fabric(X=X, radius=r, friction=mu,
                 bodies=(Plane(np.zeros(3), normal),))
    model = FullModel(SELF, fab, Material(EA=10.0, EI=1e-6, rho=1e-3))
    t, steps = 0.1, 100
    _, x, v = run(model, BackwardEuler, t / steps, steps)
    moved = (x.getArray().reshape(-1, 3) - X[0]).mean(axis=0) @ down
    g = 9.81
    slide = 0.5 * g * max(np.sin(theta) - mu * np.cos(theta), 0.0) * t * t
    if mu >= np.tan(theta):      # sticks, but for the creep of f₀'s smoothing
        assert abs(moved) < 0.02 * 0.5 * g * np.sin(theta) * t * t
    else:
        assert moved == pytest.approx(slide, rel=0.05)
    model.destroy()


def test_bodies_and_friction_do_not_care_which_way_the_world_faces():
    """Knit and bodies turned and moved together: the barrier's energy, the
    lagged friction's potential and their Hessian's spectrum stay, and the
    forces turn with them."""
    import scipy.sparse as sp

    from knitfem.cli.scenes import rotation

    R, shift = rotation((30, -50, 70)), np.array([0.01, -0.02, 0.03])
    fab = jersey(2, 2)
    low = fab.X[..., 1].min()
    bodies = (Sphere(np.array([0.004, low - 0.003, 0.002]), 0.0032),
              Capsule(np.array([0.0, low + 1e-4, -0.01]),
                      np.array([0.01, low + 1e-4, 0.01]), 5e-4),
              Plane(np.array([0.0, low + 2e-4, 0.0]), np.array([0.1, 1.0, 0.0])))
    turned = (Sphere(R @ bodies[0].centre + shift, bodies[0].R),
              Capsule(R @ bodies[1].a + shift, R @ bodies[1].b + shift, bodies[1].R),
              Plane(R @ bodies[2].point + shift, R @ bodies[2].normal))
    rng = np.random.default_rng(5)
    x = fab.X.reshape(-1, 3) + 1e-4 * rng.standard_normal((fab.X.size // 3, 3))
    x0 = fab.X.reshape(-1, 3)
    out = []
    for bs, move in ((bodies, lambda p: p), (turned, lambda p: p @ R.T + shift)):
        fab.bodies, fab.friction = bs, 0.3
        model = FullModel(SELF, fab, Material())
        b = model.barrier
        b.lag(move(x0))
        g = np.zeros_like(x)
        b.add_gradient(move(x), g)
        slot = model.slot3
        values = np.zeros_like(model.K_values)
        b.add_hessian(move(x), slot, values)
        indptr3, indices3, _ = model.pattern.blocks3()
        K = sp.csr_matrix((values, indices3, indptr3)).toarray()
        out.append((b.energy(move(x)), b.friction_potential(move(x)), g,
                    np.linalg.eigvalsh(0.5 * (K + K.T))))
        model.destroy()
    (e0, d0, g0, k0), (e1, d1, g1, k1) = out
    assert e0 > 0 and d0 > 0
    # measured 2.1e-15 and 1.8e-15
    assert e1 == pytest.approx(e0, rel=1.5e-14, abs=0)
    assert d1 == pytest.approx(d0, rel=1.5e-14, abs=0)
    # measured 1.1e-13
    assert np.allclose(g1, g0 @ R.T, rtol=0, atol=7e-13 * np.abs(g0).max())
    assert np.allclose(k1, k0, rtol=0, atol=6e-13 * np.abs(k0).max())  # measured 1e-9


@pytest.mark.parametrize("check", [True, False])
def test_a_step_through_a_thin_body_is_refused(check):
    """A straight yarn falls onto a thin rod (radius 0.6 r) under backward
    Euler steps of 1e-2 s, which carry it farther than rod and yarn are
    thick: the step that would pass through is refused and halved, and the
    yarn rests on the rod. Without the check it falls through."""
    from knitfem.knit.fabric import Fabric
    from knitfem.cli.scenes import straight_yarn
    from solvers.integrators import BackwardEuler

    rod = Capsule(np.array([0.01, -0.003, -0.01]), np.array([0.01, -0.003, 0.01]), 3e-4)
    fab = Fabric(straight_yarn(0.02, 10)[None], 5e-4, bodies=(rod,))
    model = FullModel(SELF, fab, Material())
    if not check:
        model.tunnelled = lambda x0, x1: None
    integ = BackwardEuler(model, 1e-2)
    x = model.start_state()
    v = x.duplicate()
    v.zeroEntries()
    for n in range(10):
        integ.step(n * 1e-2, x, v)
    middle = x.getArray().reshape(-1, 3)[fab.npoints // 2]
    if check:
        assert middle[1] > rod.a[1] + rod.R and model.min_collider_distance(x) > 0
    else:
        assert middle[1] < rod.a[1] - 0.02                  # fell through


def test_friction_smoothing_follows_the_step_as_first_tried():
    """ε = ε_v h of the step as first tried: its halvings keep it, the next
    step's lag takes the next step's."""
    from knitfem.contact.colliders import SLIP_SPEED

    fab = jersey(2, 2)
    fab.bodies, fab.friction = (BODIES["plane"],), 0.3
    model = FullModel(SELF, fab, Material())
    x = model.rest_state()
    barrier = model.barrier
    model.begin_step(x, 0.0)
    model.move_bodies(0.0, 0.01)
    # round-off (measured 0, 0 and 1.4e-16)
    assert barrier.eps_slip == pytest.approx(SLIP_SPEED * 0.01, rel=1e-15, abs=0)
    model.move_bodies(0.0, 0.005)                     # the step halved
    assert barrier.eps_slip == pytest.approx(SLIP_SPEED * 0.01, rel=1e-15, abs=0)
    model.begin_step(x, 0.005)
    model.move_bodies(0.005, 0.0075)
    assert barrier.eps_slip == pytest.approx(SLIP_SPEED * 0.0025, rel=1e-15, abs=0)
    model.destroy()


def test_distances_kept_for_a_state_are_those_computed_afresh(pressed):
    """The δ a barrier keeps for a state (``surface_distance``) is φ − r of
    every body computed afresh, and is formed again when the points move
    (in place) or a moving body is posed at another time."""
    from knitfem.contact.motion import Kinematic, Motion

    model, x = pressed
    b = model.barrier
    body = b.bodies[0]
    b.bodies = (Kinematic(body, Motion([0.0, 1.0], [[0, 0, 0], [0.001, 0.002, 0]])),)
    P = model.yarn_points(x).copy()

    def afresh():
        pts = b.el.points(P).reshape(-1, 3)
        return (b.phi(b.bodies[0], pts) - b.radius).reshape(b.surface_distance(P)[0].shape)

    for change in (lambda: None, lambda: P.__iadd__(1e-4), lambda: b.at(0.5)):
        change()
        assert b.surface_distance(P)[0] is b.surface_distance(P)[0]
        assert np.array_equal(b.surface_distance(P)[0], afresh())        # exactly


@pytest.mark.parametrize("name", BODIES)
def test_the_lowest_point_of_a_path_is_where_it_comes_nearest_a_body(name):
    """``lowest``: φ at the τ it gives is the least over 2 001 points of each
    straight path (paths through, past and away from the body, and of
    zero length)."""
    body = BODIES[name]
    rng = np.random.default_rng(3)
    p = 0.01 * rng.standard_normal((200, 3)) + [0.01, 0.0, 0.0]
    q = 0.02 * rng.standard_normal((200, 3))
    q[0] = 0.0
    tau = body.lowest(p, q)
    assert np.all((tau >= 0) & (tau <= 1))
    t = np.linspace(0, 1, 2001)
    sampled = np.min([body.phi(p + s * q) for s in t], axis=0)
    # never above a sample (measured 0; a τ off by a sample's spacing, 3e-5
    # of a path, would be ~1e-6 m above)
    assert np.all(body.phi(p + tau[:, None] * q) <= sampled + 1e-12)


@pytest.mark.parametrize("name", ["sphere", "capsule"])
def test_an_update_through_a_body_stops_at_its_surface(name):
    """The step filter stops an update whose straight path passes through a
    body and ends beyond it (its end alone shows nothing) where the yarn
    surface first reaches the gap's bound, δ = −ĥ, as it stops one ending
    inside. Without the search along the path, τ = 1 and the knit lands
    6 r beyond the body."""
    body = {"sphere": Sphere(np.zeros(3), 0.004),
            "capsule": Capsule(np.array([-0.01, 0, 0]), np.array([0.01, 0, 0]), 0.004)}[name]
    fab = jersey(2, 2)
    fab.bodies = (body,)
    model = FullModel(SELF, fab, Material())
    b = model.barrier
    P = model.yarn_points(model.rest_state()).copy()
    P += np.array([0.0, 0.012, 0.0]) - P.mean(0)          # 12 mm above the centre
    for far in (0.024, 0.014):                             # through it, into it
        d = np.zeros_like(P)
        d[:, 1] = -far
        tau = b.step_limit(P, d)
        delta = body.phi(b.el.points(P + tau * d).reshape(-1, 3)) - b.radius
        # bisection to 2^-30 of the path: measured −0.1 r + 1.2e-9 r and 4.3e-9 r
        assert 0 < tau < 1
        assert delta.min() == pytest.approx(-b.gap, rel=0, abs=1e-7 * b.radius)
    model.destroy()


def test_the_swept_depth_samples_only_the_paths_that_can_reach_its_floor():
    """``swept_depth`` below −r is the deepest point of every path sampled
    (a knit swept through a sphere, parts of it far from it), and where no
    path can reach −r (the knit 10 r away moving 5 r) it samples none."""
    body = Sphere(np.zeros(3), 0.004)
    fab = jersey(2, 2)
    fab.bodies = (body,)
    model = FullModel(SELF, fab, Material())
    b, r = model.barrier, model.fabric.radius
    P = model.yarn_points(model.rest_state()).copy()
    P += np.array([0.0, 0.012, 0.0]) - P.mean(0)          # 12 mm above the centre
    d = np.zeros_like(P)
    d[:, 1] = -0.024                                       # through it
    every = b.swept_depth(P, P + d, floor=np.inf)
    assert every < -r and b.swept_depth(P, P + d) == every
    P += np.array([0.0, 0.0, 0.004 + 10 * r + np.ptp(P[:, 2])]) - [0, 0, P[:, 2].min()]
    d[:, 1] = -5 * r
    assert b.min_distance(P) > 10 * r and b.min_distance(P + d) > 10 * r
    assert b.swept_depth(P, P + d) == np.inf > b.swept_depth(P, P + d, floor=np.inf) > 0
    model.destroy()


def test_a_body_that_moves_through_a_resting_knit_is_seen_along_its_path():
    """A ball that passes through a knit at rest within a step (from 12 mm
    behind it to 12 mm before) leaves both ends clear; the swept depth,
    sampled along the ball's motion relative to the knit, goes below −r."""
    from knitfem.contact.motion import Kinematic, Motion

    ball = Kinematic(Sphere(np.array([0.0, 0.0, -0.012]), 0.004),
                     Motion([0.0, 0.01], [[0, 0, 0], [0, 0, 0.024]]))
    fab = jersey(2, 2)
    fab.bodies = (ball,)
    model = FullModel(SELF, fab, Material())
    b, r = model.barrier, model.fabric.radius
    P = model.yarn_points(model.rest_state()).copy()
    P -= P.mean(0)
    b.lag(P, 0.0)
    b.step_to(0.0, 0.01)
    assert b.min_distance(P) > 10 * r
    assert b.swept_depth(P, P) < -r
    model.destroy()


def test_a_knit_in_a_crease_feels_each_body_barrier_and_friction():
    """Two planes meeting in a crease under a jersey, its lowest points within
    the gap of both: E_c + D is the sum of each body's own (the barrier of
    both bodies against those of each alone, and friction lagged on both),
    and its gradient and Hessian match central differences there."""
    fab = jersey(2, 2)
    low = np.array([0.0, fab.X[..., 1].min(), 0.0])
    crease = (Plane(low, np.array([0.0, 1.0, 0.2])), Plane(low, np.array([0.0, 1.0, -0.2])))
    fab.friction = 0.4
    models = []
    for bodies in (crease, crease[:1], crease[1:]):
        fab.bodies = bodies
        models.append(FullModel(SELF, fab, Material()))
    x0 = models[0].yarn_points(models[0].rest_state()).copy()
    for m in models:
        m.barrier.lag(x0)
    both = models[0].barrier
    e, *_, which = both._active(x0)
    twice = np.intersect1d(e[(which == 0).all(axis=1)], e[(which == 1).all(axis=1)])
    assert len(twice) > 0                             # elements in both gaps
    rng = np.random.default_rng(5)
    x = x0 + 0.3 * both.eps_slip * rng.standard_normal(x0.shape)
    total = [m.barrier.energy(x) + m.barrier.friction_potential(x) for m in models]
    grads = []
    for m in models:
        g = np.zeros_like(x)
        m.barrier.add_gradient(x, g)
        grads.append(g)
    # round-off of sums in another order: measured 0 and 1.4e-16
    assert total[0] == pytest.approx(total[1] + total[2], rel=1e-14, abs=0)
    assert np.allclose(grads[0], grads[1] + grads[2], rtol=0, atol=1e-14 * np.abs(grads[0]).max())
    dP, gd, Kd, fd = barrier_differences(models[0], x, rng)
    assert dP == pytest.approx(gd, rel=9e-7)                     # measured 4.6e-7
    # measured 1.7e-6 of the largest (sticking, as the one-body test's)
    assert np.allclose(Kd, fd, rtol=2e-5, atol=2e-7 * np.abs(fd).max())
    for m in models:
        m.destroy()
