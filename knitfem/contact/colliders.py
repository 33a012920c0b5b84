"""Rigid bodies the knit rests on: spheres, capsules and planes.

A body is its signed distance φ(x) (negative inside), with the outward
normal n = ∇φ and the curvature ∇²φ:

    sphere (c, R)     φ = |x − c| − R,          ∇²φ = (I − n nᵀ) / |x − c|,
    capsule (a, b, R) φ = |x − q(x)| − R,       q the closest point of the
                      segment ab; ∇²φ = (P − n nᵀ) / |x − q|, P = I − u uᵀ
                      (u = (b − a)/|b − a|) along the segment, I at its ends,
    plane (p, n)      φ = n·(x − p),            ∇²φ = 0.

The yarn surface (centreline ± r) keeps out of a body by a smooth barrier on
the distance of the surface, δ = φ(x) − r, at the yarn quadrature points:

    E_c = Σ_b Σ_{e,q} w_q |X'| f(δ_b,eq),   f(δ) = κ/3 (ĥ − δ)³ for δ < ĥ, else 0,

a C² penalty (f, f', f'' vanish at δ = ĥ) acting within a gap ĥ of the
surface. Its stiffness κ = 1e4 ρ g / ĥ² makes the barrier force per length
at contact, κ ĥ², ten thousand times the yarn's weight per length, so a
resting knit sinks into its gap by about 1 % of ĥ, and the energy at δ = 0,
κ ĥ³ / 3, stops a yarn falling from centimetres. Each body b has a barrier
of its own (as IPC sums its pairs): a point in the crease where two bodies
meet (an elbow bent) feels both, smoothly, where a barrier on the nearer
body's distance alone would turn its normal at once as the point crosses
the crease's bisector, and Newton would cycle across it. With
x_eq = Σ_a b_a(u_q) p_{e,a}, the forces and the tangent are exact (each
body's n and ∇²φ):

    ∂E_c/∂p_a = Σ_b Σ_q w_q |X'| f'(δ_b) b_a n,
    ∂²E_c/∂p_a∂p_b = Σ_b Σ_q w_q |X'| b_a b_b (f''(δ_b) n nᵀ + f'(δ_b) ∇²φ),

4 × 4 blocks of the yarn element itself, so they enter the yarn elements'
sparsity pattern: colliders never change it. Only the elements with a
quadrature point within the gap are evaluated.

Friction (Coulomb, μ = ``-knit_friction``) is lagged as in IPC (Li et al.,
SIGGRAPH 2020): at the start of a step the points within the gap of a body
keep, for that body, their normal force λ = w_q |X'| |f'(δ_b)|, tangent
projector T = I − n nᵀ and position x⁰, and the step minimises, with the
rest, the dissipative potential

    D = Σ_b Σ_q μ λ f₀(|u|),   u = T (x_q − x⁰),
    f₀(y) = y²/ε − y³/(3ε²) + ε/3 (y < ε), y (y ≥ ε),   ε = ε_v h,

so a point slides against a force μλ and sticks (moves by less than ε a
step) below it; ∂D/∂x_q = μλ f₁(y) û, ∂²D/∂x_q² = μλ (f₁' û ûᵀ + f₁/y
(T − û ûᵀ)), positive semi-definite, in the same 4 × 4 blocks.

Bodies that move (``motion.Kinematic``) are where they are at the step's
end time t₁ in E_c; friction measures the slip against the body, so a
lagged point's reference is the body point that was at x⁰ at the step's
start t₀, carried rigidly to t₁, and its normal turns with the body:

    u = T₁ (x_q − x¹),   x¹ = R₁ R₀ᵀ (x⁰ − s₀) + s₁,   n₁ = R₁ R₀ᵀ n,

(R, s) the body's pose x → R x + s at t₀ and t₁: the relative sliding
velocity times the step. A resting point on a body that moves is carried
along up to the force μλ.
"""

from dataclasses import dataclass

import numpy as np

from knitfem.contact.motion import moving
from knitfem.contact.segments import closest_parameters
from knitfem.yarn.kernels import compiled_module

__all__ = ["Sphere", "Capsule", "Plane", "Barrier", "parse_colliders", "KINDS"]

BODIES_VERSION = 1          # of knitfem/contact/_bodies.pyx, which this module calls

