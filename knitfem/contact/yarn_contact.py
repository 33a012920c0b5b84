"""Yarn–yarn contact: a barrier keeps every two pieces of yarn surface apart.

Each yarn's centreline is sampled ``samples`` times a B-spline segment,
x_j = Σ_a b_a(u_j) p_{k_j + a}, so the samples are x = S ε with a constant
sparse S (and D = S ⊗ I₃ on interleaved coordinates); consecutive samples of
a yarn make the edges of a polyline. With d_ij the distance of two edges
(segment–segment: edge–edge, edge–vertex or vertex–vertex, whichever is
closest), the energy is the IPC barrier (Li et al., SIGGRAPH 2020) of the
IPC Toolkit (``ipctk``) on squared distances with a thickness dmin = 2r:

    E_y = κ Σ_(i,j) b(d_ij² − dmin², 2 dmin d̂ + d̂²),
    b(x, x̂) = −(x − x̂)² ln(x / x̂) for 0 < x < x̂, 0 beyond,

which acts only where the clearance d − 2r is below d̂ and grows without
bound as two yarn surfaces touch. Its gradient and Hessian in ε are
Dᵀ ∇E_y and Dᵀ ∇²E_y D, each pair's 12 × 12 Hessian projected to positive
semi-definite (eigenvalues clamped) by the toolkit. Distances are rigid
invariants, so E_y is frame-indifferent. κ makes the barrier's force at
half the band, κ b'(x̂/2) 2d ≈ 4.77 κ dmin² d̂, the bending force scale
EI / r² of the yarn.

Which pairs may touch. Parts of one yarn less than ``self_reach`` × r
apart along it never do: each yarn is cut into patches of L = 2
``self_reach`` r of its rest arc, once from its first sample and once
shifted by L / 2, and two samples of one yarn are kept apart only when
they lie in different patches of both groupings (the toolkit's vertex
patch filters, combined in C++): pairs closer than L / 2 along the yarn are
always excluded, pairs farther than L always included (on a closed yarn,
a tube's course, the pairs less than L apart across its seam are excluded
too: the patches do not wrap round). The patches are cut by arc, not by a
count of samples: a pattern's template has segments of unequal lengths
(a 10×10 seed's rest edges 0.43–1.11 r), and runs of samples sized by the
shortest reached 30 r along its yarns, past the pairs of one loop that
touch. Near a persistent
crossing (s_a, s_b) the samples of yarn a within ``window`` of s_a and of
yarn b within ``window`` of s_b are excluded from each other (a sparse
filter; a window on a closed yarn reaches across its seam): the crossing
holds that pair at its rest separation, and a barrier there would fight the
constraint. Pairs a rest state itself holds within half the band of
touching are excluded the same way (``tight_at_rest`` edge pairs): no band
above them could vanish at rest (the templates have none; a relaxed rest
may).
The rest's gaps are read on ``Fabric.contact_X`` where the fabric has one (a
natural knit's template at its own size, when X is that template scaled to
a shorter loop: read on X, its gaps would close and a 10×10 seed at 91 % of
its loop length left out pairs it then let through, 0.93 × 2r).
d̂ is ``band`` × r, lowered
below the smallest clearance of the remaining pairs at rest, so E_y = 0
at rest: the rest state, rigid motions of it and the reduction stay exact.

Broad phase: a Verlet list of the edge pairs within the band, a margin
and a skin (a compiled search on a grid of the edges' midpoints: 11 ms a
list on the 12×12 jersey at rest, 21 000 pairs, against 25 ms for its
numpy reference, a k-d tree and vectorised segment distances; the
toolkit's own broad phase found 57 000 box candidates on the 7×7 jersey
and took 7–18 ms a call), found again when a sample has
moved by half the skin, less the samples' common move (a knit falling or
sliding whole keeps its list). A pair's distance changes by at most the
moves of its two edges since the list was made, so only the pairs that
this bound lets near enough are measured again, and only the pairs in the
band are handed to the toolkit (none most of the time: E_y and its
derivatives are then 0 without a call). Step filter: ``step_fraction``, a conservative
bound per pair of edges on the straight path of the samples between two
states, advanced along the path (the toolkit's Tight Inclusion CCD with a
minimum distance took 0.1–0.2 s a call on the 7×7 jersey's 2 359 samples),
so a Newton update scaled by it never brings two yarn surfaces into
contact.

The tangent couples control points of different yarns. ``pairs`` lists
the segment pairs (8 control points) of the edges that may touch and are
within the band plus a margin of each other: a pattern that stays valid
while the pairs within the band and half the margin are among them
(``fits``); entries outside it are dropped from the tangent (counted in
``missed``) until the model rebuilds its pattern.

Every rank evaluates the whole set on all control points (gathered) and
keeps its own rows, so results do not depend on the number of ranks. The
toolkit runs on one thread: its parallel sums add in an order that changes
from run to run, and a path that branches (a relaxation, which has more than
one equilibrium) then ends somewhere else each time (the 8 × 8 jersey's
relaxation: k_w 4.87 to 5.62 over four runs of one command; the same to the
last digit on one thread, in the same time).
"""

