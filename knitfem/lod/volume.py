"""Bounding volume V and the stitches-fitting map Γ̃ (paper, section 3).

V is the linear interpolation, through the thickness, of two bicubic uniform
B-spline surfaces S₁ (k3 = 0) and S₂ (k3 = 1) built on the same n₁ × n₂
control points (n₁ along x, the courses; n₂ along y, the wales). In patch
j = (j1, j2), at local parameters ω = (ω₁, ω₂, ω₃) ∈ [0, 1]³,

    P(j, ω) = (1 − ω₃) Σ_{a,b} b_a(ω₁) b_b(ω₂) q_{j1+a, j2+b, 0}
            +      ω₃  Σ_{a,b} b_a(ω₁) b_b(ω₂) q_{j1+a, j2+b, 1},

with b_a the uniform cubic blending functions of `bspline.basis`. We use the
global parameters s₁ = j1 + ω₁ ∈ [0, n₁ − 3], s₂ = j2 + ω₂ ∈ [0, n₂ − 3] and
w₃ = ω₃ ∈ [0, 1]; the patch is floor(s), clipped.

Numbering. Control point (k1, k2, k3) is volume DOF

    k = k1 + n₁ (k2 + n₂ k3),

the column of Γ̃. The net is stored as an array (2, n₂, n₁, 3) indexed
[k3, k2, k1, :], so that its C-order flattening ``flat`` (2 n₁ n₂, 3) is in
that numbering.

A volume periodic in s₁ (``periodic=True``) closes on itself around a tube
knitted in the round: its n₁ control points around make n₁ patches, patch
j1 blends k1 = (j1 + a) mod n₁, s₁ ∈ [0, n₁) is read modulo n₁
(``bspline``'s closed curves); S₁ is the inner surface and S₂ the outer
(``BoundingVolume.tube``).

Stitches fitting. A yarn control point keeps constant parameters (s₁, s₂, w₃)
in V, so ε = Γ̃ q is linear in the volume's control points q: the row of Γ̃
of a point holds the 4 · 4 · 2 = 32 weights (1 − ω₃) b_a(ω₁) b_b(ω₂) and
ω₃ b_a(ω₁) b_b(ω₂) at columns k(j1 + a, j2 + b, k3). The weights are ≥ 0 and
sum to 1, so Γ̃ reproduces affine maps exactly.
"""

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from knitfem.yarn import bspline

__all__ = ["BoundingVolume", "DEFAULT_AMOUNTS", "MODES"]

MODES = ("flexion", "traction", "shear", "torsion")

# Our choice: the paper's figures 2-8 show these deformations but give no
# numbers. Angles in degrees, traction as a stretch ratio.
DEFAULT_AMOUNTS = {"flexion": 90.0, "traction": 1.2, "shear": 30.0, "torsion": 90.0}

# meshio's readers by name, called directly (meshio.read() calls sys.exit
# on a bad file); meshio is imported when a volume file is read or written
_READERS = {".vtu": "vtu", ".xdmf": "xdmf", ".vtk": "vtk"}
_LATTICE = "lattice_index"
_PERIODIC = "periodic"


def _spaced(lo, hi, n):
    """n control points of a linear open spline over [lo, hi]: equally spaced,
    x_i = lo + (i − 1)(hi − lo)/(n − 3), so its value at s = 0 is lo and at
    s = n − 3 is hi."""
    return lo + (np.arange(n) - 1) * (hi - lo) / (n - 3)


