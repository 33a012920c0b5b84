"""Constraints on yarn control points: persistent contacts and world holds.

A yarn point P_f(s) = Σ_a b_a(u) p_{f, k+a} (k, u from s) is linear in the
control points (``Fabric.point_rows``; yarns of their own lengths). World
constraints are linear in ε:

    fixed point   P_f(s)  = x₀,       clamped tangent   P_f'(s) = X_f'(s).

Contacts are frame-indifferent. Course k interlocks with course k + 1 at
fixed spline parameters (s_a, s_b). With the separation and the tangents

    r = P_a(s_a) − P_b(s_b),   t_a = P_a'(s_a),   t_b = P_b'(s_b),

a contact holds three invariants at their rest values (R, T_a, T_b at rest):

    g₁ = (r·r − R·R) / 2|R|,   g₂ = (r·t_a − R·T_a) / |T_a|,
    g₃ = (r·t_b − R·T_b) / |T_b|.

Dot products of vectors that turn with the fabric do not change under a
rotation, and r, t_a, t_b do not change under a translation (their weights
sum to zero), so every rigid motion satisfies g = 0 exactly. The scales make
each g_j a length (≈ |r| − |R| and the tangential slips, in metres). At the
rest closest approach R ⟂ T_a, T_b, so the rows ∂g/∂(shift of yarn a) =
(r/|R|, t_a/|T_a|, t_b/|T_b|) are independent when the yarns cross (the
jersey's interlocks cross at 64°), and the two yarns are held at fixed
parameters, their distance kept, sliding along neither.

Why these invariants and not a world offset P_a − P_b = d (the linear
contact knitfem had: a 45° turn violated it by 1.6 r) or an offset carried
in a frame built from the tangents: each g_j is a bilinear form
(u·P)·(v·P) of the contact's 8 control points P, so g is quadratic, C(ε) =
∂g/∂ε is linear in ε and the curvature Σ_j μ_j ∇²g_j is a constant matrix
times μ, exact in closed form. A tangent frame (normalised t_a, t_a × t_b)
is rational in ε, with a Hessian ten times the work and singular where the
tangents align. Measured on the hanging 7×7 (BDF2, 3 s): the invariant
contacts take the same Newton iterations a step as the linear ones did
(docs/results.md).

A contact is three scalar rows; a world constraint is three rows, one a
component. Rows are grouped by the yarn that owns them (course k for a
k/k+1 contact) so that a rank owning whole yarns owns their rows.
"""

from dataclasses import dataclass

import numpy as np


__all__ = ["Contacts", "Holds", "contacts", "fixed_points", "build"]


@dataclass
class Holds:
    """Linear world constraints (fixed points, clamped tangents) in CSR form.

    owner (n,) yarn owning each vector constraint; indptr, indices, values
    the CSR of the scalar rows c over global control points (c x = rhs for
    each component); rhs (n, 3); kind (n,) "fixed" or "clamped".
    """

    owner: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    values: np.ndarray
    rhs: np.ndarray
    kind: np.ndarray

    @property
    def count(self):
        return len(self.owner)

    def residual(self, x):
        """c x − d for control points x (ncp, 3): (n, 3)."""
        rows = np.repeat(np.arange(self.count), np.diff(self.indptr))
        r = np.zeros((self.count, 3))
        np.add.at(r, rows, self.values[:, None] * x[self.indices])
        return r - self.rhs

    def select(self, keep):
        """The rows where ``keep`` (bool array) is true."""
        keep = np.flatnonzero(keep)
        start, length = self.indptr[keep], np.diff(self.indptr)[keep]
        indptr = np.concatenate([[0], np.cumsum(length)])
        take = np.repeat(start - indptr[:-1], length) + np.arange(indptr[-1])
        return Holds(self.owner[keep], indptr, self.indices[take], self.values[take],
                     self.rhs[keep], self.kind[keep])

    @staticmethod
    def concatenate(parts):
        """One set from several, rows in order."""
        shift = np.cumsum([0] + [p.indptr[-1] for p in parts[:-1]])
        return Holds(np.concatenate([p.owner for p in parts]),
                     np.concatenate([[0]] + [p.indptr[1:] + s
                                             for p, s in zip(parts, shift)]),
                     np.concatenate([p.indices for p in parts]),
                     np.concatenate([p.values for p in parts]),
                     np.concatenate([p.rhs for p in parts]),
                     np.concatenate([p.kind for p in parts]))