SLIP_SPEED = 5e-3
"""ε_v [m/s] of friction's smoothing ε = ε_v h (IPC's; at least 0.001 r), h
the step as first tried (its halvings keep its ε): a sticking point creeps
by less than ε a step. At ε = 0.01 r for a step of 0.01 s Newton cycled
between sticking and sliding on a moving arm (25 iterations a step without
converging, the 16 × 10 sleeve); at 0.1 r, this speed's, it converges in
about 10, as at 0.3 r and 1 r; a halved step whose ε halved too cycled
again."""


def quadrature_points(B, x, conn):
    """x_eq = Σ_a B_qa x_{conn[e, a]} of the elements of control points
    ``conn`` (m, 4), (m, nq, 3): one gather and one product (numpy's einsum
    takes six times as long)."""
    X = np.take(np.asarray(x), conn.T, axis=0).reshape(conn.shape[1], -1)
    return np.ascontiguousarray((B @ X).reshape(len(B), len(conn), 3).transpose(1, 0, 2))


def to_control_points(B, v):
    """Σ_q B_qa v_eqi of point values v (m, nq, 3): their share at each
    element's control points, (m, 4, 3) (``quadrature_points``' transpose)."""
    m, nq, _ = v.shape
    V = np.ascontiguousarray(v.transpose(1, 0, 2)).reshape(nq, -1)
    return np.ascontiguousarray((B.T @ V).reshape(B.shape[1], m, 3).transpose(1, 0, 2))


def _same(a, b):
    """Whether two element selections (index arrays, or None for all) are
    the same."""
    if a is None or b is None:
        return a is b
    return np.array_equal(a, b)


def _unit(d):
    """(d/|d|, |d|) row-wise."""
    r = np.linalg.norm(d, axis=-1)
    return d / np.maximum(r, 1e-300)[..., None], r


def signed_distance(body, x, compiled=None):
    """φ of ``body`` at the points x (n, 3): by the compiled loops of
    ``compiled`` (``_bodies.pyx``) where given and the body, as it is posed,
    is a sphere or a capsule, else by the body's own ``phi`` (the numpy
    reference)."""
    shape = getattr(body, "body", body)                 # a moving body's pose
    if compiled is None or not isinstance(shape, (Sphere, Capsule)):
        return body.phi(x)
    x = np.ascontiguousarray(x, dtype=float)
    out = np.empty(len(x))
    if isinstance(shape, Sphere):
        compiled.sphere_phi(x, np.asarray(shape.centre, dtype=float), shape.R, out)
    else:
        compiled.capsule_phi(x, np.asarray(shape.a, dtype=float),
                             np.asarray(shape.b, dtype=float), shape.R, out)
    return out


@dataclass
class Sphere:
    centre: np.ndarray
    R: float
    bounded = True                  # pictures keep it in view (a plane: not)

    def phi(self, x):
        """φ (n,) at points x (n, 3), without its derivatives."""
        return np.linalg.norm(x - self.centre, axis=-1) - self.R

    def distance(self, x):
        """(φ (n,), n (n, 3), ∇²φ (n, 3, 3)) at points x (n, 3)."""
        n, r = _unit(x - self.centre)
        H = (np.eye(3) - n[:, :, None] * n[:, None, :]) / np.maximum(r, 1e-300)[:, None, None]
        return r - self.R, n, H

    def lowest(self, p, q):
        """τ ∈ [0, 1] where the paths p + τ q (n, 3 each) come nearest the
        sphere: the closest approach to its centre."""
        qq = np.sum(q * q, axis=1)
        return np.clip(-np.sum((p - self.centre) * q, axis=1) / np.where(qq > 0, qq, 1.0), 0, 1)

    def describe(self):
        return f"sphere centre {np.round(self.centre, 6).tolist()} R {self.R:g} m"

    def geometry(self):
        return dict(type="sphere", centre=self.centre.tolist(), radius=self.R)

    def moved(self, R, s):
        """The sphere moved rigidly, x → R x + s."""
        return Sphere(R @ self.centre + s, self.R)

    def surface(self, size=None):
        """Triangles of the surface: (points (n, 3), triangles (m, 3))."""
        return _revolved(self.centre, np.array([0.0, 0.0, 1.0]),
                         np.linspace(np.pi, 0.0, 17), self.R, 0.0)


