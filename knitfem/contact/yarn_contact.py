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
apart along it never do: samples are grouped along each yarn in runs of W
(W / 2 samples ≥ ``self_reach`` r of rest arc), once from the first sample
and once shifted by W / 2, and two samples of one yarn are kept apart only
when they lie in different runs of both groupings (the toolkit's vertex
patch filters, combined in C++): pairs closer than W / 2 samples are
always excluded, pairs farther than W always included. Near a persistent
crossing (s_a, s_b) the samples of yarn a within ``window`` of s_a and of
yarn b within ``window`` of s_b are excluded from each other (a sparse
filter): the crossing holds that pair at its rest separation, and a
barrier there would fight the constraint. d̂ is ``band`` × r, lowered
below the smallest clearance of the remaining pairs at rest, so E_y = 0
at rest: the rest state, rigid motions of it and the reduction stay exact.

Broad phase: the toolkit's hash grid over the edges' boxes. Step filter:
``step_fraction``, a conservative bound on the straight path of the
samples between two states (the toolkit's Tight Inclusion CCD with a
minimum distance took 0.1–0.2 s a call on the 7×7 jersey's 2 359 samples,
the bound a few ms), so a Newton update scaled by it never brings two yarn
surfaces into contact.

The tangent couples control points of different yarns. ``pairs`` lists
the segment pairs (8 control points) whose samples are within the band
plus a margin of each other: a pattern that stays valid while the active
pairs are among them (``fits``); entries outside it are dropped from the
tangent (counted in ``missed``) until the model rebuilds its pattern.

