"""The full model's constraints in PETSc: g(ε), its Jacobian C(ε) and the
curvature Σ_i μ_i ∇²g_i, on whole yarns a rank.

Rows. The vector constraints (contacts of ``constraints.Contacts`` or
``sliding.SlidingCrossings``, holds of ``constraints.Holds``) are ordered
by the yarn that owns them, contacts of a yarn before its holds, whatever
the number of ranks. A contact gives the rows of its kind (``rows``: three
for a fixed crossing, one for a sliding one), a hold three. A rank owns the
rows of its yarns.

C(ε) keeps one sparsity pattern for the run: a contact row couples the
control points of its two yarn points in all three components (8 points
for a fixed crossing, two windows for a sliding one), a hold row 4 points
in its own component. Its values are written in place,
into the array C holds (``solvers.aij.OwnAIJ``).

Ghosts. A contact owned by course k reads the control points of course
k + 1, which may live on the next rank; the curvature term of a contact
lands in the rows of both its yarns and reads its multipliers μ, which live
on the rank of course k. Two PETSc scatters, set up once, bring both.

For fixed crossings the curvature is linear in μ with constant
coefficients (g is quadratic), so its values in the tangent are
S (Σ_j μ_cj h_cj) for the constant Hessians h and a constant 0/1 scatter S
built once from the slots of the tangent's pattern (``Curvature``); a
sliding crossing's Hessian depends on ε and goes through the same kind of
scatter, with full 3 × 3 blocks (``sliding.BlockCurvature``).
"""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from solvers.aij import OwnAIJ

from knitfem.contact.sliding import BlockCurvature

__all__ = ["ConstraintAssembly", "Curvature"]


def _block_is(comm, points):
    """IS of the interleaved coordinates of ``points`` (block size 3)."""
    return PETSc.IS().createBlock(3, np.asarray(points, dtype=PETSc.IntType),
                                  comm=PETSc.COMM_SELF)


class Curvature:
    """Σ_i μ_i ∇²g_i of n contacts added into a tangent's values.

    ∇²g_cj = h_cj ⊗ I₃ with h (n, 3, 8, 8) constant, so entry (3k + d,
    3l + d) of contact c gets m_ckl = Σ_j μ_cj h_cjkl for d = 0, 1, 2: the
    sums m (n·64, one small contraction) go to their three slots through a
    constant 0/1 matrix S (nnz × 64 n, built column by column: no sort),
    three entries a column where the rows are local."""

    def __init__(self, h, slots, nnz):
        n = len(h)
        self.h = np.ascontiguousarray(h.reshape(n, 3, 64))
        order = np.ascontiguousarray(slots.transpose(0, 2, 3, 1)).reshape(64 * n, 3)
        keep = order >= 0                                  # column 64c + 8k + l, d
        indptr = np.zeros(64 * n + 1, dtype=np.int64)
        np.cumsum(keep.sum(axis=1), out=indptr[1:])
        self.S = sp.csc_matrix((np.ones(indptr[-1]), order[keep], indptr),
                               shape=(nnz, 64 * n))

    def add(self, mu, weight, values):
        """values += weight · Σ_i μ_i ∇²g_i for the multipliers ``mu`` (3 n,
        a contact's three rows together)."""
        m = np.einsum("cj,cjx->cx", np.reshape(mu, (-1, 3)), self.h)
        values += self.S @ (weight * m.ravel())