class BoundingVolume:
    """Two bicubic B-spline surfaces joined linearly through the thickness.

    Parameters
    ----------
    net : array_like, shape (2, n2, n1, 3)
        Control points q[k3, k2, k1]; n1, n2 ≥ 4 (one patch at least). Copied.
    periodic : bool
        Closed around s₁ (a tube), n1 patches around.

    Attributes
    ----------
    net : ndarray, shape (2, n2, n1, 3)
    flat : ndarray, shape (2 n1 n2, 3)
        A view of ``net``: row k = k1 + n1 (k2 + n2 k3) is control point k.
    n1, n2 : int
        Control points along x (s₁) and along y (s₂).
    periodic : bool
    """

    def __init__(self, net, periodic=False):
        net = np.array(net, dtype=float)
        if net.ndim != 4 or net.shape[0] != 2 or net.shape[3] != 3:
            raise ValueError(
                f"control net must have shape (2, n2, n1, 3), got {net.shape}")
        n2, n1 = net.shape[1:3]
        if n1 < 4 or n2 < 4:
            raise ValueError(
                f"control net is {n1}×{n2}×2; bicubic patches need n1, n2 >= 4")
        if not np.all(np.isfinite(net)):
            raise ValueError("control net has non-finite coordinates")
        self.net, self.n1, self.n2 = net, n1, n2
        self.periodic = bool(periodic)
        self.flat = net.reshape(-1, 3)

    def like(self, q):
        """A volume of this one's kind (size, periodicity) on control points q."""
        return BoundingVolume.from_flat(q, self.n1, self.n2, self.periodic)

    @classmethod
    def from_flat(cls, q, n1, n2, periodic=False):
        """Volume from control points q (2 n1 n2, 3) in the DOF numbering."""
        q = np.asarray(q, dtype=float)
        if q.shape != (2 * n1 * n2, 3):
            raise ValueError(
                f"control points have shape {q.shape}, expected "
                f"({2 * n1 * n2}, 3) for a {n1}×{n2}×2 net")
        return cls(q.reshape(2, n2, n1, 3), periodic)

    @classmethod
    def around(cls, points, n1=5, n2=5, margin=0.0, frame=None):
        """Box volume enclosing ``points`` (N, 3), with an exactly affine map.

        The box is aligned with the columns of the rotation ``frame``
        (default: the world axes); below, x, y, z are coordinates along them.

        The box is [x_min − m, x_max + m] × [y_min − m, y_max + m] ×
        [z_min − m, z_max + m]; S₁ is its bottom face, S₂ its top face. Along
        x the control points are equally spaced,

            x_i = x_lo + (i − 1)(x_hi − x_lo)/(n1 − 3),   i = 0 … n1 − 1,

        (likewise y), so the spline is linear and s₁ ∈ [0, n1 − 3] maps onto
        [x_lo, x_hi]: the value at s = 0 is (x_0 + 4x_1 + x_2)/6 = x_1 = x_lo.
        """
        R = np.eye(3) if frame is None else np.asarray(frame, dtype=float)
        pts = np.asarray(points, dtype=float).reshape(-1, 3) @ R
        if len(pts) == 0 or margin < 0:
            raise ValueError("around() needs at least one point and margin >= 0")
        lo, hi = pts.min(0) - margin, pts.max(0) + margin
        flat = [ax for ax, d in zip("xyz", hi - lo) if not d > 0]
        if flat:
            raise ValueError(
                f"points span no volume along {', '.join(flat)}; use margin > 0")
        x, y = _spaced(lo[0], hi[0], n1), _spaced(lo[1], hi[1], n2)
        z = np.array([lo[2], hi[2]])
        Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
        return cls(np.stack([X, Y, Z], axis=-1) @ R.T)

    @classmethod
    def tube(cls, points, n1=8, n2=5, margin=0.0, frame=None):
        """Coaxial volume enclosing ``points`` (N, 3) of a tube, periodic
        around it: S₁ a cylinder inside them, S₂ one outside.

        In the coordinates of ``frame`` (as in `around`) the axis is parallel
        to y through the points' mean (x, z); with ρ the distance from it,
        the cylinders have radii ρ_min − m and ρ_max + m and span [y_min − m,
        y_max + m], equally spaced along y as in `around`. Around, control
        point k1 sits at the angle φ = 2π k1/n1 and the radius divided by
        σ = (4 + 2 cos(2π/n1))/6 (``bspline.junction_symbol``), so that each
        surface passes through its circle at every junction s₁ ∈ ℤ.
        """
        R = np.eye(3) if frame is None else np.asarray(frame, dtype=float)
        pts = np.asarray(points, dtype=float).reshape(-1, 3) @ R
        if len(pts) == 0 or margin < 0 or n1 < 4 or n2 < 4:
            raise ValueError("tube() needs points, margin >= 0 and n1, n2 >= 4")
        c = pts[:, [0, 2]].mean(axis=0)
        rho = np.linalg.norm(pts[:, [0, 2]] - c, axis=1)
        radii = np.array([rho.min() - margin, rho.max() + margin])
        if not radii[0] > 0:
            raise ValueError("the points reach the tube's axis: not a tube")
        lo, hi = pts[:, 1].min() - margin, pts[:, 1].max() + margin
        y = _spaced(lo, hi, n2)
        phi = 2 * np.pi * np.arange(n1) / n1
        r = radii / bspline.junction_symbol(2 * np.pi / n1)
        net = np.empty((2, n2, n1, 3))
        net[..., 0] = c[0] + r[:, None, None] * np.sin(phi)
        net[..., 1] = y[:, None]
        net[..., 2] = c[1] + r[:, None, None] * np.cos(phi)
        return cls(net @ R.T, periodic=True)

    @property
    def size(self):
        """Number of control points n = 2 n1 n2 (columns of Γ̃)."""
        return 2 * self.n1 * self.n2

    @property
    def domain(self):
        """Upper bounds (n1 − 3, n2 − 3, 1) of (s₁, s₂, w₃), n1 − 3 → n1 if
        periodic; lower bounds 0."""
        return np.array([bspline.segments(self.n1, self.periodic), self.n2 - 3, 1.0])

    def index(self, k1, k2, k3):
        """DOF number k = k1 + n1 (k2 + n2 k3) of control point (k1, k2, k3)."""
        return np.asarray(k1) + self.n1 * (np.asarray(k2) + self.n2 * np.asarray(k3))

    def __repr__(self):
        return (f"BoundingVolume({self.n1}×{self.n2}×2 control points"
                f"{', periodic around' if self.periodic else ''})")

    # -- evaluation -------------------------------------------------------

    def _rows(self, s1, s2, w3, nu=(0, 0, 0)):
        """Columns and weights of d^nu P / d(s₁, s₂, w₃)^nu, each (..., 32).

        Weights (..., k3, b, a) = W_k3(w₃) b_b(ω₂) b_a(ω₁), W = (1 − w₃, w₃),
        at columns (j1 + a) + n1 ((j2 + b) + n2 k3), j1 + a modulo n1 if
        periodic.
        """
        s1, s2, w3 = np.broadcast_arrays(*(np.asarray(v, dtype=float)
                                           for v in (s1, s2, w3)))
        j1, u1 = bspline.locate(s1, bspline.segments(self.n1, self.periodic),
                                self.periodic)
        j2, u2 = bspline.locate(s2, self.n2 - 3)
        B1 = bspline.basis(u1, nu[0])
        B2 = bspline.basis(u2, nu[1])
        if nu[2] == 0:
            W = np.stack([1.0 - w3, w3], axis=-1)
        else:
            W = np.stack([-np.ones_like(w3), np.ones_like(w3)], axis=-1)
        vals = W[..., :, None, None] * B2[..., None, :, None] * B1[..., None, None, :]
        a = np.arange(4)
        k1 = bspline.span(j1, self.n1, self.periodic)[..., None, None, :]
        cols = (k1 + self.n1 * (j2[..., None, None, None] + a[:, None]
                             + self.n2 * np.arange(2)[:, None, None]))
        shape = s1.shape + (32,)
        return cols.reshape(shape), vals.reshape(shape)

    def weights(self, s1, s2, w3, nu=(0, 0, 0)):
        """Rows of Γ̃: ε = Σ_c vals[c] q[cols[c]] for parameters (s₁, s₂, w₃).

            Γ̃_{i,k(j1+a, j2+b, 0)} = (1 − ω₃) b_a(ω₁) b_b(ω₂),
            Γ̃_{i,k(j1+a, j2+b, 1)} =      ω₃  b_a(ω₁) b_b(ω₂),

        or, with ``nu``, those of the derivative ∂^nu P/∂(s₁, s₂, w₃)^nu.

        Parameters
        ----------
        s1, s2, w3 : array_like, broadcastable to shape (...)
        nu : (int, int, int)

        Returns
        -------
        cols : ndarray of int, shape (..., 32)
            Volume DOF numbers k (distinct within a row).
        vals : ndarray, shape (..., 32)
            Non-negative weights summing to 1 (for nu = 0).
        """
        return self._rows(s1, s2, w3, nu)

    def points(self, s1, s2, w3):
        """P(s₁, s₂, w₃), shape (..., 3), for broadcastable parameters."""
        cols, vals = self._rows(s1, s2, w3)
        return np.einsum("...c,...ci->...i", vals, self.flat[cols])

    def jacobian(self, s1, s2, w3):
        """J[..., i, c] = ∂P_i/∂(s₁, s₂, w₃)_c, shape (..., 3, 3)."""
        cols = []
        for nu in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
            k, v = self._rows(s1, s2, w3, nu)
            cols.append(np.einsum("...c,...ci->...i", v, self.flat[k]))
        return np.stack(cols, axis=-1)

    # -- inversion --------------------------------------------------------

    def _initial_guess(self, x, per_patch=3):
        """Nearest point of a coarse parameter grid, for each x (N, 3) (a k-d
        tree of the grid's points)."""
        n = bspline.segments(self.n1, self.periodic)
        g1 = np.linspace(0, n, per_patch * n + 1)[:-1 if self.periodic else None]
        g2 = np.linspace(0, self.n2 - 3, per_patch * (self.n2 - 3) + 1)
        g3 = np.linspace(0, 1, 3)
        G = np.stack(np.meshgrid(g1, g2, g3, indexing="ij"), -1).reshape(-1, 3)
        if not len(x):
            return np.zeros((0, 3))
        return G[cKDTree(self.points(*G.T)).query(x)[1]]

    def embed(self, points, tol=1e-12, maxit=50, slack=1e-9):
        """Parameters (s₁, s₂, w₃) with P(s₁, s₂, w₃) = x, by Newton.

        Solves J Δ = P(t) − x, t ← t − Δ for all points at once, from the
        nearest node of a coarse parameter grid, until |Δ|_∞ ≤ tol (parameter
        units). Iterates may leave the domain by up to one patch (the
        polynomials are extended); the result is clipped into the domain
        (s₁ of a periodic volume is taken modulo n1 instead).

        Parameters
        ----------
        points : array_like, shape (..., 3)
        tol : float
            Newton step tolerance, in parameter units.
        maxit : int
        slack : float
            A converged point whose parameters leave [0, n1 − 3] × [0, n2 − 3]
            × [0, 1] by more than this is outside.

        Returns
        -------
        s1, s2, w3 : ndarray, shape (...)

        Raises
        ------
        ValueError
            If any point lies outside V, or Newton does not converge.
        """
        x = np.asarray(points, dtype=float)
        if x.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {x.shape}")
        shape, x = x.shape[:-1], x.reshape(-1, 3)
        hi = self.domain
        t = self._initial_guess(x)
        done = np.zeros(len(x), dtype=bool)
        active = np.arange(len(x))
        for _ in range(maxit):
            if active.size == 0:
                break
            ta = t[active]
            r = self.points(*ta.T) - x[active]
            J = self.jacobian(*ta.T)
            scale = np.prod(np.linalg.norm(J, axis=-2), axis=-1)
            regular = np.abs(np.linalg.det(J)) > 1e-14 * scale
            J[~regular] = np.eye(3)
            step = np.linalg.solve(J, r[..., None])[..., 0]
            t[active] = self._wrap(np.clip(ta - step, -1.0, hi + 1.0))
            conv = regular & (np.abs(step).max(axis=-1) <= tol)
            done[active[conv]] = True
            active = active[regular & ~conv]
        t = self._wrap(t)
        outside = np.any((t < -slack) | (t > hi + slack), axis=-1)
        for bad, what in ((outside, "lie outside the bounding volume"),
                          (~done, "were not embedded: Newton did not converge "
                                  f"in {maxit} iterations")):
            if bad.any():
                i = np.flatnonzero(bad)[0]
                raise ValueError(
                    f"{bad.sum()} of {len(x)} points {what} (first: point {i} at "
                    f"({x[i, 0]:.6g}, {x[i, 1]:.6g}, {x[i, 2]:.6g}), parameters "
                    f"({t[i, 0]:.4g}, {t[i, 1]:.4g}, {t[i, 2]:.4g}) in "
                    f"[0, {hi[0]:g}]×[0, {hi[1]:g}]×[0, 1])")
        t = np.clip(t, 0.0, hi)
        return tuple(t[:, c].reshape(shape) for c in range(3))

    def _wrap(self, t):
        """Parameters (N, 3) with s₁ taken modulo n1 if periodic."""
        if self.periodic:
            t[:, 0] = np.mod(t[:, 0], self.n1)
        return t

    # -- imposed deformations (paper, section 4) --------------------------

    def deformed(self, mode, amount=None):
        """A new volume whose control points are moved, along the row axis x.

        c is the centre of the control net's bounding box, L = (x_max −
        x_min)(n1 − 3)/(n1 − 1) the volume's length along x, ξ = x − c_x,
        η = y − c_y, ζ = z − c_z (for a box from `around`, c is the centre of
        the volume and z = c_z its mid-plane).

        traction   x' = c_x + λ ξ                      (λ = amount > 0)
        shear      x' = x + tan γ · η                  (γ = amount, degrees)
        torsion    (η', ζ') = R(θ) (η, ζ)/σ,  θ = Θ ξ/L (Θ = amount, degrees)
        flexion    x' = c_x + ρ sin(ξ/R),  z' = c_z + R − ρ cos(ξ/R),
                   ρ = (R − ζ)/σ,  R = L/Θ            (Θ = amount, degrees)

        Traction and shear are affine: every point of V moves by the map.
        Torsion twists V about the line (c_y, c_z) by Θ from end to end;
        flexion bends it onto arcs about the axis (x, z) = (c_x, c_z + R),
        parallel to y, by Θ from end to end, towards +z, the mid-plane keeping
        its length L. Both rotate neighbouring control points by
        δ = Θ/(n1 − 3), and a spline whose control points turn by δ passes
        at σ = (4 + 2 cos δ)/6 of their radius at the junctions
        (`bspline.junction_symbol`); dividing the radius by σ makes a regular
        net (as from `around`) follow the ideal map exactly at every junction
        s₁ ∈ ℤ, and to O(δ⁴) in between.

        Parameters
        ----------
        mode : {'flexion', 'traction', 'shear', 'torsion'}
        amount : float, optional
            Defaults to DEFAULT_AMOUNTS[mode].

        Returns
        -------
        BoundingVolume
        """
        if mode not in MODES:
            raise ValueError(
                f"unknown deformation {mode!r}; valid modes: {', '.join(MODES)}")
        amount = float(DEFAULT_AMOUNTS[mode] if amount is None else amount)
        q = self.flat.copy()
        lo, hi = q.min(axis=0), q.max(axis=0)
        c = 0.5 * (lo + hi)
        L = (hi[0] - lo[0]) * (self.n1 - 3) / (self.n1 - 1)
        xi, eta, zeta = (q - c).T
        angle = np.radians(amount)
        sigma = bspline.junction_symbol(angle / (self.n1 - 3))
        if mode == "traction":
            if not amount > 0:
                raise ValueError(f"traction ratio must be > 0, got {amount}")
            q[:, 0] = c[0] + amount * xi
        elif mode == "shear":
            q[:, 0] += np.tan(angle) * eta
        elif mode == "torsion":
            th = angle * xi / L
            q[:, 1] = c[1] + (eta * np.cos(th) - zeta * np.sin(th)) / sigma
            q[:, 2] = c[2] + (eta * np.sin(th) + zeta * np.cos(th)) / sigma
        elif angle != 0.0:
            R = L / angle
            rho = (R - zeta) / sigma
            if np.any(rho * np.sign(R) <= 0):
                raise ValueError(
                    f"flexion by {amount:g}° folds the volume: curvature radius "
                    f"{abs(R):.4g} is below the half thickness")
            q[:, 0] = c[0] + rho * np.sin(xi / R)
            q[:, 2] = c[2] + R - rho * np.cos(xi / R)
        return self.like(q)

    # -- files ------------------------------------------------------------

    def _hexahedra(self):
        """VTK hexahedra of the control lattice, ((n1 − 1)(n2 − 1), 8), closed
        around (n1 (n2 − 1)) if periodic."""
        around = self.n1 if self.periodic else self.n1 - 1
        k2, k1 = np.indices((self.n2 - 1, around)).reshape(2, -1)
        k1n = (k1 + 1) % self.n1
        quad = np.stack([self.index(k1, k2, 0), self.index(k1n, k2, 0),
                         self.index(k1n, k2 + 1, 0), self.index(k1, k2 + 1, 0)],
                        axis=-1)
        return np.concatenate([quad, quad + self.n1 * self.n2], axis=-1)

    def _lattice(self):
        """(k1, k2, k3) of every control point, (2 n1 n2, 3), in DOF order."""
        k3, k2, k1 = np.indices((2, self.n2, self.n1)).reshape(3, -1)
        return np.stack([k1, k2, k3], axis=-1)

    def save(self, path):
        """Write the control net as a hexahedral mesh (.vtu, .xdmf or .vtk).

        Points are the control points in DOF order, cells the hexahedra of
        the lattice, and point data ``lattice_index`` holds (k1, k2, k3),
        from which `load` recovers n1 and n2, and ``periodic`` (1 on every
        point of a volume closed around).
        """
        path = Path(path)
        if path.suffix not in _READERS:
            raise ValueError(
                f"{path}: use one of {', '.join(_READERS)} for a bounding volume")
        import meshio

        meshio.Mesh(self.flat, [("hexahedron", self._hexahedra())],
                    point_data={_LATTICE: self._lattice(),
                                _PERIODIC: np.full(self.size, int(self.periodic))}
                    ).write(path)

    @classmethod
    def load(cls, path):
        """Read a control net written by `save`; ValueError if malformed."""
        path = Path(path)
        if path.suffix not in _READERS:
            raise ValueError(
                f"{path}: use one of {', '.join(_READERS)} for a bounding volume")
        import meshio

        try:
            mesh = getattr(meshio, _READERS[path.suffix]).read(str(path))
        except OSError:
            raise
        except Exception as err:
            raise ValueError(f"{path}: not a readable {path.suffix} mesh "
                             f"({type(err).__name__}: {err})") from err
        lattice = mesh.point_data.get(_LATTICE)
        if lattice is None:
            raise ValueError(f"{path}: no {_LATTICE!r} point data giving n1, n2; "
                             "not a knitfem bounding volume")
        lattice = np.asarray(lattice)
        pts = np.asarray(mesh.points, dtype=float)
        if (lattice.shape != (len(pts), 3) or pts.shape[-1:] != (3,)
                or len(pts) == 0):
            raise ValueError(f"{path}: {len(pts)} points with {_LATTICE} of shape "
                             f"{lattice.shape}; expected (N, 3) for both")
        n1, n2 = (int(m) + 1 for m in lattice[:, :2].max(axis=0))
        if len(pts) != 2 * n1 * n2:
            raise ValueError(f"{path}: {len(pts)} points, expected 2·{n1}·{n2} = "
                             f"{2 * n1 * n2} for a {n1}×{n2}×2 net")
        periodic = np.asarray(mesh.point_data.get(_PERIODIC, [0]))
        volume = cls.from_flat(pts, n1, n2, bool(periodic.ravel()[0]))
        if not np.array_equal(lattice, volume._lattice()):
            raise ValueError(f"{path}: points are not in the numbering "
                             "k1 + n1 (k2 + n2 k3)")
        return volume
