"""Bodies that move: a prescribed rigid motion of a body, from keyframes.

A keyframe k gives, at time t_k, a translation c_k and a rotation vector
θ_k (axis × angle) about a pivot p: a body point x of the body at rest is at

    x(t) = R(θ(t)) (x − p) + p + c(t),   R(θ) = exp([θ]×) (Rodrigues).

Between keyframes c and θ follow cubic Hermite curves in t,

    c(t) = h₀₀ c_k + h₁₀ Δ ċ_k + h₀₁ c_{k+1} + h₁₁ Δ ċ_{k+1},   Δ = t_{k+1} − t_k,

(h the Hermite basis of s = (t − t_k)/Δ), with slopes ċ_k the centred
differences (c_{k+1} − c_{k−1})/(t_{k+1} − t_{k−1}) at inner keyframes and the
one-sided ones at the first and last, so the motion is C¹, passes through
every keyframe exactly, and two keyframes make a constant velocity; with
``ease`` the first and last slopes are zero (a start and a stop from rest:
smoothstep between two keyframes). Interpolating the rotation vector turns
a body about a fixed axis by the interpolated angle exactly; about moving
axes it is a smooth rotation through the keyframes' own. Before the first
keyframe the body stays at it, after the last at the last.

A ``Kinematic`` body is a body of ``colliders`` (its rest pose) with a
``Motion``; ``at(t)`` poses it, and it answers every body question (φ, n,
∇²φ, its surface) as the body where it is then.

The file of ``-knit_collider_motion`` (JSON) keyframes bodies by their index
among the scene's and ``-knit_collider``'s bodies::

    {"bodies": [{"body": 0, "pivot": [0, 0, 0], "ease": false,
                 "keyframes": [{"t": 0, "translation": [0, 0, 0]},
                               {"t": 1, "translation": [0, 0.01, 0],
                                "rotation": [0, 0, 30]}]}]}

lengths in metres, times in seconds, rotation vectors in degrees (a turn of
30° about z above); a missing translation or rotation is zero.
"""

import json
from dataclasses import dataclass

import numpy as np

__all__ = ["Motion", "Kinematic", "rotation_matrix", "load_motions", "moving", "carried"]


def rotation_matrix(theta):
    """R = exp([θ]×) of a rotation vector θ (3,) in radians (Rodrigues)."""
    theta = np.asarray(theta, dtype=float)
    angle = np.linalg.norm(theta)
    if angle < 1e-300:
        return np.eye(3)
    k = theta / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _slopes(t, y, ease):
    """Hermite slopes (k, d) at the keyframes (module docstring)."""
    if len(t) < 2:
        return np.zeros_like(y)
    d = np.empty_like(y)
    d[1:-1] = (y[2:] - y[:-2]) / (t[2:] - t[:-2])[:, None]
    d[0] = (y[1] - y[0]) / (t[1] - t[0])
    d[-1] = (y[-1] - y[-2]) / (t[-1] - t[-2])
    if ease:
        d[0] = d[-1] = 0.0
    return d


class Motion:
    """A rigid motion through keyframes (module docstring): ``times`` (k,)
    increasing, ``translations`` and ``rotations`` (k, 3) (rotation vectors
    in radians), about ``pivot`` (3,)."""

    def __init__(self, times, translations=None, rotations=None, pivot=(0, 0, 0),
                 ease=False):
        self.t = np.asarray(times, dtype=float)
        k = len(self.t)
        if k == 0 or np.any(np.diff(self.t) <= 0):
            raise ValueError("keyframes need increasing times")
        zero = np.zeros((k, 3))
        self.c = zero if translations is None else np.asarray(translations, float)
        self.theta = zero if rotations is None else np.asarray(rotations, float)
        if self.c.shape != (k, 3) or self.theta.shape != (k, 3):
            raise ValueError("a keyframe's translation and rotation are 3 numbers")
        self.pivot, self.ease = np.asarray(pivot, dtype=float), ease
        self.dc = _slopes(self.t, self.c, ease)
        self.dtheta = _slopes(self.t, self.theta, ease)

    def _hermite(self, t, y, dy):
        """The Hermite curve through (t_k, y_k) with slopes dy at time t."""
        if t <= self.t[0] or len(self.t) == 1:
            return y[0]
        if t >= self.t[-1]:
            return y[-1]
        k = int(np.searchsorted(self.t, t, side="right")) - 1
        h = self.t[k + 1] - self.t[k]
        s = (t - self.t[k]) / h
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        return h00 * y[k] + h10 * h * dy[k] + h01 * y[k + 1] + h11 * h * dy[k + 1]

    def pose(self, t):
        """(R, s) with x(t) = R x + s for a body point x at rest."""
        R = rotation_matrix(self._hermite(t, self.theta, self.dtheta))
        c = self._hermite(t, self.c, self.dc)
        return R, self.pivot + c - R @ self.pivot

    def between(self, t0, t1):
        """(R, s) with x(t1) = R x(t0) + s for a body point: R₁ R₀ᵀ and
        s₁ − R₁ R₀ᵀ s₀."""
        (R0, s0), (R1, s1) = self.pose(t0), self.pose(t1)
        R = R1 @ R0.T
        return R, s1 - R @ s0