class ConstraintAssembly:
    """g, C(ε) and Σμ∇²g of ``contacts`` and ``holds`` on a ``YarnLayout``.

    Collective on ``comm``. ``C`` is the Jacobian (rows: this rank's
    constraints; columns: the yarn coordinates), ``kind`` the kind of every
    vector constraint in global order ("contact", "fixed", "clamped"),
    ``reach`` (count, 2) the first and last yarn each one reads, ``count``
    their number.
    """

    def __init__(self, comm, layout, contacts, holds):
        self.comm, self.layout = comm, layout
        nct, nr, kc = contacts.count, contacts.rows, contacts.cols.shape[1]
        owner = np.concatenate([contacts.owner, holds.owner])
        order = np.argsort(owner, kind="stable")
        position = np.empty(len(owner), dtype=np.int64)
        position[order] = np.arange(len(owner))
        self.kind = np.concatenate([np.full(nct, "contact"), holds.kind])[order] \
            if len(owner) else np.zeros(0, "<U7")
        self.owner = owner[order]
        self.count = len(owner)
        ends = np.stack([contacts.cols.min(axis=1), contacts.cols.max(axis=1)], 1)
        self.reach = np.concatenate([
            np.searchsorted(layout.yarn_offset, ends, side="right") - 1,
            np.repeat(holds.owner[:, None], 2, axis=1)]).reshape(-1, 2)[order]
        # scalar rows of each vector constraint, and the first of each
        self.nrows = np.where(self.kind == "contact", nr, 3)
        first = np.concatenate([[0], np.cumsum(self.nrows)])
        lo, hi = np.searchsorted(owner[order], [layout.yarn_start, layout.yarn_end])
        self.start, self.nlocal = int(lo), int(hi - lo)
        cpos, hpos = position[:nct], position[nct:]
        # this rank's contacts and holds, and their first local scalar row
        self.mine = np.flatnonzero((cpos >= lo) & (cpos < hi))
        self.mine_h = np.flatnonzero((hpos >= lo) & (hpos < hi))
        crow = first[cpos[self.mine]] - first[lo]
        hrow = first[hpos[self.mine_h]] - first[lo]
        self.hold_rows = hrow            # first local row of each of mine_h
        k, K = int(first[hi] - first[lo]), int(first[-1])
        length = np.zeros(k, dtype=np.int64)
        length[crow[:, None] + np.arange(nr)] = 3 * kc
        length[hrow[:, None] + np.arange(3)] = 4
        indptr = np.concatenate([[0], np.cumsum(length)]).astype(PETSc.IntType)
        # control points read: the local contacts', the holds' 4 and those of
        # the contacts whose curvature reaches this rank's rows
        cp0, cp1 = layout.cp_start, layout.cp_end
        touch = (contacts.cols >= cp0) & (contacts.cols < cp1)
        self.touching = np.flatnonzero(touch.any(axis=1))
        hi_ent = holds.indptr[self.mine_h][:, None] + np.arange(4)
        hcols = holds.indices[hi_ent].reshape(-1, 4)
        parts = [contacts.cols[self.mine].ravel(), hcols.ravel(),
                 contacts.cols[self.touching].ravel()]
        need, inv = np.unique(np.concatenate(parts), return_inverse=True)
        cut = np.cumsum([len(q) for q in parts])
        self.ghost_c = inv[:cut[0]].reshape(-1, kc)
        self.ghost_h = inv[cut[0]:cut[1]].reshape(-1, 4)
        self.ghost_r = inv[cut[1]:].reshape(-1, kc)
        # positions of the values: contact row v + j holds (k, d) at 3k + d
        self.cslot = (indptr[crow][:, None, None, None]
                      + 3 * kc * np.arange(nr)[None, :, None, None]
                      + 3 * np.arange(kc)[None, None, :, None]
                      + np.arange(3)[None, None, None, :])          # (n, nr, kc, 3)
        self.hslot = (indptr[hrow][:, None, None]
                      + 4 * np.arange(3)[None, :, None]
                      + np.arange(4)[None, None, :])                # (n, 3, 4)
        indices = np.empty(indptr[-1], dtype=PETSc.IntType)
        indices[self.cslot] = 3 * contacts.cols[self.mine][:, None, :, None] \
            + np.arange(3)
        indices[self.hslot] = 3 * hcols[:, None, :] + np.arange(3)[None, :, None]
        n, N = 3 * layout.ncp_local, 3 * layout.ncp
        # block size 3 where every constraint has three rows
        self.own = OwnAIJ.from_csr(comm, ((k, K), (n, N)), indptr, indices,
                                   bsize=3 if nr == 3 else None)
        self.cslot, self.hslot = self.own.place(self.cslot), self.own.place(self.hslot)
        self.values = self.own.values
        self.values[self.hslot] = holds.values[hi_ent][:, None, :]
        self.C = self.own.mat
        self.C.assemble()
        self.C.setOptionsPrefix("full_C_")
        self.rhs = holds.rhs[self.mine_h]
        self.hrow = hrow
        self.crow = crow
        self.points = PETSc.Vec().createSeq(3 * len(need), comm=PETSc.COMM_SELF)
        x = self.C.createVecRight()
        self.gather_points = PETSc.Scatter().create(
            x, _block_is(comm, need), self.points, None)
        x.destroy()
        # the μ of the contacts whose curvature reaches this rank's rows
        rows_mu = first[cpos[self.touching]][:, None] + np.arange(nr)
        self.mu = PETSc.Vec().createSeq(rows_mu.size, comm=PETSc.COMM_SELF)
        lam = self.C.createVecLeft()
        self.gather_mu = PETSc.Scatter().create(
            lam, PETSc.IS().createGeneral(rows_mu.ravel().astype(PETSc.IntType),
                                          comm=PETSc.COMM_SELF), self.mu, None)
        lam.destroy()
        self.rows, self.contact_kind = nr, contacts.kind
        self.local = contacts.select(self.mine)          # rows of this rank
        # into its tangent rows: the same crossings (one rank), or more
        self.reaching = self.local if np.array_equal(self.touching, self.mine) \
            else contacts.select(self.touching)
        self.nonlinear = contacts.count > 0               # C depends on ε
        self.B = None          # curvature_operator in the owning model's tangent
        self.reanchored = 0    # sliding crossings' reference tangents moved

    def _points(self, x):
        """Control points read by this rank's rows, from the state x (Vec)."""
        self.gather_points.scatter(x, self.points)
        return self.points.getArray(readonly=True).reshape(-1, 3)

    def residual(self, x, g):
        """g(ε) into the Vec g (C's row layout). Collective."""
        P = self._points(x)
        out = g.getArray()
        out[self.crow[:, None] + np.arange(self.rows)] = \
            self.local.values(P[self.ghost_c])
        w = self.values[self.hslot]                                # (n, 3, 4)
        out[self.hrow[:, None] + np.arange(3)] = \
            np.einsum("nja,naj->nj", w, P[self.ghost_h]) - self.rhs

    def jacobian(self, x):
        """C(ε) = ∂g/∂ε, values written in place (collective); returns C."""
        if self.nonlinear:
            P = self._points(x)
            grad = self.local.gradients(P[self.ghost_c])
            self.values[self.cslot] = grad
            self.C.assemble()
        return self.C

    def element_cols(self):
        """Control points (n, 8) of the contacts that reach this rank's rows:
        elements to add to the tangent's pattern."""
        return self.reaching.cols

    @property
    def diagonal_curvature(self):
        """Whether a contact's Hessians are blocks h ⊗ I₃ (fixed crossings)
        rather than full 3 × 3 blocks (sliding crossings)."""
        return self.contact_kind == "fixed"

    def curvature_operator(self, slots, nnz):
        """The curvature Σ_i μ_i ∇²g_i of the contacts that reach this rank's
        rows, into a tangent's ``nnz`` values; ``slots`` from
        ``ElementPattern.blocks3`` (−1 off this rank's rows). Fixed crossings
        (``Curvature``): (len(touching), 3, 8, 8), the slot of entry
        (3k + d, 3l + d) at [c, d, k, l] (``diagonal``); sliding crossings
        (``sliding.BlockCurvature``): (len(touching), 3K, 3K), full blocks."""
        if self.diagonal_curvature:
            return Curvature(self.reaching.hessians(), slots, nnz)
        return BlockCurvature(self.reaching, slots, nnz)

    def add_curvature(self, mu, weight, values, x=None):
        """values += weight · Σ_i μ_i ∇²g_i (the owning model's tangent
        values, through ``self.B``, its curvature operator), at the state x
        (needed by sliding crossings, whose Hessians depend on it).
        Collective."""
        self.gather_mu.scatter(mu, self.mu)
        mu = self.mu.getArray(readonly=True)
        if self.diagonal_curvature:
            self.B.add(mu, weight, values)
        else:
            self.B.add(mu, weight, values, self._points(x)[self.ghost_r])

    def commit(self, x):
        """An accepted state x: sliding crossings start the search for their
        point from there. Returns how many have strayed so far from their
        windows' middle that a window should move (``SlidingCrossings.centred``)
        and how many sit at an end of a window that cannot move (an open
        yarn's end) (collective; 0, 0 for fixed crossings)."""
        if self.diagonal_curvature:
            return 0, 0
        P = self._points(x)
        loc = self.local
        self.reanchored += loc.commit(P[self.ghost_c])
        if self.reaching is not loc:
            self.reaching.commit(P[self.ghost_r])
        move = (loc.centred() != loc.first).any(axis=1)
        stuck = np.zeros(loc.count, bool)
        stuck[loc.at_edge()] = True
        counts = np.array([np.count_nonzero(move), np.count_nonzero(stuck & ~move)])
        return tuple(self.comm.tompi4py().allreduce(counts))

    def slid_out(self, x):
        """How many sliding crossings' s* at the state x lie on an end of
        their window, where they were held (collective; 0 for fixed)."""
        if self.diagonal_curvature:
            return 0
        self.local.solve(self._points(x)[self.ghost_c])
        return self.comm.tompi4py().allreduce(len(self.local.at_edge()))

    def sliding_parameters(self):
        """Every sliding crossing's committed state
        (``SlidingCrossings.state``: s, σ, windows, slide so far, locks, χ),
        (ncontacts, 11 + 4W) on every rank, for a checkpoint or to move the
        windows (collective); None for fixed crossings."""
        if self.diagonal_curvature:
            return None
        parts = self.comm.tompi4py().allgather((self.mine, self.local.state()))
        s = np.zeros((sum(len(m) for m, _ in parts), parts[0][1].shape[1]))
        for mine, part in parts:
            s[mine] = part
        return s

    def set_sliding_parameters(self, state, X):
        """Commit the sliding crossings' ``state`` (``sliding_parameters``,
        on the windows they have now; X the rest control points)."""
        state = np.asarray(state, dtype=float)
        for part, which in ((self.local, self.mine), (self.reaching, self.touching)):
            part.set_state(state[which], X)

    def slides(self):
        """Arc lengths (n, 2) along both yarns by which this rank's sliding
        crossings have moved from rest (none for fixed crossings)."""
        if self.diagonal_curvature:
            return np.zeros((0, 2))
        return self.local.slide_lengths()

    def destroy(self):
        for obj in (self.C, self.points, self.gather_points, self.mu, self.gather_mu):
            obj.destroy()