Every rank evaluates the whole set on all control points (gathered) and
keeps its own rows, so results do not depend on the number of ranks.
"""

import ipctk
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from knitfem.yarn import bspline

__all__ = ["YarnContact"]


def _fortran(a):
    return np.asfortranarray(a, dtype=float)


class YarnContact:
    """E_y of the yarns of ``fabric`` (module docstring) on all control
    points (ncp_total, 3), in global coordinates.

    ``EI`` sets the stiffness κ; ``samples`` a segment; ``band`` d̂ / r at
    most; ``self_reach`` and ``window`` (spline parameter) the excluded
    pairs; ``margin`` × r widens the tangent's pattern beyond the band.
    """

    def __init__(self, fabric, EI, samples=6, band=0.08, self_reach=8.0,
                 window=0.5, margin=1.0):
        r = fabric.radius
        self.radius, self.dmin = r, 2.0 * r
        self.margin = margin * r
        nyarn, ncp, nseg = fabric.nyarn, fabric.ncp, fabric.nseg
        self.nseg, self.ncp = nseg, ncp
        k = np.repeat(np.arange(nseg), samples)
        u = np.tile(np.arange(samples) / samples, nseg)
        if not fabric.closed:
            k, u = np.append(k, nseg - 1), np.append(u, 1.0)
        m = len(k)
        cols = bspline.span(k, ncp, fabric.closed)
        first = np.arange(nyarn)[:, None, None] * ncp
        self.S = sp.csr_matrix(
            (np.tile(bspline.basis(u).ravel(), nyarn),
             (np.repeat(np.arange(nyarn * m), 4), (first + cols[None]).ravel())),
            shape=(nyarn * m, nyarn * ncp))
        self.D = sp.kron(self.S, sp.identity(3), format="csr")
        j = np.arange(m if fabric.closed else m - 1)
        ends = np.stack([j, (j + 1) % m], -1)
        self.edges = (np.arange(nyarn)[:, None, None] * m + ends[None]).reshape(-1, 2)
        # the segment of every edge, and those of the edges at each sample
        self.edge_segment = (np.arange(nyarn)[:, None] * nseg + k[j][None]).ravel()
        at = np.full((nyarn * m, 2), -1)
        at[self.edges[:, 0], 0] = at[self.edges[:, 1], 1] = np.arange(len(self.edges))
        self.sample_edges = self.edge_segment[np.where(at < 0, at[:, ::-1], at)]
        self.nseg_total = nyarn * nseg
        self.sample_yarn = np.repeat(np.arange(nyarn), m)
        self.sample_param = np.tile(k + u, nyarn)
        V = self.S @ fabric.X.reshape(-1, 3)
        self.mesh = ipctk.CollisionMesh(_fortran(V), self.edges.astype(np.int32),
                                        np.zeros((0, 3), np.int32))
        edge = np.linalg.norm(V[self.edges[:, 1]] - V[self.edges[:, 0]], axis=1)
        self.edge_length = edge.max(initial=r)
        half = max(1, int(np.ceil(self_reach * r / edge.min(initial=r))))
        self.run = 2 * half
        self.mesh.can_collide = self._filter(fabric, m, window)
        self.collisions = ipctk.NormalCollisions()
        clearance = self._clearance(V, band * r)
        self.dhat = min(band * r, 0.9 * clearance)
        self.kappa = EI / r**2 / (4.77 * self.dmin**2 * self.dhat)
        self.potential = ipctk.BarrierPotential(self.dhat, self.kappa)
        self.pairs = self.segment_pairs(fabric.X.reshape(-1, 3), self.margin)
        self.missed = 0

    def _filter(self, fabric, m, window):
        """The toolkit's filter of the sample pairs that may touch."""
        i = np.arange(len(self.sample_yarn)) % m
        base = self.sample_yarn * (m + 2)
        runs = [ipctk.make_vertex_patches_filter(
            (base + (i + shift) // self.run).astype(np.int32))
            for shift in (0, self.run // 2)]
        ya, sa, yb, sb = fabric.contacts
        near = {}
        for y1, s1, y2, s2 in zip(ya, sa, yb, sb):
            a = np.flatnonzero((self.sample_yarn == y1)
                               & (np.abs(self.sample_param - s1) < window))
            b = np.flatnonzero((self.sample_yarn == y2)
                               & (np.abs(self.sample_param - s2) < window))
            lo, hi = np.minimum.outer(a, b).ravel(), np.maximum.outer(a, b).ravel()
            near.update(dict.fromkeys(zip(lo.tolist(), hi.tolist()), False))
        return runs[0] & runs[1] & ipctk.make_sparse_filter(near, True)

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

    def _build(self, V):
        self.collisions.build(self.mesh, V, self.dhat, self.dmin)
        return self.collisions

    def energy(self, P):
        """E_y at all control points P (ncp_total, 3)."""
        V = _fortran(self.samples(P))
        return float(self.potential(self._build(V), self.mesh, V))

    def gradient(self, P):
        """∂E_y/∂ε (3 ncp_total,), interleaved."""
        V = _fortran(self.samples(P))
        return self.D.T @ self.potential.gradient(self._build(V), self.mesh, V)

    def hessian(self, P, project=True):
        """∂²E_y/∂ε² (scipy CSR, 3 ncp_total square), each pair's block
        projected to positive semi-definite unless ``project`` is False."""
        V = _fortran(self.samples(P))
        how = ipctk.PSDProjectionMethod.CLAMP if project else \
            ipctk.PSDProjectionMethod.NONE
        H = self.potential.hessian(self._build(V), self.mesh, V, how)
        return (self.D.T @ H.tocsr() @ self.D).tocsr()

    def min_distance(self, P, reach=None):
        """Smallest distance of two edges that may touch, among those closer
        than dmin + ``reach`` (default d̂ + margin; inf when none is)."""
        V = _fortran(self.samples(P))
        col = ipctk.NormalCollisions()
        col.build(self.mesh, V, reach or self.dhat + self.margin, self.dmin)
        return np.sqrt(col.compute_minimum_distance(self.mesh, V)) \
            if not col.empty() else np.inf

    def step_fraction(self, P0, P1, keep=0.1):
        """The largest t ≤ 1 for which the straight path from P0 towards P1
        keeps every two yarn surfaces apart, by a conservative bound: an
        edge's points move by at most δ = max_j |x_j(P1) − x_j(P0)|, so two
        edges at distance d come no closer than d − 2δt; pairs farther than
        dmin + 2δ cannot touch, and t = (1 − keep)(d_min − dmin) / 2δ keeps
        ``keep`` of the closest pair's clearance; pairs are looked for within
        the margin at most (a clearance beyond it counts as the margin)."""
        V0, V1 = self.samples(P0), self.samples(P1)
        move = np.sqrt(np.max(np.sum((V1 - V0) ** 2, axis=1), initial=0.0))
        if move == 0.0:
            return 1.0
        reach = min(2.0 * move, self.margin)
        gap = min(self.min_distance(P0, reach) - self.dmin, reach)
        return float(np.clip((1.0 - keep) * gap / (2.0 * move), 0.0, 1.0))

    def segment_pairs(self, P, reach):
        """Keys a · nseg_total + b (a < b, global segment numbers) of the
        segment pairs whose samples come within dmin + d̂ + an edge +
        ``reach`` of each other (sorted, unique): every pair of edges within
        dmin + d̂ + ``reach`` is among them."""
        close = cKDTree(self.samples(P)).query_pairs(
            self.dmin + self.dhat + self.edge_length + reach, output_type="ndarray")
        i, j = close[:, 0], close[:, 1]
        keep = (self.sample_yarn[i] != self.sample_yarn[j]) | \
            (np.abs(i - j) >= self.run // 2)
        a = np.repeat(self.sample_edges[i[keep]], 2, axis=1).ravel()
        b = np.tile(self.sample_edges[j[keep]], (1, 2)).ravel()
        n = self.nseg_total
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return np.unique((lo * n + hi)[lo != hi])

    def pair_points(self, conn):
        """Control points (npairs, 8) of the segment pairs ``pairs``, from
        the global connectivity ``conn`` (nseg_total, 4)."""
        a, b = np.divmod(self.pairs, self.nseg_total)
        return np.concatenate([conn[a], conn[b]], axis=1)

    def fits(self, P):
        """Whether the segment pairs within the band and half the margin at P
        are all in ``pairs`` (the tangent's pattern still holds them)."""
        return bool(np.isin(self.segment_pairs(P, 0.5 * self.margin),
                            self.pairs, assume_unique=True).all())

    def relayout(self, P):
        """``pairs`` taken again around P, with the whole margin."""
        self.pairs = self.segment_pairs(P, self.margin)