@dataclass
class Capsule:
    a: np.ndarray
    b: np.ndarray
    R: float
    bounded = True

    def _nearest(self, x):
        """(axis, |axis|², parameter t of the closest point of the segment)."""
        axis = self.b - self.a
        L2 = axis @ axis
        return axis, L2, np.clip((x - self.a) @ axis / L2, 0.0, 1.0)

    def phi(self, x):
        axis, _, t = self._nearest(x)
        return np.linalg.norm(x - (self.a + t[:, None] * axis), axis=-1) - self.R

    def distance(self, x):
        axis, L2, t = self._nearest(x)
        n, r = _unit(x - (self.a + t[:, None] * axis))
        u = axis / np.sqrt(L2)
        inside = (t > 0) & (t < 1)
        P = np.eye(3) - inside[:, None, None] * np.outer(u, u)
        H = (P - n[:, :, None] * n[:, None, :]) / np.maximum(r, 1e-300)[:, None, None]
        return r - self.R, n, H

    def lowest(self, p, q):
        """τ ∈ [0, 1] where the paths p + τ q come nearest the capsule: the
        closest points of each path and the axis (``segments``)."""
        a = np.broadcast_to(self.a, p.shape)
        return closest_parameters(p, p + q, a, a + (self.b - self.a))[0]

    def describe(self):
        return (f"capsule {np.round(self.a, 6).tolist()} to "
                f"{np.round(self.b, 6).tolist()} R {self.R:g} m")

    def geometry(self):
        return dict(type="capsule", p0=self.a.tolist(), p1=self.b.tolist(),
                    radius=self.R)

    def moved(self, R, s):
        return Capsule(R @ self.a + s, R @ self.b + s, self.R)

    def surface(self, size=None):
        """Triangles of the surface: (points (n, 3), triangles (m, 3))."""
        axis = self.b - self.a
        polar = np.concatenate([np.linspace(np.pi, np.pi / 2, 9),
                                np.linspace(np.pi / 2, 0.0, 9)])
        return _revolved(self.a, axis / np.linalg.norm(axis), polar, self.R,
                         np.linalg.norm(axis), split=9)


@dataclass
class Plane:
    point: np.ndarray
    normal: np.ndarray
    bounded = False

    def phi(self, x):
        return (x - self.point) @ (self.normal / np.linalg.norm(self.normal))

    def distance(self, x):
        n = self.normal / np.linalg.norm(self.normal)
        return (x - self.point) @ n, np.broadcast_to(n, x.shape), \
            np.zeros((len(x), 3, 3))

    def lowest(self, p, q):
        """τ ∈ [0, 1] where the paths p + τ q come nearest the plane (an end)."""
        return (q @ self.normal < 0).astype(float)

    def describe(self):
        return (f"plane through {np.round(self.point, 6).tolist()} normal "
                f"{np.round(self.normal, 6).tolist()}")

    def geometry(self):
        return dict(type="plane", point=self.point.tolist(),
                    normal=self.normal.tolist())

    def moved(self, R, s):
        return Plane(R @ self.point + s, R @ self.normal)

    def surface(self, size=1.0):
        """A square of side 2 ``size`` about ``point``: (points, triangles)."""
        n = self.normal / np.linalg.norm(self.normal)
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        u = np.linspace(-size, size, 9)
        a, b = np.meshgrid(u, u, indexing="ij")
        pts = self.point + a.reshape(-1, 1) * t1 + b.reshape(-1, 1) * t2
        return pts, _grid_triangles(9, 9)


def _grid_triangles(n1, n2, wrap=False):
    """Two triangles a cell of an n1 × n2 grid of points (row-major), the
    second index closing on itself with ``wrap``."""
    i, j = np.meshgrid(np.arange(n1 - 1), np.arange(n2 if wrap else n2 - 1),
                       indexing="ij")
    a = i * n2 + j
    b = i * n2 + (j + 1) % n2
    c, d = a + n2, b + n2
    return np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                           np.stack([a, d, c], -1).reshape(-1, 3)])


def _revolved(base, u, polar, R, length, split=None, around=32):
    """A surface of revolution about the axis base + s u: a ring of radius
    R sin θ at s = R cos θ for each polar angle θ of ``polar`` (a sphere),
    the rings from index ``split`` on moved by ``length`` along u (a
    capsule). Returns (points, triangles)."""
    t1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(u, t1)
    s = R * np.cos(polar) + (np.arange(len(polar)) >= (split or len(polar))) * length
    phi = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    ring = np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2
    pts = base + s[:, None, None] * u + (R * np.sin(polar))[:, None, None] * ring
    return pts.reshape(-1, 3), _grid_triangles(len(polar), around, wrap=True)


