"""The mixed model: yarn level in full regions, the bounding volume elsewhere.

The yarn control points are split into a *full* set F (their coordinates
are unknowns of their own) and an *embedded* set E (ε = Γα as in the
reduced model). With q = [α; ε_F] the two are one linear map

    ε = Γ_mix q,   Γ̃_mix = [Γ̃_E  0]   (rows of embedded points)
                           [ 0   I ]   (rows of full points),   Γ_mix = Γ̃_mix ⊗ I₃,

and Lagrange's equations in q are those of the reduced model with Γ_mix in
place of Γ:

    M_mix q̈ = Γ_mixᵀ Q(Γ_mix q, Γ_mix q̇) + (C Γ_mix)ᵀλ,   (C Γ_mix) q = d,
    M_mix = Γ_mixᵀ M Γ_mix (PtAP),  tangent Γ_mixᵀ K Γ_mix (PtAP).

Yarn elements that straddle the border are evaluated at ε = Γ_mix q, so
they are exact. Constraints: fixed points and clamps stay (those touching
no full point reduced to independent rows, as in the reduced model);
contacts are kept when one of their two contact points lies in the full
region — at least half of the B-spline weight of P(s) there comes from full
control points — and dropped otherwise (the embedding holds those stitches
together). A contact whose full side carries only a sliver of weight would
pin a full control point to an embedded yarn with that weight's inverse as
its lever, which is why it is dropped rather than kept.

Full regions are unions of the volume's patches: stitch ranges given by the
user are widened to the patches they touch (``VolumeWeights.patches_of``).
An embedded region made of whole patches determines its volume control
points as well as the reduced model does (B-splines are locally linearly
independent on each patch); a patch left with a sliver of embedded points
does not (a 15x30 jersey in a 13x8 volume with stitches 0:5, courses 0:3
full: cond(M_mix) 1e19, against 3e8 once widened).

Sampled mixed model (``sampling`` given: -knit_sampling sampled; not the
default, see ``mixed_from_options``). Split the yarn elements into those touching a full control point
(T: exact, evaluated at ε = Γ_mix q) and those whose 4 points are all
embedded (V, the volume part, which sees α only). V's sum is hyper-reduced
as the reduced model's is (``sampling``, ECSW): trained on the same volume
states with the candidates and the target sums restricted to V,

    Σ_{e∈V} Γ_eᵀ Q_e ≈ Σ_{e∈S} ξ_e Γ_eᵀ Q_e,   S ⊂ V,  ξ ≥ 0,

so the model's energy is E_T(Γ_mix q) + Σ_{e∈S} ξ_e E_e(Γ_e α), its forces
and tangent that energy's. The tangent is Γ_mixᵀ K_T Γ_mix by PtAP, K_T over
T's elements and the kept contacts only, plus the sampled dense α–α block,
written into one matrix of fixed pattern (the union of the two). Each rank
samples its own yarns' V; the α–α block is summed over the ranks.

Volume control points that no embedded point depends on are no unknowns
(every one of them when all points are full: Γ_mix is then the identity and
the mixed model *is* the full model; with no full point it *is* the reduced
model). Columns are distributed by rank: rank r owns its share of α (an
even split) followed by the full control points of its own yarns, so every
identity row of Γ_mix lies in the rank's diagonal block.
"""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from knitfem.yarn import bspline
from knitfem.contact import constraints as cons
from knitfem.model.assembly import ElementPattern, create_aij, kron_identity
from knitfem.yarn.kernels import yarn_kernels
from knitfem.model.full import EV_FORCES, EV_TANGENT, applied_forces
from knitfem.errors import KnitError
from knitfem.knit.pattern import SEGMENTS_PER_STITCH
from knitfem.lod.reduced import EV_PTAP, EmbeddedModel, sampling_options
from knitfem.lod.sampling import SampledElements, over_ranks, sampled_set
from knitfem.yarn.elements import YarnElements

__all__ = ["VolumeWeights", "MixedSpace", "MixedModel", "trained", "stitch_mask",
           "parse_regions", "regions_from_options", "mixed_from_options"]

EV_MIXED = PETSc.Log.Event("knitMixedSetUp")

