"""Bodies that move: the keyframed motion passes through its keyframes and
is C¹, a posed body is the rest body moved rigidly, a body moving at a
constant velocity carries a resting yarn by friction, the barrier with
the carried friction is still one potential (finite differences) and the
implicit step's too, and an implicit step's guess carries the points near
a moving body with it."""

import json

import numpy as np
import pytest
from petsc4py import PETSc

from helpers import barrier_differences, jersey, run, step_potential_slopes
from knitfem.contact.colliders import Capsule, Plane, Sphere
from knitfem.contact.motion import (Kinematic, Motion, carried, load_motions,
                                   rotation_matrix)
from knitfem.knit.fabric import Fabric
from knitfem.model.full import FullModel, Material

SELF = PETSc.COMM_SELF
KEYS = dict(times=[0.0, 0.3, 0.5, 1.0],
            translations=[[0, 0, 0], [0.01, 0.0, 0.002], [0.01, 0.004, 0.0],
                          [-0.002, 0.0, 0.0]],
            rotations=np.radians([[0, 0, 0], [10, 0, 0], [0, 25, 5], [0, 0, 40]]),
            pivot=[0.001, 0.002, -0.003])


@pytest.mark.parametrize("ease", [False, True])
def test_motion_passes_through_its_keyframes_and_is_c1(ease):
    """At every keyframe the pose is the keyframe's exactly; across an inner
    keyframe the velocity of a body point has no jump (one-sided differences
    of step 1e-6 s agree to 1e-4 of the speed: measured 3e-5); with ``ease``
    it starts and stops from rest."""
    m = Motion(**KEYS, ease=ease)
    p = np.array([0.003, -0.001, 0.002])
    for k, t in enumerate(KEYS["times"]):
        R, s = m.pose(t)
        want = (rotation_matrix(KEYS["rotations"][k]) @ (p - KEYS["pivot"])
                + KEYS["pivot"] + KEYS["translations"][k])
        # round-off (measured 3.5e-18 m of ~1e-2 m; 4.4e-16)
        assert np.allclose(R @ p + s, want, rtol=0, atol=3e-17)
        assert np.allclose(R @ R.T, np.eye(3), rtol=0, atol=4e-15)

    def x(t):
        R, s = m.pose(t)
        return R @ p + s

    h = 1e-6
    for t in KEYS["times"][1:-1]:
        before = (x(t) - x(t - h)) / h
        after = (x(t + h) - x(t)) / h
        assert np.linalg.norm(after - before) < 1e-4 * np.linalg.norm(after)
    start = np.linalg.norm(x(h) - x(0.0)) / h
    assert (start < 1e-4) if ease else (start > 1e-3)


def test_two_keyframes_move_at_constant_velocity_and_turn_about_a_fixed_axis():
    """Two keyframes: the translation is linear in t, a turn about a fixed
    axis the linearly interpolated angle, exactly; with ease, smoothstep."""
    m = Motion([1.0, 3.0], [[0, 0, 0], [0.02, 0, 0]],
               np.radians([[0, 0, 0], [0, 0, 60]]))
    for t in (1.5, 2.0, 2.7):
        R, s = m.pose(t)
        angle = 30.0 * (t - 1.0)
        # round-off (measured 2.2e-16, and 0 m of ~1e-2 m)
        assert np.allclose(R, rotation_matrix(np.radians([0, 0, angle])), rtol=0,
                           atol=2e-15)
        assert np.allclose(s, [0.01 * (t - 1.0), 0, 0], rtol=0, atol=2e-17)
    eased = Motion([0.0, 1.0], rotations=np.radians([[0, 0, 0], [60, 0, 0]]),
                   ease=True)
    R = eased.pose(0.25)[0]
    smooth = 3 * 0.25**2 - 2 * 0.25**3
    assert np.arctan2(R[2, 1], R[1, 1]) == pytest.approx(np.radians(60) * smooth,
                                                          rel=1.5e-15, abs=0)  # measured 1.7e-16