KINDS = {"sphere": (Sphere, 4), "capsule": (Capsule, 7), "plane": (Plane, 6)}


def parse_colliders(text):
    """Bodies from "sphere:cx,cy,cz,R", "capsule:x0,y0,z0,x1,y1,z1,R" and
    "plane:px,py,pz,nx,ny,nz", several separated by ";" (ValueError with
    what is wrong and how to write it)."""
    bodies = []
    for spec in filter(None, (s.strip() for s in text.split(";"))):
        kind, _, numbers = spec.partition(":")
        if kind not in KINDS:
            raise ValueError(f"collider {spec!r}: the kind is one of "
                             f"{', '.join(KINDS)} (e.g. sphere:0,0,0,0.01)")
        cls, count = KINDS[kind]
        try:
            v = np.array([float(s) for s in numbers.split(",")])
        except ValueError:
            v = np.zeros(0)
        if len(v) != count:
            raise ValueError(f"collider {spec!r}: {kind} takes {count} numbers")
        if kind == "sphere":
            body = Sphere(v[:3], v[3])
        elif kind == "capsule":
            body = Capsule(v[:3], v[3:6], v[6])
        else:
            body = Plane(v[:3], v[3:])
        if (kind != "plane" and v[-1] <= 0) or \
                (kind == "plane" and not np.linalg.norm(v[3:])) or \
                (kind == "capsule" and not np.linalg.norm(v[3:6] - v[:3])):
            raise ValueError(f"collider {spec!r}: needs a positive radius, a "
                             "nonzero normal or two distinct ends")
        bodies.append(body)
    return tuple(bodies)