CONTACT_SIDE_FULL = 0.5     # a contact point is full when ≥ this weight is


def even_counts(n, size):
    """n items split evenly over ``size`` ranks: the count of each rank."""
    return n // size + (np.arange(size) < n % size)


class VolumeWeights:
    """Rows of Γ̃ for every yarn control point of a fabric (every rank holds all).

    cols, vals (N, 32) as ``BoundingVolume.weights``, sorted by column as in
    ``reduced.Embedding``; patch (N, 2) the volume patch (j1, j2) of each
    point; ``volume`` the bounding volume.
    """

    def __init__(self, fabric, volume):
        X = fabric.X
        try:
            s1, s2, w3 = volume.embed(X)
        except ValueError as err:
            raise KnitError(f"bounding volume: {err}") from None
        cols, vals = volume.weights(s1, s2, w3)
        order = np.argsort(cols, axis=1)
        self.cols = np.take_along_axis(cols, order, 1)
        self.vals = np.take_along_axis(vals, order, 1)
        around = bspline.segments(volume.n1, volume.periodic)
        self.patch = np.stack([bspline.locate(s1, around, volume.periodic)[0],
                               bspline.locate(s2, volume.n2 - 3)[0]], axis=-1)
        self.volume = volume
        self.npatch = (around, volume.n2 - 3)

    def patch_mask(self, patches):
        """Points whose patch (j1, j2) is in ``patches`` (an (n1−3, n2−3) bool
        array): the full set of a patch-wise refinement."""
        return np.asarray(patches, bool)[self.patch[:, 0], self.patch[:, 1]]

    def patches_of(self, mask):
        """The patches holding at least one point of ``mask``, (n1−3, n2−3)."""
        patches = np.zeros(self.npatch, bool)
        patches[self.patch[mask, 0], self.patch[mask, 1]] = True
        return patches


class MixedSpace:
    """Γ̃_mix and Γ_mix = Γ̃_mix ⊗ I₃ for a full-point mask. Collective.

    Parameters
    ----------
    comm, layout : the full model's communicator and ``YarnLayout``
    weights : VolumeWeights
    full : (N,) bool, the full control points (global numbering)
    """

    def __init__(self, comm, layout, weights, full):
        self.comm, self.layout, self.weights = comm, layout, weights
        self.full = full = np.asarray(full, bool)
        N, NV, P = layout.ncp, weights.volume.size, comm.size
        emb = ~full
        used = np.zeros(NV, bool)
        used[weights.cols[emb][weights.vals[emb] != 0]] = True
        self.alpha = np.flatnonzero(used)                  # kept volume points
        na = even_counts(len(self.alpha), P)
        cp = layout.cp_ranges
        nf = np.array([full[cp[r]:cp[r + 1]].sum() for r in range(P)])
        self.counts = na + nf
        off = np.concatenate([[0], np.cumsum(self.counts)])
        astart = np.concatenate([[0], np.cumsum(na)])
        self.ncol, self.ncol_local = off[-1], self.counts[comm.rank]
        self.na_local, self.col_start = na[comm.rank], off[comm.rank]
        # global column of every kept volume point and every full point
        owner = np.repeat(np.arange(P), na)
        self.volcol = np.full(NV, -1)
        self.volcol[self.alpha] = off[owner] + np.arange(len(self.alpha)) - astart[owner]
        owner = np.searchsorted(cp, np.arange(N), side="right") - 1
        rank_first = np.concatenate([[0], np.cumsum(nf)])[owner]
        self.fullcol = np.full(N, -1)
        self.fullcol[full] = (off[owner] + na[owner]
                              + np.cumsum(full) - 1 - rank_first)[full]
        # padded mixed rows of every point: (N, 32) columns and weights
        self.cols = np.where((weights.vals != 0) & emb[:, None],
                             self.volcol[weights.cols], 0)
        self.vals = np.where(emb[:, None], weights.vals, 0.0)
        self.cols[full, 0], self.vals[full, 0] = self.fullcol[full], 1.0
        lo, hi = layout.cp_start, layout.cp_end
        csr = self.csr(np.arange(hi - lo), np.arange(lo, hi), np.ones(hi - lo),
                       hi - lo)
        n, nc = hi - lo, self.ncol_local
        self.Gamma_scalar = create_aij(comm, (n, N), (nc, self.ncol), csr)
        self.Gamma = create_aij(comm, (3 * n, 3 * N), (3 * nc, 3 * self.ncol),
                                kron_identity(*csr), bsize=3)
        self.Gamma_scalar.setOptionsPrefix("mixed_Gammascalar_")
        self.Gamma.setOptionsPrefix("mixed_Gamma_")

    @property
    def volume(self):
        return self.weights.volume

    def csr(self, rows, points, w, nrows):
        """CSR of Σ w · (mixed row of point) into rows: the product c Γ̃_mix of
        a scalar matrix c given by its entries (rows, points, w)."""
        r = np.repeat(rows, self.cols.shape[1])
        v = (w[:, None] * self.vals[points]).ravel()
        A = sp.csr_matrix((v, (r, self.cols[points].ravel())),
                          shape=(nrows, max(self.ncol, 1)))
        A.sum_duplicates()
        A.eliminate_zeros()
        A.sort_indices()
        return A.indptr, A.indices, A.data

    def state(self, eps_points, alpha_points):
        """Local part of q from all control points (N, 3) and all volume
        points (NV, 3): q = [α (own share); ε_F (own full points)]."""
        lo, hi = self.layout.cp_start, self.layout.cp_end
        a0 = self.col_start
        mine = (self.volcol >= a0) & (self.volcol < a0 + self.na_local)
        q = np.empty((self.ncol_local, 3))
        q[self.volcol[mine] - a0] = alpha_points[mine]
        q[self.na_local:] = eps_points[lo:hi][self.full[lo:hi]]
        return q.ravel()

    def destroy(self):
        self.Gamma.destroy()
        self.Gamma_scalar.destroy()