@pytest.mark.parametrize("body", [Sphere(np.array([0.01, -0.002, 0.0]), 0.004),
                                  Capsule(np.array([0.0, -0.002, -0.01]),
                                          np.array([0.02, -0.002, 0.01]), 0.003),
                                  Plane(np.array([0.0, 0.003, 0.0]),
                                        np.array([0.2, -1.0, 0.1]))])
def test_a_posed_body_is_the_rest_body_moved(body):
    """φ of the posed body at R x + s is φ of the rest body at x, its normal
    turned by R."""
    moving = Kinematic(body, Motion(**KEYS)).at(0.4)
    x = np.random.default_rng(1).normal(scale=0.01, size=(20, 3))
    y = x @ moving.R.T + moving.s
    phi0, n0, _ = body.distance(x)
    phi1, n1, _ = moving.distance(y)
    # round-off (measured 6.9e-18 m of φ ~1e-2 m; 1.1e-15)
    assert np.allclose(phi1, phi0, rtol=0, atol=6e-17)
    assert np.allclose(n1, n0 @ moving.R.T, rtol=0, atol=1e-14)


def test_motion_file_keyframes_the_bodies_it_names(tmp_path):
    path = tmp_path / "motion.json"
    path.write_text(json.dumps({"bodies": [{"body": 1, "pivot": [0, 0, 0], "keyframes": [
        {"t": 0}, {"t": 2, "translation": [0, 0.02, 0], "rotation": [0, 0, 90]}]}]}))
    bodies = (Sphere(np.zeros(3), 0.01), Sphere(np.array([0.01, 0, 0]), 0.01))
    moved = load_motions(str(path), bodies)
    assert moved[0] is bodies[0]
    # measured 1.1e-18 m; round-off of 0.03 m is 7e-18
    assert np.allclose(moved[1].at(2.0).body.centre, [0, 0.03, 0], rtol=0, atol=2e-17)
    path.write_text(json.dumps({"bodies": [{"body": 5, "keyframes": [{"t": 0}]}]}))
    with pytest.raises(ValueError, match="there are 2 bodies"):
        load_motions(str(path), bodies)
    path.write_text(json.dumps({"bodies": [{"keyframes": []}]}))
    with pytest.raises(ValueError, match="expected"):
        load_motions(str(path), bodies)


@pytest.mark.parametrize("mu", [0.0, 0.5])
def test_a_floor_moving_at_constant_velocity_carries_a_resting_yarn(mu):
    """A straight free yarn resting on a floor that slides along x at V =
    1 cm/s (the floor's shape does not change: only friction knows it
    moves), backward Euler 0.1 s: with μ = 0.5 friction accelerates the
    yarn at μg until it moves with the floor, so it travels V t − V²/(2μg)
    (measured within 0.2 % of it); without friction it stays."""
    from solvers.integrators import BackwardEuler

    r, V, t, steps = 5e-4, 0.01, 0.1, 100
    s = np.linspace(-0.01, 0.01, 12)
    X = (s[:, None] * np.array([0.0, 0.0, 1.0]) + [0.0, 1.099 * r, 0.0])[None]
    floor = Kinematic(Plane(np.zeros(3), np.array([0.0, 1.0, 0.0])),
                      Motion([0.0, 1.0], [[0, 0, 0], [V, 0, 0]]))
    fab = Fabric(X=X, radius=r, friction=mu, bodies=(floor,))
    model = FullModel(SELF, fab, Material(EA=10.0, EI=1e-6, rho=1e-3))
    _, x, _ = run(model, BackwardEuler, t / steps, steps)
    moved = (x.getArray().reshape(-1, 3) - X[0]).mean(axis=0)
    if mu:
        assert moved[0] == pytest.approx(V * t - V * V / (2 * mu * 9.81), rel=0.01)
    else:
        assert abs(moved[0]) < 1e-16 * r          # no force along x: measured 0
    # it rests: measured 3.6e-20 and 5.2e-19 m on two machines (an ulp of its
    # height, 1.1 r, is 1.2e-19 m)
    assert abs(moved[1]) < 4e-15 * r
    model.destroy()