import ipctk
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from knitfem.contact.segments import segment_distance
from knitfem.yarn import bspline
from knitfem.yarn.kernels import KINDS, compiled_module

__all__ = ["YarnContact", "segment_distance"]

ipctk.set_num_threads(1)
PAIRS_VERSION = 2           # of knitfem/contact/_pairs.pyx, which this module calls


def _fortran(a):
    return np.asfortranarray(a, dtype=float)


def _index(a):
    return np.ascontiguousarray(a, dtype=np.int64)


class YarnContact:
    """E_y of the yarns of ``fabric`` (module docstring) on all control
    points (ncp_total, 3), in global coordinates.

    ``EI`` sets the stiffness κ; ``samples`` a segment; ``band`` d̂ / r at
    most; ``self_reach`` and ``window`` (spline parameter) the excluded
    pairs; ``margin`` × r widens the tangent's pattern beyond the band,
    ``skin`` × r the Verlet list beyond the pattern's reach; ``kernels``
    (one of ``kernels.KINDS``) measures the edge pairs in the compiled loops
    of ``_pairs.pyx`` or by their numpy reference.
    """

    def __init__(self, fabric, EI, samples=6, band=0.08, self_reach=8.0,
                 window=0.5, margin=0.1, skin=0.4, kernels="compiled"):
        if kernels not in KINDS:
            raise ValueError(f"kernels {kernels!r}: expected one of {', '.join(KINDS)}")
        self._kernels = compiled_module("knitfem.contact._pairs", PAIRS_VERSION) \
            if kernels == "compiled" else None
        r = fabric.radius
        self.radius, self.dmin = r, 2.0 * r
        self.margin = margin * r
        self.skin = skin * r
        rows, cols, vals, edges, segment, yarn, param = ([] for _ in range(7))
        nv = nseg_total = 0
        for f in range(fabric.nyarn):           # set-up only: a few arrays a yarn
            ncp, nseg = int(fabric.yarn_ncp[f]), int(fabric.yarn_nseg[f])
            closed = bool(fabric.closed[f])
            k = np.repeat(np.arange(nseg), samples)
            u = np.tile(np.arange(samples) / samples, nseg)
            if not closed:
                k, u = np.append(k, nseg - 1), np.append(u, 1.0)
            m = len(k)
            rows.append(nv + np.repeat(np.arange(m), 4))
            cols.append((fabric.yarn_start[f] + bspline.span(k, ncp, closed)).ravel())
            vals.append(bspline.basis(u).ravel())
            j = np.arange(m if closed else m - 1)
            edges.append(nv + np.stack([j, (j + 1) % m], -1))
            segment.append(nseg_total + k[j])
            yarn.append(np.full(m, f))
            param.append(k + u)
            nv, nseg_total = nv + m, nseg_total + nseg
        cat = (lambda parts, shape: np.concatenate(parts) if parts
               else np.zeros(shape, np.int64))
        self.S = sp.csr_matrix((cat(vals, 0), (cat(rows, 0), cat(cols, 0))),
                               shape=(nv, fabric.npoints))
        self.D = sp.kron(self.S, sp.identity(3), format="csr")
        self.S_cols = cat(cols, 0).reshape(-1, 4)    # S's four entries a sample
        self.S_vals = cat(vals, 0).reshape(-1, 4)
        self.edges = cat(edges, (0, 2))
        self.edge_segment = cat(segment, 0)        # the segment of every edge
        self.nseg_total = nseg_total
        self.sample_yarn = cat(yarn, 0)
        self.sample_param = cat(param, 0).astype(float)
        first = np.searchsorted(self.sample_yarn, np.arange(fabric.nyarn))
        self.sample_index = np.arange(nv) - first[self.sample_yarn]   # along its yarn
        self.yarn_first = first
        self.yarn_samples = np.bincount(self.sample_yarn, minlength=fabric.nyarn)
        self.yarn_closed = np.asarray(fabric.closed, bool)
        V = self.S @ fabric.X.reshape(-1, 3)
        self.mesh = ipctk.CollisionMesh(_fortran(V), self.edges.astype(np.int32),
                                        np.zeros((0, 3), np.int32))
        edge = np.linalg.norm(V[self.edges[:, 1]] - V[self.edges[:, 0]], axis=1)
        if fabric.contact_X is not None:     # the rest's gaps read elsewhere
            V = self.S @ np.asarray(fabric.contact_X).reshape(-1, 3)
        self.patch = 2.0 * self_reach * r
        self.arc, self.perimeter = self._rest_arc(edge)
        self.edge_max = edge.max(initial=0.0)
        self._patch_ids = self._patches()
        self.excluded = self._excluded(fabric, window)
        self.mesh.can_collide = self._filter()
        # pairs the rest itself brings within half the band are left out:
        # no band above them vanishes
        e, f = self.close_edges(V, self.dmin + 0.5 * band * r)
        self.tight_at_rest = len(e)
        if len(e):
            a, b = self.edges[e], self.edges[f]
            self.excluded = np.union1d(self.excluded, self._keys(
                np.repeat(a, 2, axis=1).ravel(), np.tile(b, 2).ravel()))
            self.mesh.can_collide = self._filter()
        self.collisions, self.built, self.active = ipctk.NormalCollisions(), None, None
        self.candidates_at, self.moved_at, self.candidate_builds = None, None, 0
        clearance = self._clearance(V, band * r)
        self.dhat = min(band * r, 0.9 * clearance)
        self.kappa = EI / r**2 / (4.77 * self.dmin**2 * self.dhat)
        self.potential = ipctk.BarrierPotential(self.dhat, self.kappa)
        self.pairs = self.segment_pairs(fabric.X.reshape(-1, 3), self.margin)
        self.missed, self._DT = 0, None

    def _rest_arc(self, edge):
        """Arc length along its yarn of every sample at rest (from the
        yarn's first sample) and the perimeter of its yarn (closed yarns;
        inf on an open one), from the rest lengths ``edge`` of the edges."""
        e0 = self.edges[:, 0]
        arc = np.zeros(len(self.sample_yarn))
        perimeter = np.full(len(self.yarn_first), np.inf)
        for f, (first, m) in enumerate(zip(self.yarn_first, self.yarn_samples)):
            mine = (e0 >= first) & (e0 < first + m)      # the yarn's edges, in order
            run = np.cumsum(edge[mine])
            arc[first + 1:first + m] = run[:m - 1]
            if self.yarn_closed[f]:
                perimeter[f] = run[-1]
        return arc, perimeter[self.sample_yarn]

    def _patches(self):
        """Patch numbers (two groupings) of every sample: its yarn's patches
        of L of rest arc, the second grouping shifted by L / 2 (module
        docstring), numbered apart from every other yarn's."""
        per_yarn = int(np.ceil(np.max(self.arc, initial=0.0) / self.patch)) + 2
        base = self.sample_yarn * per_yarn
        return [base + np.floor(self.arc / self.patch + shift).astype(np.int64)
                for shift in (0.0, 0.5)]

    def _filter(self):
        """The toolkit's filter of the sample pairs that may touch: not
        those along a yarn (patches of L, in two groupings) nor the
        ``excluded`` ones."""
        runs = [ipctk.make_vertex_patches_filter(p.astype(np.int32))
                for p in self._patch_ids]
        lo, hi = np.divmod(self.excluded, len(self.sample_yarn))
        near = dict.fromkeys(zip(lo.tolist(), hi.tolist()), False)
        return runs[0] & runs[1] & ipctk.make_sparse_filter(near, True)

    def _keys(self, a, b):
        """Sorted unique keys min · nsamples + max of sample pairs (a, b),
        int64 (the compiled filter reads them as they are)."""
        a, b = _index(a), _index(b)
        return np.unique(np.minimum(a, b) * len(self.sample_yarn) + np.maximum(a, b))

    def _excluded(self, fabric, window):
        """Keys (``_keys``) of the sample pairs near a crossing, and along a
        closed yarn across its seam (``_seam_pairs``)."""
        ya, sa, yb, sb = fabric.contacts
        # samples sorted by (yarn, parameter): a crossing's window on a yarn,
        # |param − s| < window, is one run of them, found by bisection
        span = self.sample_param.max(initial=0.0) + 2 * window + 1.0
        key = self.sample_yarn * span + self.sample_param

        def run(yarn, s):
            centre = np.asarray(yarn) * span + np.asarray(s)
            return (np.searchsorted(key, centre - window, side="right"),
                    np.searchsorted(key, centre + window, side="left"))

        # on a closed yarn a window reaches across its seam: the crossing is
        # taken again a whole yarn (nseg) before and after, on either side
        ya, yb = np.asarray(ya), np.asarray(yb)
        turn_a = np.where(fabric.closed[ya], fabric.yarn_nseg[ya], 0)
        turn_b = np.where(fabric.closed[yb], fabric.yarn_nseg[yb], 0)
        shift = np.array([-1, 0, 1])
        n = len(ya)
        sa = np.broadcast_to(np.asarray(sa)[:, None, None] + shift[:, None]
                             * turn_a[:, None, None], (n, 3, 3)).ravel()
        sb = np.broadcast_to(np.asarray(sb)[:, None, None] + shift
                             * turn_b[:, None, None], (n, 3, 3)).ravel()
        ya, yb = np.repeat(ya, 9), np.repeat(yb, 9)
        (a0, a1), (b0, b1) = run(ya, sa), run(yb, sb)
        na, nb = np.maximum(a1 - a0, 0), np.maximum(b1 - b0, 0)
        c = np.repeat(np.arange(len(na)), na * nb)        # every (a, b) pair
        k = np.arange(len(c)) - np.repeat(np.cumsum(na * nb) - na * nb, na * nb)
        a, b = a0[c] + k // nb[c], b0[c] + k % nb[c]
        seam_a, seam_b = self._seam_pairs()
        return self._keys(np.append(a, seam_a), np.append(b, seam_b))

    def _seam_pairs(self):
        """Sample pairs (a, b) of a closed yarn less than L apart along it
        across its seam (the patches of ``_filter`` do not wrap round)."""
        a, b = [], []
        for start, m in zip(self.yarn_first[self.yarn_closed],
                            self.yarn_samples[self.yarn_closed]):
            arc, per = self.arc[start:start + m], self.perimeter[start]
            head = np.flatnonzero(arc < self.patch)
            tail = np.flatnonzero(arc > per - self.patch)
            i, j = np.repeat(head, len(tail)), np.tile(tail, len(head))
            keep = (i < j) & (arc[i] + per - arc[j] < self.patch)
            a.append(start + i[keep])
            b.append(start + j[keep])
        cat = (lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64))
        return cat(a), cat(b)

    def _clearance(self, V, probe):
        """Smallest d − dmin of the pairs that may touch at the samples V,
        looked for within ``probe`` (probe when none is closer)."""
        col = ipctk.NormalCollisions()
        col.build(self.mesh, _fortran(V), probe, self.dmin)
        if col.empty():
            return probe
        return np.sqrt(col.compute_minimum_distance(self.mesh, _fortran(V))) \
            - self.dmin

    def samples(self, P):
        """Sample points x = S ε (nsamples, 3) of all control points P."""
        return self.S @ np.asarray(P).reshape(-1, 3)

    def _near(self, V, within):
        """The candidate edge pairs (e, f) (``_candidates``) closer than
        ``within`` at the samples V, and their distances d. Only the pairs
        whose distance where the candidates were found, less the largest
        moves of their two edges since, is below ``within`` are measured
        again (a pair's distance changes by at most those moves)."""
        if self.moved_at is None or not np.array_equal(self.moved_at, V):
            self._candidates(V)
        e, f, d0 = self.candidate_edges
        maybe = d0 - self.edge_moved[e] - self.edge_moved[f] < within
        e, f = e[maybe], f[maybe]
        d = self.edge_distances(V, e, f)
        near = d < within
        return e[near], f[near], d[near]

    def _build(self, V):
        """The toolkit's collisions of the pairs within the band at the
        samples V (kept for the next call at the same V: forces and tangent
        are taken at the same state): only the candidates closer than
        dmin + d̂ are handed to it (pairs farther apart add nothing); None
        when there are none, so that E_y, its gradient and Hessian are
        exactly 0."""
        if self.built is None or not np.array_equal(self.built, V):
            e, f, _ = self._near(V, (self.dmin + self.dhat) * (1.0 + 1e-9))
            order = np.argsort(e * len(self.edges) + f)  # not the list's order:
            e, f = e[order], f[order]                    # the same sums on restart
            self.active = None
            if len(e):
                cand = ipctk.Candidates()
                cand.ee_candidates = [ipctk.EdgeEdgeCandidate(a, b) for a, b
                                      in zip(e.tolist(), f.tolist())]
                self.collisions.build(cand, self.mesh, V, self.dhat, self.dmin)
                self.active = None if self.collisions.empty() else self.collisions
            self.built = V.copy()
        return self.active

    def _candidates(self, V):
        """Keep ``candidate_edges``, the edge pairs (e, f) within dmin + d̂ +
        margin + skin of the samples where they were last found and their
        distances there, for the samples V: found again at V when a sample
        has moved more than skin / 2 since, so that every pair within the
        band and the margin at V is among them (a Verlet list; two edges
        close in by at most twice the largest move, less the samples' common
        move: ``_moves``); and ``edge_moved``, each edge's largest move
        since."""
        dv = None if self.candidates_at is None else \
            np.sqrt(np.sum(self._moves(V) ** 2, axis=1))
        if dv is None or dv.max() > 0.5 * self.skin:
            self._make_list(V)
            self.candidate_builds += 1
            dv = np.zeros(len(V))
        self.edge_moved = np.maximum(dv[self.edges[:, 0]], dv[self.edges[:, 1]])
        self.moved_at = V.copy()

    def _moves(self, V):
        """The samples' moves since the Verlet list was made, less their
        common part c (the centre of their bounding box): two points move
        apart by |u_a − u_b| ≤ |u_a − c| + |u_b − c| for any c, so the list's
        bounds hold on these, and a knit that falls or slides whole keeps
        its list."""
        u = V - self.candidates_at
        return u - 0.5 * (u.max(axis=0) + u.min(axis=0))

    def _make_list(self, V):
        """The Verlet list (``_candidates``) made at the samples V."""
        self.candidate_edges = self.close_edges(
            V, self.dmin + self.dhat + self.margin + self.skin, distances=True)
        self.candidates_at, self.moved_at = V.copy(), None

    def energy(self, P):
        """E_y at all control points P (ncp_total, 3)."""
        V = _fortran(self.samples(P))
        col = self._build(V)
        return 0.0 if col is None else float(self.potential(col, self.mesh, V))

    def gradient(self, P):
        """∂E_y/∂ε (3 ncp_total,), interleaved."""
        V = _fortran(self.samples(P))
        col = self._build(V)
        if col is None:
            return np.zeros(self.D.shape[1])
        return self.D.T @ self.potential.gradient(col, self.mesh, V)

    def hessian(self, P, project=True, rows=None):
        """∂²E_y/∂ε² = Dᵀ ∇²E_y D (scipy CSR, 3 ncp_total square, or its
        rows of control points ``rows`` = (lo, hi) only), each pair's 12 × 12
        block of ∇²E_y projected to positive semi-definite unless
        ``project`` is False (sparse products: the samples' 3 × 3 blocks go,
        weighted, to the 4 × 4 control points of S's rows)."""
        lo, hi = rows or (0, self.S.shape[1])
        n = self.D.shape[1]
        V = _fortran(self.samples(P))
        col = self._build(V)
        if col is None:
            return sp.csr_matrix((3 * (hi - lo), n))
        how = ipctk.PSDProjectionMethod.CLAMP if project else \
            ipctk.PSDProjectionMethod.NONE
        H = self.potential.hessian(col, self.mesh, V, how).tocsr()
        if self._DT is None or self._DT[0] != (lo, hi):
            self._DT = (lo, hi), self.D.T.tocsr()[3 * lo:3 * hi]
        return self._DT[1] @ H @ self.D

    def min_distance(self, P, reach=None):
        """Smallest distance of two edges that may touch, among those closer
        than dmin + ``reach`` (default d̂ + margin; inf when none is): from
        the Verlet list (``_near``) within its reach, else a search of its own
        (``close_edges``)."""
        V = self.samples(P)
        reach = self.dhat + self.margin if reach is None else reach
        if reach <= self.dhat + self.margin:
            d = self._near(V, self.dmin + reach)[2]
        else:
            d = self.close_edges(V, self.dmin + reach, distances=True)[2]
        return float(d.min()) if len(d) else np.inf

    def step_fraction(self, P0, P1, keep=0.1, rounds=6):
        """The largest t ≤ 1 (found conservatively) for which the straight
        path from P0 towards P1 keeps every two yarn surfaces apart by
        ``keep`` of their clearance at P0 at least.

        The points of edges e and f move relative to each other by convex
        combinations of their samples' relative moves, so by at most
        δ_ef = max_(i∈e, j∈f) |Δx_i − Δx_j| ≤ δ_e + δ_f along the whole path
        (δ_e the largest move of e's samples less the mean move: a rigid
        translation is never cut): a pair at distance d(t) on the path stays
        above g = dmin + keep (d(0) − dmin) until at least
        t + (d(t) − g) / δ_ef. Starting from 0, each pair's t is advanced so,
        ``rounds`` times (additive conservative advancement, Li et al.,
        SIGGRAPH 2021: a pair sliding past another reaches 1 in a round or
        two, one closing in stops short of where it would reach g).

        Only the pairs with δ_e + δ_f > (1 − keep)(d − dmin) can stop
        short of 1: candidates of the Verlet list (``_near``), and pairs
        beyond it, whose clearance at P0 is at least d̂ + margin + skin
        less the moves m_e + m_f of their edges since the list was made, so
        that s_e + s_f > (1 − keep)(d̂ + margin + skin) with
        s_e = δ_e + (1 − keep) m_e: the pairs of an edge with s_e above half
        that (a k-d tree around those alone). Those are looked for on the
        part [0, t] of the path the candidates allow, where they move by t δ
        (a large predicted move, cut short by a near pair, does not search
        the whole swatch)."""
        V0 = _fortran(self.samples(P0))
        dV = self.samples(P1) - V0
        dV -= dV.mean(axis=0)
        dv = np.sqrt(np.sum(dV * dV, axis=1))
        de = np.maximum(dv[self.edges[:, 0]], dv[self.edges[:, 1]])
        reach = 2.0 * de.max(initial=0.0) / (1.0 - keep)
        e, f, d = self._near(V0, self.dmin + reach)
        t = self._advance(V0, dV, de, e, f, d, keep, rounds)
        # beyond the list: only the path up to t, whose moves are t δ_e
        fast = np.flatnonzero(t * de + (1.0 - keep) * self.edge_moved > 0.5 * (1.0 - keep)
                              * (self.dhat + self.margin + self.skin))
        if t > 0.0 and len(fast):
            g, h, dg = self.edges_near(V0, fast, t * de / (1.0 - keep))
            may = self.edges_may_touch(g, h)
            t = min(t, self._advance(V0, dV, de, g[may], h[may], dg[may], keep, rounds))
        return t

    def _advance(self, V0, dV, de, e, f, d, keep, rounds):
        """``step_fraction``'s conservative advancement on the edge pairs
        (e, f) at distances d at the samples V0, moving by dV."""
        may = de[e] + de[f] > (1.0 - keep) * (d - self.dmin)
        if not may.any():
            return 1.0
        if self._kernels is not None:
            return self._kernels.advance(V0, dV, self.edges, _index(e[may]), _index(f[may]),
                                         np.ascontiguousarray(d[may]), self.dmin, keep, rounds)
        a, b, d = self.edges[e[may]], self.edges[f[may]], d[may]
        rel = np.max([np.linalg.norm(dV[a[:, p]] - dV[b[:, q]], axis=1)
                      for p in range(2) for q in range(2)], axis=0)
        low = self.dmin + keep * (d - self.dmin)
        t = np.zeros(len(d))
        for _ in range(rounds):
            t = np.minimum(t + (d - low) / np.maximum(rel, 1e-300), 1.0)
            go = np.flatnonzero(t < 1.0)
            if not len(go):
                return 1.0
            a, b, d, rel, low, t = a[go], b[go], d[go], rel[go], low[go], t[go]
            x = [V0[a[:, k]] + t[:, None] * dV[a[:, k]] for k in range(2)]
            y = [V0[b[:, k]] + t[:, None] * dV[b[:, k]] for k in range(2)]
            d = segment_distance(x[0], x[1], y[0], y[1])
        return float(np.clip(t.min(), 0.0, 1.0))

    def edges_near(self, V, some, slack):
        """Pairs (e, f) of an edge e of ``some`` and any edge f not of its
        neighbourhood along the yarn (``close_edges``' first filter) closer
        than dmin + slack_e + slack_f at the samples V (``slack`` per edge),
        and their distances: a k-d tree of the edges' midpoints, the pairs
        it finds first thinned by the distance bound |m_e − m_f| less the
        half lengths, then measured."""
        e0, e1 = self.edges[:, 0], self.edges[:, 1]
        mid, half = 0.5 * (V[e0] + V[e1]), 0.5 * self.edge_lengths(V)
        close = cKDTree(mid[some]).sparse_distance_matrix(
            cKDTree(mid), self.dmin + slack[some].max() + slack.max() + 2 * half.max(),
            output_type="ndarray")
        e, f = some[close["i"]], close["j"]
        within = self.dmin + slack[e] + slack[f]
        keep = self._apart(e, f) & (close["v"] - half[e] - half[f] < within)
        e, f, within = e[keep], f[keep], within[keep]
        d = self.edge_distances(V, e, f)
        near = d < within
        return e[near], f[near], d[near]

    def _apart(self, e, f):
        """Edge pairs on different yarns, or on one yarn whose first samples
        are at least L / 2 less the longest rest edge apart along it (a
        cheap first filter: nearer pairs never touch)."""
        e0 = self.edges[:, 0]
        a, b = e0[e], e0[f]
        gap = np.abs(self.arc[a] - self.arc[b])
        gap = np.minimum(gap, self.perimeter[a] - gap)
        return (self.sample_yarn[a] != self.sample_yarn[b]) | \
            (gap >= 0.5 * self.patch - self.edge_max)

    def edge_lengths(self, V):
        return np.linalg.norm(V[self.edges[:, 1]] - V[self.edges[:, 0]], axis=1)

    def samples_may_touch(self, i, j):
        """The toolkit's filter (``_filter``) on sample pairs, vectorised."""
        p0, p1 = self._patch_ids
        apart = (p0[i] != p0[j]) & (p1[i] != p1[j])
        ok = (self.sample_yarn[i] != self.sample_yarn[j]) | apart
        key = np.minimum(i, j) * len(self.sample_yarn) + np.maximum(i, j)
        at = np.minimum(np.searchsorted(self.excluded, key), len(self.excluded) - 1)
        return ok & (self.excluded[at] != key) if len(self.excluded) else ok

    def edge_distances(self, V, e, f):
        """Distances of the edge pairs (e, f) at the samples V: the compiled
        loop, or ``segment_distance``."""
        if self._kernels is not None:
            return self._kernels.edge_distances(V, self.edges, _index(e), _index(f))
        e0, e1 = self.edges[:, 0], self.edges[:, 1]
        return segment_distance(V[e0[e]], V[e1[e]], V[e0[f]], V[e1[f]])

    def edges_may_touch(self, e, f):
        """Edge pairs without a common sample, one of whose sample pairs may
        touch (as the toolkit's broad phase decides): the compiled loop, or
        its numpy reference."""
        if self._kernels is not None:
            p0, p1 = self._patch_ids
            return self._kernels.edges_may_touch(self.edges, _index(e), _index(f), p0, p1,
                                               self.sample_yarn, self.excluded)
        a, b = self.edges[e], self.edges[f]
        shared = (a[:, :, None] == b[:, None, :]).any(axis=(1, 2))
        may = np.zeros(len(e), bool)
        for p in range(2):
            for q in range(2):
                may |= self.samples_may_touch(a[:, p], b[:, q])
        return may & ~shared

    def close_edges(self, V, within, distances=False):
        """Edge pairs (e, f), e < f, that may touch and are closer than
        ``within`` at the samples V (and their distances, if ``distances``),
        sorted by (e, f): the compiled grid search (``_pairs.close_pairs``),
        or a k-d tree of the edges' midpoints."""
        if self._kernels is not None:
            e, f, d = self._kernels.close_pairs(
                V, self.edges, within, self.arc, self.perimeter, self.sample_yarn,
                0.5 * self.patch - self.edge_max)
        else:
            e0, e1 = self.edges[:, 0], self.edges[:, 1]
            mid, half = 0.5 * (V[e0] + V[e1]), 0.5 * self.edge_lengths(V)
            close = cKDTree(mid).query_pairs(within + 2 * half.max(), output_type="ndarray")
            close = close[np.argsort(close[:, 0] * len(self.edges) + close[:, 1], kind="stable")]
            e, f = close[:, 0], close[:, 1]
            apart = self._apart(e, f)
            e, f = e[apart], f[apart]
            d = self.edge_distances(V, e, f)
            near = d < within
            e, f, d = e[near], f[near], d[near]
        hit = self.edges_may_touch(e, f)
        return (e[hit], f[hit], d[hit]) if distances else (e[hit], f[hit])

    def segment_pairs(self, P, reach):
        """Keys a · nseg_total + b (a < b, global segment numbers; sorted,
        unique) of the segments of the edge pairs that may touch and are
        closer than dmin + d̂ + ``reach`` (at most the margin)."""
        e, f, _ = self._near(self.samples(P), self.dmin + self.dhat + reach)
        a, b = self.edge_segment[e], self.edge_segment[f]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return np.unique((lo * self.nseg_total + hi)[lo != hi])

    def pair_points(self, conn):
        """Control points (npairs, 8) of the segment pairs ``pairs``, from
        the global connectivity ``conn`` (nseg_total, 4)."""
        a, b = np.divmod(self.pairs, self.nseg_total)
        return np.concatenate([conn[a], conn[b]], axis=1)

    def restore(self, pairs, anchor):
        """Continue from a saved state: the tangent's segment ``pairs`` and
        the Verlet list made again at the samples ``anchor`` where it was
        made (None: at the next call), so that the step filter, which looks
        beyond the list by the moves since its anchor, cuts as it did."""
        self.pairs = np.asarray(pairs, dtype=np.int64)
        self.built = self.moved_at = self.candidates_at = None
        if anchor is not None:
            self._make_list(np.asarray(anchor, dtype=float))

    def fits(self, P):
        """Whether the segment pairs within the band and half the margin at P
        are all in ``pairs`` (the tangent's pattern still holds them)."""
        return bool(np.isin(self.segment_pairs(P, 0.5 * self.margin), self.pairs).all())

    def relayout(self, P):
        """``pairs`` taken again around P, with the whole margin."""
        self.pairs = self.segment_pairs(P, self.margin)