def independent_rows(rows, rhs):
    """Rows (k, n) and right-hand sides (k, 3) reduced to an independent set
    with the same solutions, by a rank-revealing SVD (as the reduced model
    does for its world constraints)."""
    if not len(rows):
        return rows, rhs
    U, S, Vt = np.linalg.svd(rows, full_matrices=False)
    rank = int(np.sum(S > 1e-10 * S[0]))
    return Vt[:rank], (U[:, :rank].T @ rhs) / S[:rank, None]


def trained(tol):
    """The sampling rule of -knit_sampling sampled: each rank's set drawn from
    its embedded elements, trained to ``tol`` (or read from the cache, whose
    key holds the subset)."""
    def rule(full, embedding, subset):
        return sampled_set(full, embedding, tol, subset)
    rule.tol = tol
    return rule


class MixedModel(EmbeddedModel):
    """The mixed mechanical system of a ``FullModel`` through a ``MixedSpace``.

    Offers the interface of ``ReducedModel`` (M, m, C, Qg, forces,
    stiffness, constraints, rest_state, full_state, project, …) with
    q = [α; ε_F].
    ``reduced`` is the reduced model's ``Embedding`` of the same volume,
    kept for the error indicator and needed by the sampling. ``sampling``,
    a rule ``(full, embedding, subset) → (elements, weights, report)`` (e.g.
    ``trained(tol)``), samples the embedded elements (module docstring);
    None keeps every element (exact). Collective.
    """

    kind = "mixed"
    dense_saddle = False
    null_space = True       # Γ_mix may have one: solvers detect null pivots

    @property
    def Gamma(self):
        return self.space.Gamma

    def __init__(self, full, space, reduced=None, sampling=None):
        self.space, self.reduced = space, reduced
        G = space.Gamma
        self._embed(full, G, space.Gamma_scalar, "mixed_M_")
        with EV_MIXED:
            self._constraints()
        self.Qfull = G.createVecLeft()
        self.K = None
        self._proj = None
        self.rule, self.sampling, self.sampled = None, None, None
        if sampling is not None:
            if reduced is None or full.barrier is not None:
                raise KnitError("the sampled mixed model needs the reduced model's "
                                "embedding and no bodies: use -knit_sampling exact")
            with EV_MIXED:
                self._sample(sampling)

    @property
    def nfull(self):
        """Number of full control points."""
        return int(self.space.full.sum())

    def _constraints(self):
        """The kept rows of the full model's constraints through Γ_mix, and
        the world holds touching no full point as independent rows in α.

        g_mix(q) = [S g(Γ_mix q); c_w α − d_w], C_mix = [S C(Γ_mix q) Γ_mix; c_w],
        S the selection of the kept rows (contacts with a full side, holds
        touching a full point): each rank keeps rows of its own yarns.
        """
        full, space = self.full, self.space
        contacts, holds = cons.build(self.fabric)
        w = np.abs(contacts.U[:, 0])                                # |r weights|
        wf = w * space.full[contacts.cols]
        frac = np.stack([wf[:, :4].sum(1) / w[:, :4].sum(1),
                         wf[:, 4:].sum(1) / w[:, 4:].sum(1)], axis=1) \
            if contacts.count else np.zeros((0, 2))
        keep_c = frac.max(1) >= CONTACT_SIDE_FULL
        hrow = np.repeat(np.arange(holds.count), np.diff(holds.indptr))
        touches = np.zeros(holds.count, bool)
        np.logical_or.at(touches, hrow, space.full[holds.indices]
                         & (holds.values != 0))
        self.keep_contact = keep_c
        self.contacts_kept = int(keep_c.sum())
        self.nonlinear_constraints = self.contacts_kept > 0
        # the kept rows among the full model's own (same order and owners)
        kind = full.constraint_kind
        keep = np.empty(len(kind), bool)
        keep[kind == "contact"] = keep_c
        keep[kind != "contact"] = touches
        a = full.constraints
        kept = np.flatnonzero(keep[a.start:a.start + a.nlocal])
        self.kept_rows = (3 * kept[:, None] + np.arange(3)).ravel()
        # world holds in α only: independent rows (rank 0)
        pure = holds.select(~touches)
        wi, wj, wv = space.csr(np.repeat(np.arange(pure.count), np.diff(pure.indptr)),
                               pure.indices, pure.values, pure.count)
        dense = sp.csr_matrix((wv, wj, wi), shape=(pure.count, max(space.ncol, 1)))
        acols = space.volcol[space.alpha]
        c_w, d_w = independent_rows(dense[:, acols].toarray(), pure.rhs)
        self.world_rank, self.world_rows = len(c_w), pure.count
        comm = self.comm
        if comm.rank:
            c_w, d_w = c_w[:0], d_w[:0]
        nz = np.abs(c_w) > 0
        world = kron_identity(np.concatenate([[0], np.cumsum(nz.sum(1))]),
                              acols[np.nonzero(nz)[1]], c_w[nz])
        self.d_world = d_w.ravel()
        # C_mix: the product's kept rows, then the world rows
        self.eps0 = self.Gamma.createVecLeft()
        self.product = full.C.matMult(self.Gamma)
        indptr, cols, _ = self.product.getValuesCSR()
        length = np.diff(indptr)[self.kept_rows]
        self.take = (np.repeat(indptr[self.kept_rows] - np.concatenate(
            [[0], np.cumsum(length)[:-1]]), length) + np.arange(length.sum()))
        self.C_indptr = np.concatenate([[0], np.cumsum(length),
                                        length.sum() + world[0][1:]]).astype(
                                            PETSc.IntType)
        self.C_indices = np.concatenate([cols[self.take], world[1]]).astype(
            PETSc.IntType)
        self.world_values = world[2]
        k = len(self.kept_rows) + len(self.d_world)
        K = comm.tompi4py().allreduce(k)
        n, N = 3 * space.ncol_local, 3 * space.ncol
        self.C = create_aij(comm, (k, K), (n, N), (self.C_indptr, self.C_indices,
                                                  self._values()), bsize=3)
        self.mu_full = full.C.createVecLeft()
        self.g_full = full.C.createVecLeft()
        self.Cq = self.C.createVecLeft()

    def _values(self):
        """C_mix's values from the product S C Γ_mix (last formed) and c_w."""
        return np.concatenate([self.product.getValuesCSR()[2][self.take],
                               self.world_values])

    def constraint_jacobian(self, q):
        """C_mix(q) = [S C(Γ_mix q) Γ_mix; c_w] (collective), in place."""
        if self.nonlinear_constraints:
            self.full.constraint_jacobian(self.full_state(q, self.eps0))
            self.full.C.matMult(self.Gamma, self.product)
            self.C.setValuesCSR(self.C_indptr, self.C_indices, self._values())
            self.C.assemble()
        return self.C

    def constraint_residual(self, q, g):
        """g_mix(q) = [S g(Γ_mix q); c_w α − d_w] into g (collective)."""
        self.full.constraint_residual(self.full_state(q, self.eps0), self.g_full)
        self.C.mult(q, self.Cq)
        out, nk = g.getArray(), len(self.kept_rows)
        out[:nk] = self.g_full.getArray(readonly=True)[self.kept_rows]
        out[nk:] = self.Cq.getArray(readonly=True)[nk:] - self.d_world

    # -- sampling ------------------------------------------------------------
    def _sample(self, rule):
        """Split the rank's elements into T (touching a full point) and V (all
        four embedded), sample V by ``rule``, and set up T's kernels, T's
        tangent pattern (with the kept contacts), and the gather of α."""
        from mpi4py import MPI

        full, space, emb = self.full, self.space, self.reduced
        el, comm = full.elements, self.comm.tompi4py()
        self.rule = rule
        inner = ~space.full[full.conn].any(axis=1)
        volume_part, touching = np.flatnonzero(inner), np.flatnonzero(~inner)
        elements, weights, report = rule(full, emb, volume_part)
        self.sampled = (SampledElements(full, emb, elements, weights)
                        if len(elements) else None)
        self.touch = YarnElements(el.X, el.conn[touching], el.rho, el.EA, el.EI,
                                  nq=len(el.weights), natural=el.natural)
        self.touch.delta = el.delta
        self.touch_kernels = yarn_kernels(self.touch, full.kernels.kind)
        # K_T's pattern: T's elements and the kept contacts reaching our rows
        lay, asm = self.layout, full.constraints
        reach = asm.element_cols()
        kept = self.keep_contact[asm.touching]
        pattern = ElementPattern([full.conn[touching], reach[kept]], lay.cp_start,
                                 lay.ncp_local)
        indptr3, indices3, (slot_t, slot_c) = pattern.blocks3(diagonal=(1,))
        self.t_csr = (indptr3.astype(PETSc.IntType), indices3.astype(PETSc.IntType))
        self.t_slot = np.ascontiguousarray(slot_t, dtype=np.int64)
        self.t_values = np.zeros(len(indices3), dtype=PETSc.ScalarType)
        slots = np.full((len(reach), 3, 8, 8), -1, dtype=np.int64)
        slots[kept] = slot_c
        self.t_curvature = asm.curvature_operator(slots, len(indices3))
        self.Kt = self.Kp = None
        # every α on every rank (S's points reach any volume point)
        NV = space.volume.size
        self.acomp = (3 * space.volcol[space.alpha][:, None] + np.arange(3)).ravel()
        self.alpha_seq = PETSc.Vec().createSeq(len(self.acomp), comm=PETSc.COMM_SELF)
        q = self.M.createVecRight()
        self.gather = PETSc.Scatter().create(
            q, PETSc.IS().createGeneral(self.acomp.astype(PETSc.IntType),
                                        comm=PETSc.COMM_SELF), self.alpha_seq, None)
        q.destroy()
        self.alpha_np = space.volume.flat.copy()
        a0 = space.col_start
        self.alpha_mine = np.flatnonzero((space.volcol >= a0)
                                         & (space.volcol < a0 + space.na_local))
        self.R = np.zeros((3 * NV, 3 * NV))
        self.r_rows = (3 * self.alpha_mine[:, None] + np.arange(3)).ravel()
        self.r_cols = (3 * space.alpha[:, None] + np.arange(3)).ravel()
        self.sampling = dict(over_ranks(self.comm, report), kind="sampled",
                             tol=getattr(rule, "tol", None),
                             exact=comm.allreduce(len(touching)))
        cached = comm.allreduce(bool(report.get("cached", False)), op=MPI.LAND)
        self.sampling["source"] = (f"{'cached' if cached else 'trained'} "
                                   f"{report.get('cache', '')}; "
                                   f"{self.sampling['exact']} border elements exact")

    def _alpha_all(self, q):
        """Every volume point's α on this rank, (nvolume, 3); volume points
        that are no unknowns keep their rest place (S gives them no weight)."""
        self.gather.scatter(q, self.alpha_seq)
        self.alpha_np[self.space.alpha] = \
            self.alpha_seq.getArray(readonly=True).reshape(-1, 3)
        return self.alpha_np

    def elastic_energy(self, q):
        """E(Γ_mix q), or, sampled, E_T(Γ_mix q) + Σ_{e∈S} ξ_e E_e(Γ_e α): the
        energy this model's forces derive from (collective)."""
        if self.sampled is None and self.rule is None:
            return super().elastic_energy(q)
        P = self.full_state(q, self.eps).getArray(readonly=True).reshape(-1, 3)
        e = self.touch.energy(P)
        alpha = self._alpha_all(q)
        if self.sampled is not None:
            e += self.sampled.energy(alpha)
        return self.comm.tompi4py().allreduce(e)

    # -- state ---------------------------------------------------------------
    def rest_state(self, turned=False):
        """q at rest: the kept volume control points and the full points' X;
        turned as the fabric starts (``start_state``) with ``turned``."""
        q = self.M.createVecRight()
        turn = self.fabric.turn if turned else (lambda p: p)
        q.getArray()[:] = self.space.state(turn(self.fabric.X),
                                           turn(self.space.volume.flat))
        return q

    # -- mechanics -----------------------------------------------------------
    def forces(self, q, qdot, Q):
        """Γ_mixᵀ Q(Γ_mix q, Γ_mix q̇); sampled, its elastic part is T's
        through Γ_mixᵀ plus −Σ_{e∈S} ξ_e Γ_eᵀ ∇E_e on the rows of α."""
        G = self.space.Gamma
        G.mult(q, self.eps)
        G.mult(qdot, self.epsdot)
        if self.rule is None:
            self.full.forces(self.eps, self.epsdot, self.Qfull)
            G.multTranspose(self.Qfull, Q)
            return
        with EV_FORCES:
            applied_forces(self.full, self.epsdot, self.Qfull)
            self.touch_kernels.add_gradient(
                self.eps.getArray(readonly=True).reshape(-1, 3),
                self.Qfull.getArray().reshape(-1, 3), -1.0)
            G.multTranspose(self.Qfull, Q)
            f = np.zeros((self.space.volume.size, 3))
            alpha = self._alpha_all(q)
            if self.sampled is not None:
                self.sampled.add_forces(alpha, f)
            self._summed(f)
            Q.getArray().reshape(-1, 3)[:self.space.na_local] += f[self.alpha_mine]

    def stiffness(self, q, mu=None, weight=1.0, xref=None):
        """Γ_mixᵀ (K + w Σ μ_i ∇²g_i)(Γ_mix q) Γ_mix by PtAP, the symbolic
        product reused; the kept rows' μ placed among the full model's;
        ``xref`` the MIP reference state (``FullModel.stiffness``)."""
        if mu is not None:
            self.mu_full.zeroEntries()
            self.mu_full.getArray()[self.kept_rows] = \
                mu.getArray(readonly=True)[:len(self.kept_rows)]
            mu = self.mu_full
        ref = None if xref is None else self.full_state(xref, self.eps_ref)
        if self.rule is not None:
            return self._sampled_stiffness(q, mu, weight, ref, xref)
        K = self.full.stiffness(self.full_state(q, self.eps), mu, weight, ref)
        with EV_PTAP:
            if self.K is None:
                self.K = K.PtAP(self.space.Gamma)
                self.K.setBlockSize(3)
            else:
                K.PtAP(self.space.Gamma, self.K)
        return self.K

    def _sampled_stiffness(self, q, mu, weight, ref, xref):
        """Γ_mixᵀ K_T Γ_mix (PtAP, T's elements and the kept contacts'
        curvature w Σ μ_i ∇²g_i) plus the sampled α–α block Σ_{e∈S} ξ_e Γ_eᵀ
        ∇²E_e Γ_e (dense, summed over the ranks), in one matrix of fixed
        pattern."""
        x = self.full_state(q, self.eps).getArray(readonly=True).reshape(-1, 3)
        xr = None if ref is None else ref.getArray(readonly=True).reshape(-1, 3)
        with EV_TANGENT:
            self.touch_kernels.hessian_values(x, self.t_slot, self.t_values, xr)
            if mu is not None and weight:
                asm = self.full.constraints
                asm.gather_mu.scatter(mu, asm.mu)
                self.t_curvature.add(asm.mu.getArray(readonly=True), weight,
                                     self.t_values)
        with EV_PTAP:
            if self.Kt is None:
                n, N = 3 * self.layout.ncp_local, 3 * self.layout.ncp
                self.Kt = create_aij(self.comm, (n, N), (n, N),
                                     (*self.t_csr, self.t_values), bsize=3)
                self.Kt.setOptionsPrefix("mixed_KT_")
                self.Kp = self.Kt.PtAP(self.space.Gamma)
            else:
                self.Kt.setValuesCSR(*self.t_csr, self.t_values)
                self.Kt.assemble()
                self.Kt.PtAP(self.space.Gamma, self.Kp)
            self.R.fill(0.0)
            if self.sampled is not None:
                aref = None if xref is None else self._alpha_all(xref).copy()
                self.sampled.tangent(self._alpha_all(q), self.R, aref)
            self._summed(self.R)
            indptr, indices, kp = self.Kp.getValuesCSR()
            if self.K is None:
                self._union_pattern(indptr, indices)
            values = self.K_values
            values.fill(0.0)
            values[self.kp_slot] = kp
            values[self.r_slot] += self.R[np.ix_(self.r_rows, self.r_cols)].ravel()
            if self.comm.size > 1 or self.K_shared is False:
                self.K.setValuesCSR(*self.K_csr, values)
            self.K.assemble()                  # a new state: factorisations redo
        return self.K

    def _union_pattern(self, indptr, indices):
        """K's pattern: Γ_mixᵀ K_T Γ_mix's (local rows) and the dense α–α block
        (the rank's α rows × every α column); where each one's values go."""
        nrow, N = len(indptr) - 1, 3 * self.space.ncol
        rows = np.repeat(np.arange(nrow, dtype=np.int64), np.diff(indptr))
        kp_keys = rows * N + indices
        na3 = 3 * self.space.na_local
        r_keys = (np.arange(na3, dtype=np.int64)[:, None] * N
                  + self.acomp[None, :]).ravel()
        keys = np.union1d(kp_keys, r_keys)
        self.kp_slot = np.searchsorted(keys, kp_keys)
        self.r_slot = np.searchsorted(keys, r_keys)
        r, c = np.divmod(keys, N)
        self.K_csr = (np.searchsorted(r, np.arange(nrow + 1)).astype(PETSc.IntType),
                      c.astype(PETSc.IntType))
        self.K_values = np.zeros(len(keys), dtype=PETSc.ScalarType)
        n = 3 * self.space.ncol_local
        if self.comm.size > 1:
            self.K = create_aij(self.comm, (n, N), (n, N),
                                (*self.K_csr, self.K_values), bsize=3)
            self.K_shared = False
        else:
            self.K = PETSc.Mat().createAIJWithArrays(
                (N, N), (*self.K_csr, self.K_values), comm=self.comm)
            self.K.setBlockSize(3)
            self.K.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
            self.K_shared = True
        self.K.setOptionsPrefix("mixed_K_")

    def destroy(self):
        for A in (self.M, self.m, self.C, self.Qg, self.K, self.eps, self.eps_ref, self.epsdot,
                  self.Qfull, self._proj, self.eps0, self.product, self.mu_full,
                  self.g_full, self.Cq, self.dq, self.deps):
            if A is not None:
                A.destroy()
        if self.rule is not None:
            for A in (self.Kt, self.Kp, self.gather, self.alpha_seq):
                if A is not None:
                    A.destroy()