@dataclass
class Contacts:
    """Persistent contacts as bilinear invariants (module docstring).

    owner (n,) the yarn of P_a; cols (n, 8) global control points (4 of
    yarn a, then 4 of yarn b); U, V (n, 3, 8) the weights of the two factors
    of g_j = s_j ((U_j·P)·(V_j·P) − c_j); scale s (n, 3); rest c (n, 3).
    """

    owner: np.ndarray
    cols: np.ndarray
    U: np.ndarray
    V: np.ndarray
    scale: np.ndarray
    rest: np.ndarray

    rows = 3                      # scalar rows a contact
    kind = "fixed"

    @property
    def count(self):
        return len(self.owner)

    def factors(self, P):
        """(U·P, V·P), each (n, 3, 3), for the contacts' points P (n, 8, 3)."""
        return (np.einsum("njk,nkd->njd", self.U, P),
                np.einsum("njk,nkd->njd", self.V, P))

    def values(self, P):
        """g (n, 3) at the contacts' control points P (n, 8, 3)."""
        a, b = self.factors(P)
        return self.scale * (np.einsum("njd,njd->nj", a, b) - self.rest)

    def gradients(self, P):
        """∂g_j/∂p_k (n, 3, 8, 3) = s_j (U_jk V_j·P + V_jk U_j·P)."""
        a, b = self.factors(P)
        return self.scale[..., None, None] * (self.U[..., None] * b[:, :, None, :]
                                              + self.V[..., None] * a[:, :, None, :])

    def hessians(self):
        """Scalar ∇²g_j (n, 3, 8, 8) = s_j (U_j V_jᵀ + V_j U_jᵀ), constant;
        the 3-D Hessian is ∇²g_j ⊗ I₃."""
        uv = np.einsum("njk,njl->njkl", self.U, self.V)
        return self.scale[..., None, None] * (uv + uv.transpose(0, 1, 3, 2))

    def select(self, keep):
        """The contacts where ``keep`` (bool array) is true."""
        return Contacts(*(a[keep] for a in (self.owner, self.cols, self.U, self.V,
                                            self.scale, self.rest)))


def contacts(yarn_a, s_a, yarn_b, s_b, fabric, X, separation=None):
    """Contacts of P_a(s_a) with P_b(s_b) on the yarns of ``fabric``
    (``Fabric.point_rows``), invariants taken at rest X (N, 3), the distance
    |R| held ``separation`` where given (R ⟂ T_a, T_b: the parameters are the
    rest's closest approach)."""
    ca, va = fabric.point_rows(yarn_a, s_a)
    cb, vb = fabric.point_rows(yarn_b, s_b)
    da = fabric.point_rows(yarn_a, s_a, nu=1)[1]
    db = fabric.point_rows(yarn_b, s_b, nu=1)[1]
    zero = np.zeros((len(ca), 4))
    w = np.concatenate([va, -vb], axis=1)                        # r
    ta = np.concatenate([da, zero], axis=1)                      # t_a
    tb = np.concatenate([zero, db], axis=1)                      # t_b
    U = np.stack([w, w, w], axis=1)
    V = np.stack([w, ta, tb], axis=1)
    cols = np.concatenate([ca, cb], axis=1)
    P = X[cols]
    r, Ta, Tb = (np.einsum("nk,nkd->nd", f, P) for f in (w, ta, tb))
    scale = np.stack([0.5 / np.linalg.norm(r, axis=1), 1 / np.linalg.norm(Ta, axis=1),
                      1 / np.linalg.norm(Tb, axis=1)], axis=1)
    rest = np.stack([np.sum(r * r, 1), np.sum(r * Ta, 1), np.sum(r * Tb, 1)], axis=1)
    if separation is not None:
        scale[:, 0], rest[:, 0] = 0.5 / separation, separation**2
    return Contacts(np.asarray(yarn_a), cols, U, V, scale, rest)



def fixed_points(yarn, s, fabric, X, nu=0):
    """Fixed-point rows P_f(s) = x₀ (nu = 0), or clamped tangents
    P_f'(s) = X_f'(s) (nu = 1), with the right-hand side taken at X."""
    cols, vals = fabric.point_rows(yarn, s, nu)
    rhs = np.einsum("na,nai->ni", vals, X[cols])
    n = len(s)
    return Holds(np.asarray(yarn), np.arange(0, 4 * n + 1, 4), cols.ravel(),
                 vals.ravel(), rhs, np.full(n, ("fixed", "clamped")[nu]))


def build(fabric):
    """(Contacts, Holds) of a ``Fabric``: contact invariants at its rest X,
    the holds at its start state (``Fabric.start_points``)."""
    X0 = fabric.start_points()
    ya, sa, yb, sb = fabric.contacts
    holds = Holds.concatenate([fixed_points(*fabric.fixed, fabric, X0),
                               fixed_points(*fabric.clamped, fabric, X0, nu=1)])
    return contacts(ya, sa, yb, sb, fabric, fabric.X, fabric.separation), holds