def test_carried_friction_forces_and_tangent_match_finite_differences():
    """With a body that moves and turns over the step, E_c + D (the
    reference carried by the body) is one potential: its gradient and
    Hessian against central differences."""
    fab = jersey(2, 2)
    low = fab.X[..., 1].min()
    fab.bodies = (Kinematic(Capsule(np.array([-0.01, low - 0.002, 0.0]),
                                    np.array([0.02, low - 0.002, 0.0]), 0.002),
                            Motion([0.0, 0.1], [[0, 0, 0], [0.002, 0.0, 0.001]],
                                   np.radians([[0, 0, 0], [0, 5, 0]]),
                                   pivot=[0.005, low, 0.0])),)
    fab.friction = 0.4
    model = FullModel(SELF, fab, Material())
    b = model.barrier
    x0 = model.yarn_points(model.rest_state()).copy()
    x0[:, 1] -= 0.1 * b.gap                       # every low point in contact
    b.lag(x0, 0.0)
    b.step_to(0.0, 0.01)
    assert len(b.lagged[0]) > 0
    rng = np.random.default_rng(3)
    dP, gd, Kd, fd = barrier_differences(model, x0 + 1e-5 * rng.standard_normal(
        x0.shape), rng)
    # measured 3.2e-8 relative, and 4.4e-9 of the largest
    assert dP == pytest.approx(gd, rel=3e-7)
    assert np.allclose(Kd, fd, rtol=0, atol=4e-8 * np.abs(fd).max())
    model.destroy()


def test_points_are_carried_by_the_bodies_near_them():
    """``carried``: with one body, every point well within the reach goes as
    a point of the body would (x¹ = R₁R₀ᵀ(x − s₀) + s₁, to round-off), a
    point 1.25 times as far half way, one 1.67 times as far not at all (a
    knit is carried whole, by the nearest of its points); beside a body at
    rest, a point much nearer the moving body goes with it, one much nearer
    the resting body stays, and one as near to both goes half way; without
    a moving body there is nothing to carry."""
    motion = Motion(**KEYS)
    arm = Kinematic(Capsule(np.zeros(3), np.array([0.0, 0.0, 0.05]), 0.01), motion)
    rng = np.random.default_rng(5)
    x = 0.03 * rng.standard_normal((40, 3))
    (R0, s0), (R1, s1) = motion.pose(0.31), motion.pose(0.37)
    rigid = (x - s0) @ (R1 @ R0.T).T + s1 - x
    d = carried((arm,), x, 0.31, 0.37, length=5e-3, reach=1.0)
    # measured 0 (the points move up to 9 mm, 0.1 m at most from the arm)
    assert np.allclose(d, rigid, rtol=0, atol=1e-16)
    arm.at(0.31)
    edge = arm.body.a + np.array([0.0, 0.06, 0.0])            # 5 cm from the arm
    moved = (edge - s0) @ (R1 @ R0.T).T + s1 - edge
    for reach, share in ((1.0, 1.0), (0.04, 0.5), (0.03, 0.0)):     # 1, 1.25, 1.67 R
        d = carried((arm,), edge[None], 0.31, 0.37, length=5e-3, reach=reach)[0]
        assert np.allclose(d, share * moved, rtol=0, atol=1e-16)
    rest = Sphere(np.array([0.0, 0.0, -0.5]), 0.01)
    near_arm = np.array([[0.0, 0.012, 0.02]])            # 2 mm from the arm
    near_rest = np.array([[0.0, 0.0, -0.488]])           # 2 mm from the sphere
    both = [carried((arm, rest), p, 0.31, 0.37, length=5e-3, reach=1.0)[0]
            for p in (near_arm, near_rest)]
    # 0.49 m further from the other body, 98 lengths: e^-98
    assert np.allclose(both[0], carried((arm,), near_arm, 0.31, 0.37, 5e-3, 1.0)[0],
                       rtol=0, atol=1e-40)
    assert np.abs(both[1]).max() < 1e-40
    twin = Kinematic(Sphere(np.array([0.0, 0.0, -0.5]), 0.01),
                     Motion([0.0, 1.0], [[0, 0, 0], [0.01, 0, 0]]))
    mid = np.array([[0.02, 0.0, -0.5]])                   # 1 cm from both spheres
    half = carried((Sphere(np.array([0.04, 0.0, -0.5]), 0.01), twin), mid, 0.0, 0.5,
                   5e-3, 1.0)
    # measured 4.3e-19 m
    assert half[0] == pytest.approx([0.0025, 0.0, 0.0], abs=1e-17)
    assert carried((rest,), x, 0.0, 1.0, 5e-3, 1.0) is None