class Barrier:
    """E_c of the yarn elements ``elements`` (``yarn.YarnElements``) against
    ``bodies``: energy, forces and tangent blocks (module docstring); gap ĥ =
    ``gap`` × r, κ = 1e4 ρ g / ĥ² (``weight`` = ρ g, N/m); ``compiled``: the
    bodies' φ by compiled loops (``signed_distance``), else by numpy."""

    def __init__(self, bodies, elements, radius, weight, gap=0.1, friction=0.0,
                 compiled=False):
        self.bodies, self.el, self.radius = bodies, elements, radius
        self.kernels = compiled_module("knitfem.contact._bodies", BODIES_VERSION) \
            if compiled else None
        self.gap = gap * radius
        self.kappa = 1e4 * max(weight, 1e-12) / self.gap**2
        self.mu, self.eps_slip = friction, 0.01 * radius
        self.lagged, self.step_h = None, None
        self.distance_at = None

    def phi(self, body, x):
        """φ of one of the bodies at the points x (``signed_distance``)."""
        return signed_distance(body, x, self.kernels)

    def at(self, t):
        """Pose the moving bodies at time t."""
        for body in self.bodies:
            if moving(body):
                body.at(t)

    @property
    def moves(self):
        """Whether any body moves."""
        return any(moving(body) for body in self.bodies)

    def lag(self, x, t=None):
        """Friction's quantities at the step start x, the bodies posed at
        time t (module docstring): (elements, μλ (e, q), T (e, q, 3, 3), x⁰
        (e, q, 3)) of the elements with a point within the gap; none without
        friction."""
        if t is not None:
            self.at(t)
        self.window, self.step_h = None, None
        if not self.mu:
            return
        e, _, n, _, d1, _, which = self._active(x)
        self.start = (which, n, self.el.points(x)[e],
                      [(b.R, b.s) if moving(b) else None for b in self.bodies])
        self.lagged = (e, -self.mu * d1, None, None)
        self._carry()

    def step_to(self, t0, t1):
        """The step runs from t0 to t1: the bodies posed at t1, the lagged
        references carried with them; friction's ε from the step's first
        (``set_step``)."""
        if self.step_h is None and t1 > t0:
            self.set_step(t1 - t0)
        if not self.moves:
            return
        self.window = (t0, t1)
        self.at(t1)
        if self.lagged is not None:
            self._carry()

    def set_step(self, h):
        """The step since the lag as first tried is h: ε = ε_v h."""
        self.step_h = h
        self.eps_slip = max(SLIP_SPEED * h, 1e-3 * self.radius)

    def _carry(self):
        """x¹ and T₁ of the lagged points, each carried by its body from its
        pose at the lag to its pose now."""
        which, n, x0, poses = self.start
        n, x1 = n.copy(), x0.copy()
        for b, pose in enumerate(poses):
            if pose is None:
                continue
            mine = which == b
            R0, s0 = pose
            R = self.bodies[b].R @ R0.T
            n[mine] = n[mine] @ R.T
            x1[mine] = (x0[mine] - s0) @ R.T + self.bodies[b].s
        T = np.eye(3) - n[..., :, None] * n[..., None, :]
        e, mul = self.lagged[:2]
        self.lagged = (e, mul, T, x1)

    def _slip(self, x):
        """(elements, μλ, T, u, y = |u|) of the lagged points at x."""
        e, mul, T, x0 = self.lagged
        xq = quadrature_points(self.el.B, x, self.el.conn[e])
        u = np.einsum("eqij,eqj->eqi", T, xq - x0)
        return e, mul, T, u, np.linalg.norm(u, axis=-1)

    def friction_potential(self, x):
        """D = Σ μλ f₀(|u|) (local elements)."""
        if self.lagged is None:
            return 0.0
        _, mul, _, _, y = self._slip(x)
        eps = self.eps_slip
        f0 = np.where(y < eps, y * y / eps - y**3 / (3 * eps * eps) + eps / 3, y)
        return float(np.sum(mul * f0))

    def _friction_terms(self, x):
        """(elements, μλ f₁ û (e, q, 3), μλ ∂²f₀ (e, q, 3, 3))."""
        e, mul, T, u, y = self._slip(x)
        eps = self.eps_slip
        slow = y < eps
        f1_y = np.where(slow, 2 / eps - y / (eps * eps), 1 / np.maximum(y, 1e-300))
        df1 = np.where(slow, 2 / eps - 2 * y / (eps * eps), 0.0)
        uhat = u / np.maximum(y, 1e-300)[..., None]
        uu = uhat[..., :, None] * uhat[..., None, :]
        hess = mul[..., None, None] * (df1[..., None, None] * uu
                                       + f1_y[..., None, None] * (T - uu))
        return e, (mul * f1_y)[..., None] * u, hess

    def _points(self, x, elements=None):
        """x_eq of the elements ``elements`` (all: None), (m, nq, 3)."""
        if elements is None:
            return self.el.points(x)
        return quadrature_points(self.el.B, x, self.el.conn[elements])

    def _distances(self, x, elements=None):
        """(δ_b = φ_b − r of every body b (nb, m, nq), δ = min_b δ_b (m, nq),
        the nearest body (m, nq), the points x_eq (m, nq, 3)) of the
        elements ``elements`` (all: None), computed once a state: the
        forces, the tangent and the step filter at the same x, the bodies
        where they were (the moving ones' times), share them. An element
        left out must be known to lie beyond the gap."""
        x = np.asarray(x)
        poses = tuple(body.time for body in self.bodies if moving(body))
        kept = self.distance_at
        if (kept is None or kept[1] != poses or not np.array_equal(kept[0], x)
                or not _same(kept[2], elements)):
            pts = self._points(x, elements)
            each = np.stack([self.phi(body, pts.reshape(-1, 3)) for body in self.bodies])
            each = each.reshape((len(self.bodies),) + pts.shape[:2]) - self.radius
            nearest = np.argmin(each, axis=0)
            kept = self.distance_at = (
                x.copy(), poses, None if elements is None else elements.copy(),
                (each, np.take_along_axis(each, nearest[None], 0)[0], nearest, pts))
        return kept[3]

    def surface_distance(self, x):
        """δ = min over bodies of φ − r at every quadrature point, which body
        is the nearest, and the points: (δ (ne, nq), body index (ne, nq),
        x_eq (ne, nq, 3))."""
        return self._distances(x)[1:]

    def _active(self, x, elements=None):
        """The elements with a point within the gap of a body (among
        ``elements``; all: None), a row for each such element and body, and
        f', f'' (weighted by w_q |X'|) there: (elements, δ_b, n_b, ∇²φ_b, w f',
        w f'', body b), an element within the gap of two bodies listed for
        each."""
        each, _, _, pts = self._distances(x, elements)
        parts = []
        for b, body in enumerate(self.bodies):
            m = np.flatnonzero((each[b] < self.gap).any(axis=1))
            _, n, H = body.distance(pts[m].reshape(-1, 3))
            shape = (len(m),) + pts.shape[1:]
            s = np.maximum(self.gap - each[b, m], 0.0)
            e = m if elements is None else elements[m]
            W = self.el.W[e]
            parts.append((e, each[b, m], n.reshape(shape), H.reshape(shape + (3,)),
                          -W * self.kappa * s**2, 2 * W * self.kappa * s,
                          np.full(s.shape, b)))
        return tuple(np.concatenate(p) for p in zip(*parts))

    def energy(self, x, elements=None):
        """E_c (local elements; those of ``elements``, the others known to lie
        beyond the gap: ``_distances``)."""
        s = np.maximum(self.gap - self._distances(x, elements)[0], 0.0)
        W = self.el.W if elements is None else self.el.W[elements]
        return float(np.sum(W * self.kappa / 3 * s**3))

    def add_gradient(self, x, out, scale=1.0, elements=None):
        """out (ncp, 3) += scale ∂(E_c + D)/∂ε (D: friction, when lagged);
        the barrier on ``elements`` (``energy``)."""
        e, _, n, _, d1, _, _ = self._active(x, elements)
        g = to_control_points(self.el.B, d1[..., None] * n)
        np.add.at(out, self.el.conn[e], scale * g)
        if self.lagged is not None:
            e, gq, _ = self._friction_terms(x)
            np.add.at(out, self.el.conn[e], scale * to_control_points(self.el.B, gq))

    def add_hessian(self, x, slot, values):
        """values[slot[e]] += ∂²(E_c + D)/∂p∂p of the elements within the gap
        (``element_hessian``); ``slot`` the yarn elements' (ne, 12, 12)
        value slots."""
        e, blocks = self.element_hessian(x)
        where = slot[e].ravel()
        mine = where >= 0                              # rows of this rank
        values += np.bincount(where[mine], blocks.ravel()[mine], minlength=len(values))

    def quadrature_hessian(self, x, elements=None):
        """∂²(E_c + D)/∂x_q² at the quadrature points,

            H_q = w f''(δ) n nᵀ + w f'(δ) ∇²φ          (barrier),
            H_q = μλ (f₁' û ûᵀ + f₁/y (T − û ûᵀ))      (friction, lagged),

        of the elements with a point within the gap (among ``elements``:
        ``energy``) and of the lagged ones, each element once, its terms
        summed: (elements (m,), H (m, nq, 3, 3))."""
        e, _, n, H, d1, d2, _ = self._active(x, elements)
        parts = [(e, d2[..., None, None] * n[..., :, None] * n[..., None, :]
                  + d1[..., None, None] * H)]
        if self.lagged is not None:
            parts.append(self._friction_terms(x)[::2])
        e, Hq = (np.concatenate(p) for p in zip(*parts))
        if not len(e):
            return e, Hq
        order = np.argsort(e, kind="stable")
        e = e[order]
        first = np.flatnonzero(np.r_[True, e[1:] != e[:-1]])
        return e[first], np.add.reduceat(Hq[order], first, axis=0)

    def element_hessian(self, x):
        """The 12 × 12 blocks Σ_q b_a b_b H_q of ∂²(E_c + D)/∂p∂p
        (``quadrature_hessian``): (elements (m,), blocks (m, 12, 12))."""
        e, Hq = self.quadrature_hessian(x)
        B = self.el.B
        BB = (B[:, :, None] * B[:, None, :]).reshape(len(B), 16)     # b_a b_b at q
        blocks = (BB.T @ Hq.reshape(len(e), len(B), 9)).reshape(-1, 4, 4, 3, 3)
        return e, blocks.transpose(0, 1, 3, 2, 4).reshape(-1, 12, 12)

    def swept_depth(self, x0, x1, floor=None, resolution=0.5):
        """The deepest δ along the straight paths of the quadrature points
        from x0 to x1 that can go below ``floor`` (−r by default), the
        moving bodies along their own paths over the step (``step_to``): a
        step that carried a yarn point through a body shows a depth there
        even when it ends outside. Local; +inf where no path can reach the
        floor.

        Body by body: a path is looked at only if its end's δ_b less its
        length and twice how far the body carries its ends is below the
        floor (φ is 1-Lipschitz: the others stay above it), and it is
        sampled every ``resolution`` × r at least of its motion relative to
        the body, |g⁻¹(x1) − x0| (g the body's motion over the step): a
        sleeve carried by a turning forearm barely moves on it, however far
        it swings."""
        floor = -self.radius if floor is None else floor
        p0 = self.el.points(x0).reshape(-1, 3)
        p1 = self.el.points(x1).reshape(-1, 3)
        each = self._distances(x1)[0].reshape(len(self.bodies), -1)
        window = getattr(self, "window", None)
        length = np.linalg.norm(p1 - p0, axis=1)
        deepest = np.inf
        for body, delta in zip(self.bodies, each):
            rel, reach = p1 - p0, length
            if window is not None and moving(body):
                R, s = body.motion.between(*window)
                rel = (p1 - s) @ R - p0                            # g⁻¹(x1) − x0
                reach = length + 2 * np.maximum(
                    np.linalg.norm(p0 @ R.T + s - p0, axis=1),
                    np.linalg.norm(p1 @ R.T + s - p1, axis=1))
            near = np.flatnonzero(delta - reach < floor)
            if not len(near):
                continue
            a, d = p0[near], p1[near] - p0[near]
            far = np.linalg.norm(rel[near], axis=1).max()
            m = int(min(64, max(1, np.ceil(far / (resolution * self.radius)))))
            for tau in np.arange(1, m + 1) / m:
                if window is not None and moving(body):
                    body.at(window[0] + tau * (window[1] - window[0]))
                deepest = min(deepest, float(self.phi(body, a + tau * d).min()) - self.radius)
        return deepest

    def carried(self, t0, t1, x):
        """How far each moving body carries its point at x (n, 3) at t0 by
        t1, |R x + s − x| (``Motion.between``), the most over the bodies
        (n,)."""
        far = np.zeros(len(x))
        for body in filter(moving, self.bodies):
            R, s = body.motion.between(t0, t1)
            far = np.maximum(far, np.linalg.norm(x @ R.T + s - x, axis=1))
        return far

    def step_limit(self, x, dx, iterations=30, elements=None):
        """The largest τ ≤ 1 such that the update τ dx of the yarn points x
        takes no quadrature point below δ = min(δ(x), 0) − ĥ (local): a
        Newton update stops about where a yarn surface meets a body, in
        the barrier whose stiffness the next iteration knows, rather than
        far inside it (a step filter, as in IPC).

        Each body's φ is convex along a straight path (a sphere's, a
        capsule's and a plane's are distances to convex sets), so a path
        that dips below the bound does so once, before its lowest point τ*
        (``lowest``: also for a path that passes through a body and ends
        beyond it), and its first crossing is found by bisection on
        [0, τ*]. Only paths that can reach the bound are looked at: φ is
        1-Lipschitz, so φ(p + τq) ≥ φ(p) − |q|. Only the paths of
        ``elements`` (all: None) are looked at: the others must be known not
        to reach the gap."""
        each, start, _, p = self._distances(x, elements)
        p, q = p.reshape(-1, 3), self._points(dx, elements).reshape(-1, 3)
        bound = np.minimum(start.ravel(), 0.0) - self.gap + self.radius   # on φ
        reach = np.linalg.norm(q, axis=1)
        tau = 1.0
        for body, delta in zip(self.bodies, each):
            near = np.flatnonzero(delta.ravel() + self.radius - reach < bound)
            if not len(near):
                continue
            p_, q_, b_ = p[near], q[near], bound[near]
            hi = body.lowest(p_, q_)
            cross = self.phi(body, p_ + hi[:, None] * q_) < b_
            if not cross.any():
                continue
            p_, q_, b_, hi = p_[cross], q_[cross], b_[cross], hi[cross]
            lo = np.zeros(len(b_))
            for _ in range(iterations):
                mid = 0.5 * (lo + hi)
                below = self.phi(body, p_ + mid[:, None] * q_) < b_
                hi = np.where(below, mid, hi)
                lo = np.where(below, lo, mid)
            tau = min(tau, float(lo.min()))
        return tau

    def min_distance(self, x):
        """Smallest δ (local; +inf without elements)."""
        delta = self.surface_distance(x)[0]
        return float(delta.min()) if delta.size else np.inf