@dataclass
class Kinematic:
    """The body ``rest`` moved by ``motion``; ``at(t)`` poses it."""

    rest: object
    motion: Motion

    def __post_init__(self):
        self.bounded = self.rest.bounded
        self.at(0.0)

    def at(self, t):
        """Pose the body at time t (the rigid map R x + s of ``motion``)."""
        self.time = float(t)
        self.R, self.s = self.motion.pose(self.time)
        self.body = self.rest.moved(self.R, self.s)
        return self

    def body_at(self, t):
        """The body as it is at time t, leaving its pose as it is."""
        return self.rest.moved(*self.motion.pose(float(t)))

    def phi(self, x):
        return self.body.phi(x)

    def distance(self, x):
        return self.body.distance(x)

    def lowest(self, p, q):
        return self.body.lowest(p, q)

    def surface(self, size=None):
        return self.body.surface(size)

    def describe(self):
        return f"{self.body.describe()} (moving)"

    def geometry(self):
        return self.body.geometry()

    def moved(self, R, s):
        return self.body.moved(R, s)


def moving(body):
    """Whether ``body`` moves (a ``Kinematic`` one)."""
    return isinstance(body, Kinematic)


def carried(bodies, x, t0, t1, length, reach, least=float):
    """How far the points x (n, 3) go from t0 to t1 with the bodies near
    them: each point is carried by every body b as a point of it would be,
    x¹_b = R₁ R₀ᵀ (x − s₀) + s₁ ((R, s) b's pose at t0 and t1; a body at rest
    does not carry), weighted by a soft minimum of the distances φ_b(x) at
    t0, all of them in full when one comes within ``reach`` of a body and
    not at all when none comes within 1.5 times it,

        d(x) = g Σ_b w_b (x¹_b − x),   w_b = exp(−φ_b / ℓ) / Σ_c exp(−φ_c / ℓ),
        g = 1 − S((min_x,b φ_b − R) / (R/2)),   S(s) = 3s² − 2s³ on [0, 1],

    ℓ = ``length``, R = ``reach``, the minimum over the points taken by
    ``least`` (over the ranks: a garment is one), so a garment round a
    moving limb goes rigidly with it, blends smoothly into the bodies at
    rest beside it, and a knit away from every body stays (a guess for an
    implicit step: Newton from there finds the yarns still in contact and
    sticking where they were; a knit carried in part would start its step
    stretched). Returns d (n, 3), or None when no body moves."""
    if not any(moving(body) for body in bodies):
        return None
    x = np.asarray(x, dtype=float)
    phi = np.empty((len(bodies), len(x)))
    moves = []
    for b, body in enumerate(bodies):
        if not moving(body):
            phi[b] = body.phi(x)
            continue
        phi[b] = body.body_at(t0).phi(x)
        R, s = body.motion.between(t0, t1)
        moves.append((b, x @ R.T + s - x))
    near = phi.min(axis=0)
    w = np.exp(-(phi - near) / length)
    nearest = least(float(near.min(initial=np.inf)))
    s = min(max((nearest - reach) / (0.5 * reach), 0.0), 1.0)
    w *= (1.0 - s * s * (3.0 - 2.0 * s)) / w.sum(axis=0)
    return sum(w[b, :, None] * move for b, move in moves)


def load_motions(path, bodies):
    """``bodies`` with those the JSON file ``path`` keyframes made
    ``Kinematic`` (format: module docstring); ValueError saying what is
    wrong."""
    try:
        with open(path) as f:
            spec = json.load(f)
    except json.JSONDecodeError as err:
        raise ValueError(f"not JSON ({err})") from None
    bodies = list(bodies)
    try:
        tracks = spec["bodies"]
        for track in tracks:
            k = int(track["body"])
            if not 0 <= k < len(bodies):
                raise ValueError(f"body {k}: there are {len(bodies)} bodies "
                                 "(the scene's, then -knit_collider's)")
            keys = track["keyframes"]
            motion = Motion([key["t"] for key in keys],
                            [key.get("translation", (0, 0, 0)) for key in keys],
                            [np.radians(key.get("rotation", (0, 0, 0)))
                             for key in keys],
                            track.get("pivot", (0, 0, 0)), bool(track.get("ease")))
            bodies[k] = Kinematic(getattr(bodies[k], "rest", bodies[k]), motion)
    except (KeyError, TypeError) as err:
        raise ValueError(f"expected {{\"bodies\": [{{\"body\": index, "
                         f"\"keyframes\": [{{\"t\": ..., \"translation\": [...], "
                         f"\"rotation\": [...]}}, ...]}}]}} ({err!r} missing or "
                         f"malformed)") from None
    return tuple(bodies)