# -- regions -------------------------------------------------------------------
def stitch_mask(fabric, regions):
    """Control points of the stitches in ``regions`` [(c0, c1, r0, r1), …]
    (half-open stitch and course ranges): control point i of a yarn of n_f
    lies in stitch min(max(i − 1, 0) // 8, its stitches − 1), the stitch its
    parameter s = i − 1 falls in ((i − 1) mod n_f // 8 on a closed yarn), and
    in the course it knits (``Fabric.course``)."""
    f = fabric.yarn_of
    ncp, closed = fabric.yarn_ncp[f], fabric.closed[f]
    s = np.arange(fabric.npoints) - fabric.yarn_start[f] - 1
    s = np.where(closed, np.mod(s, ncp), np.maximum(s, 0))
    stitch = np.minimum(s // SEGMENTS_PER_STITCH, yarn_stitches(fabric)[f] - 1)
    course = fabric.course
    mask = np.zeros(fabric.npoints, bool)
    for c0, c1, r0, r1 in regions:
        mask |= (course >= r0) & (course < r1) & (stitch >= c0) & (stitch < c1)
    return mask


def yarn_stitches(fabric):
    """Stitches (nyarn,) of each yarn (one for a yarn shorter than a stitch)."""
    return np.maximum(fabric.yarn_nseg // SEGMENTS_PER_STITCH, 1)


def parse_regions(text, where, nc, nr):
    """Regions "c0:c1,r0:r1" (one per line or ';'-separated) as tuples,
    checked against nc stitches and nr courses."""
    regions = []
    for item in text.replace(";", "\n").splitlines():
        item = item.split("#")[0].strip()
        if not item:
            continue
        try:
            (c0, c1), (r0, r1) = (tuple(int(v) for v in part.split(":"))
                                  for part in item.split(","))
        except ValueError:
            raise KnitError(f"{where}: {item!r} is not a region c0:c1,r0:r1 "
                            "(half-open stitch and course ranges)") from None
        if not (0 <= c0 < c1 <= nc and 0 <= r0 < r1 <= nr):
            raise KnitError(f"{where}: region {item!r} is empty or outside the "
                            f"fabric's {nc} stitches x {nr} courses")
        regions.append((c0, c1, r0, r1))
    return regions


def region_options(opts):
    """(region, file) from -knit_full_region and -knit_full_regions FILE."""
    one = opts.getString("full_region", "", "yarn-level region of the mixed model: "
                         "stitches c0:c1, courses r0:r1 (half-open), as c0:c1,r0:r1")
    path = opts.getString("full_regions", "", "file of yarn-level regions, one "
                          "c0:c1,r0:r1 a line ('#' comments)")
    return one, path


def regions_from_options(opts, fabric):
    """The full regions of -knit_full_region and -knit_full_regions FILE."""
    one, path = region_options(opts)
    nc, nr = int(yarn_stitches(fabric).max()), int(fabric.course.max()) + 1
    regions = parse_regions(one, "-knit_full_region", nc, nr)
    if path:
        try:
            with open(path) as f:
                text = f.read()
        except OSError as err:
            raise KnitError(f"-knit_full_regions {path}: {err.strerror}") from None
        regions += parse_regions(text, f"-knit_full_regions {path}", nc, nr)
    return regions


def mixed_from_options(opts, full, embedding):
    """The mixed model of a full model, its regions from options, its volume
    that of the reduced model's ``embedding`` (-knit_lod, -knit_volume), its
    volume part sampled when -knit_sampling sampled asks for it (and there
    are no bodies). Not by default: on the pulled 15×30 in a 13×8 volume the
    sampled set reached its cap (639 of 2 894 embedded elements, force error
    0.017), a Newton iteration cost 108 ms against 133, and the pulled corner
    dropped 10 % further in 0.02 s."""
    kind, tol = sampling_options(opts, default="exact")
    if kind == "quadrature":
        raise KnitError("-knit_sampling quadrature is the reduced model's only: "
                        "use -knit_sampling sampled or exact with -knit_model mixed")
    rule = trained(tol) if kind == "sampled" and not full.fabric.bodies else None
    weights = VolumeWeights(full.fabric, embedding.volume)
    mask = stitch_mask(full.fabric, regions_from_options(opts, full.fabric))
    mask = weights.patch_mask(weights.patches_of(mask))
    return MixedModel(full, MixedSpace(full.comm, full.layout, weights, mask),
                      embedding, rule)
