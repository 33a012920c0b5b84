"""Linear constraints on yarn control points: contacts and fixed points.

A yarn point is P_f(s) = Σ_a b_a(u) p_{f, k+a} (k, u from s), linear in the
control points, so both kinds of constraint are linear in ε:

    contact       P_f(s_a) − P_g(s_b) = d_ab   (d_ab the rest offset),
    fixed point   P_f(s)             = x₀.

The scalar matrix c has one row a vector constraint; C = c ⊗ I₃ acts on the
interleaved coordinates. Rows are kept grouped by the yarn that owns them
(course k for a k/k+1 contact) so that a rank owning whole yarns owns their
constraint rows.
"""

from dataclasses import dataclass

import numpy as np

from . import bspline

__all__ = ["Constraints", "point_rows", "contacts", "fixed_points", "build"]


@dataclass
class Constraints:
    """Scalar constraint rows in CSR form over global control-point indices.

    owner (ncon,) yarn owning each row; indptr, indices, values the CSR of c;
    rhs (ncon, 3) the right-hand side d; kind (ncon,) "contact" or "fixed".
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

    def dense_rows(self, ncols):
        """c as a dense (ncon, ncols) array (small problems and tests only)."""
        c = np.zeros((self.count, ncols))
        rows = np.repeat(np.arange(self.count), np.diff(self.indptr))
        np.add.at(c, (rows, self.indices), self.values)
        return c

    def residual(self, x):
        """c x − d for control points x (ncp, 3): (ncon, 3)."""
        rows = np.repeat(np.arange(self.count), np.diff(self.indptr))
        r = np.zeros((self.count, 3))
        np.add.at(r, rows, self.values[:, None] * x[self.indices])
        return r - self.rhs

    @staticmethod
    def concatenate(parts):
        """Merge constraint sets and group the rows by owning yarn (stable)."""
        parts = [p for p in parts if p.count]
        if not parts:
            return Constraints(np.zeros(0, int), np.zeros(1, int), np.zeros(0, int),
                               np.zeros(0), np.zeros((0, 3)), np.zeros(0, "<U7"))
        owner = np.concatenate([p.owner for p in parts])
        lengths = np.concatenate([np.diff(p.indptr) for p in parts])
        starts = np.concatenate([p.indptr[:-1] + off for p, off in
                                 zip(parts, np.cumsum([0] + [p.indptr[-1]
                                                             for p in parts[:-1]]))])
        indices = np.concatenate([p.indices for p in parts])
        values = np.concatenate([p.values for p in parts])
        order = np.argsort(owner, kind="stable")
        take = np.concatenate([np.arange(s, s + n) for s, n in
                               zip(starts[order], lengths[order])])
        indptr = np.concatenate([[0], np.cumsum(lengths[order])])
        return Constraints(owner[order], indptr, indices[take], values[take],
                           np.concatenate([p.rhs for p in parts])[order],
                           np.concatenate([p.kind for p in parts])[order])


def point_rows(offset, s, nseg, nu=0):
    """B-spline weights of d^nu P/ds^nu at s: (cols (n,4), vals (n,4)).

    offset is the global index of each point's yarn's first control point.
    """
    k, u = bspline.locate(s, nseg)
    cols = np.asarray(offset)[..., None] + k[:, None] + np.arange(4)
    return cols, bspline.basis(u, nu)


def contacts(yarn_a, s_a, yarn_b, s_b, yarn_offset, nseg, X):
    """Contact rows P_a(s_a) − P_b(s_b) = d_ab with d_ab taken at rest X (ncp,3)."""
    ca, va = point_rows(yarn_offset[yarn_a], s_a, nseg)
    cb, vb = point_rows(yarn_offset[yarn_b], s_b, nseg)
    cols = np.concatenate([ca, cb], axis=1)
    vals = np.concatenate([va, -vb], axis=1)
    rhs = np.einsum("na,nai->ni", vals, X[cols])
    n = len(s_a)
    return Constraints(np.asarray(yarn_a), np.arange(0, 8 * n + 1, 8), cols.ravel(),
                       vals.ravel(), rhs, np.full(n, "contact"))


def fixed_points(yarn, s, yarn_offset, nseg, X, nu=0):
    """Fixed-point rows P_f(s) = x₀ (nu = 0), or clamped tangents
    P_f'(s) = X_f'(s) (nu = 1), with the right-hand side taken at rest X."""
    cols, vals = point_rows(yarn_offset[yarn], s, nseg, nu)
    rhs = np.einsum("na,nai->ni", vals, X[cols])
    n = len(s)
    return Constraints(np.asarray(yarn), np.arange(0, 4 * n + 1, 4), cols.ravel(),
                       vals.ravel(), rhs, np.full(n, ("fixed", "clamped")[nu]))


def build(fabric):
    """All constraint rows of a ``Fabric``, grouped by owning yarn."""
    offset = np.arange(fabric.nyarn + 1) * fabric.ncp
    nseg, X = fabric.ncp - 3, fabric.X.reshape(-1, 3)
    ya, sa, yb, sb = fabric.contacts
    return Constraints.concatenate([
        contacts(ya, sa, yb, sb, offset, nseg, X),
        fixed_points(*fabric.fixed, offset, nseg, X),
        fixed_points(*fabric.clamped, offset, nseg, X, nu=1),
    ])