def test_a_free_yarns_step_potential_is_what_the_residual_derives_from():
    """A yarn resting on a floor that slides and turns (friction lagged on
    it, no constraint rows): backward Euler's Φ (``NewtonStepper``) has the
    residual as its gradient (central differences along a random direction),
    through ``FullModel.potential``."""
    from solvers.integrators import BackwardEuler

    r = 5e-4
    s = np.linspace(-0.01, 0.01, 12)
    X = (s[:, None] * np.array([0.0, 0.0, 1.0]) + [0.0, 0.95 * r, 0.0])[None]
    floor = Kinematic(Plane(np.zeros(3), np.array([0.0, 1.0, 0.0])),
                      Motion([0.0, 1.0], [[0, 0, 0], [0.01, 0, 0]],
                             np.radians([[0, 0, 0], [0, 10, 0]])))
    fab = Fabric(X=X, radius=r, friction=0.5, bodies=(floor,))
    model = FullModel(SELF, fab, Material(EA=10.0, EI=1e-6, rho=1e-3, damping=2.0))
    integ = BackwardEuler(model, 1e-2)
    x = model.rest_state()
    model.begin_step(x, 0.0)
    model.move_bodies(0.0, 1e-2)
    assert len(model.barrier.lagged[0]) > 0
    z = integ.saddle.createVec()
    z.getArray()[:] = 0.02 * np.random.default_rng(9).standard_normal(z.getLocalSize())
    fd, slope = step_potential_slopes(integ, x, z, seed=10)
    # measured 1.3e-11 (without the friction potential: 0.08)
    assert fd == pytest.approx(slope, rel=1e-8)
    model.destroy()


def test_the_carried_guess_turns_with_the_whole_problem():
    """Bodies, their keyframes (translations, rotation vectors, pivot) and
    the points all turned by Q: every point is carried by Q times as far."""
    Q = rotation_matrix(np.radians([20.0, -35.0, 50.0]))
    keys = dict(KEYS, translations=np.asarray(KEYS["translations"]),
                rotations=np.asarray(KEYS["rotations"]))
    turned = dict(keys, translations=keys["translations"] @ Q.T,
                  rotations=keys["rotations"] @ Q.T, pivot=Q @ keys["pivot"])
    a, b, c = np.zeros(3), np.array([0.0, 0.0, 0.05]), np.array([0.0, -0.03, 0.0])

    def bodies(R, k):
        return (Kinematic(Capsule(R @ a, R @ b, 0.01), Motion(**k)),
                Sphere(R @ c, 0.012))

    x = 0.02 * np.random.default_rng(6).standard_normal((30, 3))
    d = carried(bodies(np.eye(3), keys), x, 0.2, 0.35, 5e-3, 0.05)
    dq = carried(bodies(Q, turned), x @ Q.T, 0.2, 0.35, 5e-3, 0.05)
    assert np.abs(d).max() > 1e-3
    # measured 1.0e-17 m (the points move up to 9 mm)
    assert np.allclose(dq, d @ Q.T, rtol=0, atol=1e-16)
