"""The reduced model's stretch: the volume read as a shell, a stitch's yarn
length the measure.

The embedding moves every yarn point with its volume, ε = Γα, and with the
stretch of the yarn curve itself (``yarn``) the embedded knit is a plate and
a membrane of yarn stiffness: bending the volume stretches the yarn by κ z
through the thickness, and shearing or squeezing a stitch stretches its
loop's legs and heads, where the knit bends and shears by turning and
bending its loops and sliding yarn through them (which no embedding shows).
Two changes make it bend and shear like a knit and keep what it resists,
the length of yarn in a stitch:

1. The shell tangent. At Gauss point q of a yarn element whose control
   points sit at volume parameters ξ_a = (s₁, s₂, w₃)_a, the stretch is
   measured on

       t_q = ∇P(s̄_q, ½) ξ̄'_q = D_q α,   s̄_q = Σ_a b_a(u_q) (s₁, s₂)_a,
       ξ̄'_q = Σ_a b'_a(u_q) ξ_a,

   the volume's Jacobian on its mid-surface (w₃ = ½) under the point applied
   to the yarn's tangent in parameter space: the yarn in the volume read as
   a shell S(s) + (w₃ − ½) T(s), the thickness vector T taken where the
   point projects. D_q (n) is constant and acts on each component of α;
   where P is affine (the rest box) t_q is the yarn's own x'_q. An isometric
   bend of S with T normal to it and of its length leaves every |t_q| alone.

2. The stitch's strain. e_q = (|t_q|² − L_q²)/(2 L_q²), L_q = |D_q α₀|, is
   averaged over the window w of a stitch (``window`` elements of a yarn,
   ``pattern.SEGMENTS_PER_STITCH``), W_q = w_q L_q:

       ē_w = Σ_{q∈w} W_q e_q / L_w,   L_w = Σ_{q∈w} W_q,   E_s = ½ EA Σ_w L_w ē_w².

   A shear, or a squeeze that turns a loop, stretches its legs and shortens
   its heads by as much: the stitch's yarn length, and E_s, stay.

With f_q = EA L_w ē_w W_q / (L_w L_q²) and J_w = ∂ē_w/∂α = Σ_{q∈w} W_q/(L_w L_q²) D_qᵀ t_q,

    ∂E_s/∂α = Σ_q f_q D_qᵀ t_q,   ∂²E_s/∂α² = Σ_q f_q D_qᵀ D_q ⊗ I₃ + Σ_w EA L_w J_w J_wᵀ,

the first sum a patch of V at a time (the rows of D of the points over one
patch share its 32 columns). It is Σ_w c_w M_w, c_w = EA L_w ē_w and
M_w = Σ_{q∈w} W_q/(L_w L_q²) D_qᵀ D_q constant: the tangent sums a matrix a
window, not a product a point. Rigid motions of α turn every t_q: free.
Bending stays the yarn curve's own, E_b(Γα).
"""

import numpy as np
from scipy import sparse

from knitfem.knit.pattern import SEGMENTS_PER_STITCH
from knitfem.lod.rows import EmbeddingRows

__all__ = ["ShellStretch"]


class ShellStretch:
    """E_s of a full model's yarns (this rank's) embedded by ``embedding``,
    the volume read as a shell, the strain averaged over windows of
    ``window`` elements of a yarn (a last, shorter one where it does not
    divide the yarn's). The full model must be built without its own stretch
    (``FullModel(stretch=False)``). α is given as every volume control
    point, (n, 3)."""

    def __init__(self, full, embedding, window=SEGMENTS_PER_STITCH, per_patch=None):
        vol, el = embedding.volume, full.elements
        nq = len(el.weights)
        self.EA = full.material.EA
        lay = full.layout
        f, k = full.fabric.segments(lay.yarn_start, lay.yarn_end)
        nwin = -(-full.fabric.yarn_nseg[lay.yarn_start:lay.yarn_end] // window)
        first = np.concatenate([[0], np.cumsum(nwin)])[f - lay.yarn_start]
        window_of = first + k // window                              # of each element
        self.windows = int(window_of.max()) + 1 if el.ne else 0     # of the rank
        keep, xi = np.arange(self.windows), np.ones(self.windows)
        if per_patch is not None and el.ne:
            head = np.unique(window_of, return_index=True)[1]        # a window's first
            cols = shell_rows(vol, embedding.params, el, head)[0][::nq]
            keep, xi = stratified(patch_of(cols, np.arange(self.windows), self.windows),
                                  per_patch)
        kept = np.full(self.windows, -1)
        kept[keep] = np.arange(len(keep))
        e = np.flatnonzero(kept[window_of] >= 0)                     # the kept windows'
        cols, vals = shell_rows(vol, embedding.params, el, e)
        t = np.einsum("qk,qki->qi", vals, vol.flat[cols])
        self.L2 = np.einsum("qi,qi->q", t, t)
        W = np.tile(el.weights, len(e)) * np.sqrt(self.L2)
        self.win = np.repeat(kept[window_of[e]], nq)
        self.L = np.bincount(self.win, W, minlength=len(keep))      # L_w
        self.xi = xi
        self.D = EmbeddingRows(cols, vals, vol.size,
                               compiled=full.kernels.kind == "compiled")
        self.share = W / self.L[self.win]                            # W_q / L_w
        self.cols, self.vals = cols, vals
        # the points over each patch of V share its 32 columns (``keys``)
        self.keys, patch = np.unique(cols, axis=0, return_inverse=True)
        self._pair_matrices(patch.ravel())
        self.placed = None            # (T, positions) of add_tangent's first call for T
        self.kept = None              # (A, t, ē) of the last _strain
        self.dense = None             # add_hessian's dense array as values

    def _pair_matrices(self, patch):
        """The constant M_wP = Σ_{q∈w over P} g_q D_qᵀ D_q of every (window,
        patch) pair, g_q = W_q/(L_w L_q²), flat (pairs, k²), and the sparse
        sum over a patch's pairs (``_patch_blocks``),
        from each point's ``patch``: f_q = c_w g_q, c_w = EA ξ_w L_w ē_w, so
        Σ_{q over P} f_q D_qᵀ D_q = Σ_w c_w M_wP."""
        nwin, k = len(self.L), self.cols.shape[1]
        keys, pair = np.unique(patch * nwin + self.win, return_inverse=True)
        pair = pair.ravel()
        order = np.argsort(pair, kind="stable")
        count = np.bincount(pair, minlength=len(keys))
        slot = np.arange(len(pair)) - np.repeat(np.cumsum(count) - count, count)
        rows = np.zeros((len(keys), count.max(initial=0), k))
        rows[pair[order], slot] = self.vals[order]
        g = np.zeros(rows.shape[:2])
        g[pair[order], slot] = (self.share / self.L2)[order]
        M = np.matmul(rows.transpose(0, 2, 1), rows * g[..., None])
        self.pair_matrices = M.reshape(len(keys), k * k)
        self.pair_window = keys % nwin
        npatch = len(self.keys)
        self.pair_sum = sparse.csr_matrix(
            (np.zeros(len(keys)), np.arange(len(keys)),
             np.searchsorted(keys // nwin, np.arange(npatch + 1))),
            shape=(npatch, len(keys)))

    def _strain(self, A):
        """t_q (npts, 3) and ē_w (nwin,), kept for the last A: the energy,
        forces and tangent at one state share them."""
        if self.kept is None or not np.array_equal(self.kept[0], A):
            t = self.D @ A
            e = 0.5 * (np.einsum("qi,qi->q", t, t) - self.L2) / self.L2
            self.kept = (np.array(A), t,
                         np.bincount(self.win, self.share * e, minlength=len(self.L)))
        return self.kept[1:]

    def energy(self, A):
        """E_s = ½ EA Σ_w ξ_w L_w ē_w² of this rank's yarns at α = A (n, 3)."""
        _, ebar = self._strain(A)
        return 0.5 * self.EA * float(np.sum(self.xi * self.L * ebar**2))

    def _forces(self, A):
        """t_q and f_q = EA ξ_w L_w ē_w W_q / (L_w L_q²) at every point."""
        return self._strain(A)[0], self._stress(A)[self.win] * self.share / self.L2

    def add_gradient(self, A, out, scale=1.0):
        """out (n, 3) += scale · ∂E_s/∂α = scale · Dᵀ (f t)."""
        t, f = self._forces(A)
        out += self.D.T @ (scale * f[:, None] * t)

    def _stress(self, A):
        """c_w = EA ξ_w L_w ē_w of every window: f_q = c_w W_q/(L_w L_q²)."""
        return self.EA * (self.xi * self.L * self._strain(A)[1])

    def _patch_blocks(self, c):
        """Σ_{q over P} f_q D_qᵀ D_q = Σ_w c_w M_wP of every patch P of V,
        (patches, 32, 32) on its columns ``keys`` (``_pair_matrices``): one
        sparse product of the windows' c_w with the pairs' matrices."""
        self.pair_sum.data[:] = c[self.pair_window]
        k = self.cols.shape[1]
        return (self.pair_sum @ self.pair_matrices).reshape(-1, k, k)

    def add_tangent(self, A, T, convex=False):
        """T's values (a ``SparseTangent``) += ∂²E_s/∂α² (``hessian_parts``),
        each part placed by positions found at the first call for T: the
        patches' blocks ⊗ I₃, and Jᵀ diag(EA ξ L) J a group of windows at a
        time (those whose first point lies over a patch), J_g (windows ×
        3 U_g, U_g the columns they reach) formed by the compiled transpose
        of rows that map the points' s_q t_q, s_q = W_q/(L_w L_q²), into it,
        and J_gᵀ diag J_g by one GEMM.

        ``convex``: the compressed stitches' geometric stiffness dropped,
        c_w replaced by max(c_w, 0) in the first sum (f_q = c_w s_q). Both
        sums are then positive semi-definite: a stitch whose yarn is
        compressed (ē_w < 0) softens by EA |ē_w| D_qᵀ D_q in every direction,
        which on a sleeve crumpled at a bending elbow makes the exact tangent
        indefinite."""
        pos, Jmap, scale, jpos = self._placed(T)
        c = self._stress(A)
        self._add_patch_blocks(T, np.maximum(c, 0.0) if convex else c)
        ng, nw = scale.shape
        t = self._strain(A)[0]
        J = (Jmap.T @ ((self.share / self.L2)[:, None] * t)).reshape(ng, nw, -1)
        T.add_at(jpos, np.matmul(J.transpose(0, 2, 1) * scale[:, None, :], J))

    def add_compressed(self, A, T, scale=1.0):
        """T's values += scale Σ_{c_w<0} c_w M_w ⊗ I₃ (``_patch_blocks``): the
        compressed stitches' geometric stiffness, what ``add_tangent``
        leaves out with ``convex``."""
        self._add_patch_blocks(T, scale * np.minimum(self._stress(A), 0.0))

    def _add_patch_blocks(self, T, c):
        """T's values += Σ_w c_w M_w ⊗ I₃ (``_patch_blocks``), at the
        positions laid out for T."""
        pos = self._placed(T)[0]
        T.add_at(pos, np.repeat(self._patch_blocks(c), 3))     # ⊗ I₃: (P, k, k, 3)

    def _placed(self, T):
        """``_placement`` for T, laid out at the first call for its layout
        (a tangent's and its parts' positions are the same)."""
        if self.placed is None or self.placed[0] is not T.layout:
            self.placed = (T.layout, self._placement(T))
        return self.placed[1]

    def _placement(self, T):
        """(pos, Jmap, scale, jpos) of ``add_tangent`` for T: the positions
        of the patches' blocks ⊗ I₃ (patches, 32, 32, 3); the rows whose
        transpose maps s_q t_q to the groups' J_g, padded (points ×
        groups · windows · U, ``EmbeddingRows``);
        EA ξ_w L_w of each group's windows (groups, windows); the positions
        of J_gᵀ diag J_g (groups, U, 3, U, 3)."""
        c = np.arange(3)
        k = self.keys
        pos = T.positions(3 * k[:, :, None, None] + c, 3 * k[:, None, :, None] + c)
        nwin, n = len(self.L), T.N // 3
        group = patch_of(self.cols, self.win, nwin)
        count = np.bincount(group)
        order = np.argsort(group, kind="stable")
        wslot = np.empty(nwin, dtype=np.int64)              # w's row in its group
        wslot[order] = np.arange(nwin) - np.repeat(np.cumsum(count) - count, count)
        g = group[self.win]                                  # each point's group
        reach, u = np.unique(g[:, None] * n + self.cols, return_inverse=True)
        width = np.bincount(reach // n, minlength=len(count))
        first = np.cumsum(width) - width
        u = u.reshape(self.cols.shape) - first[g][:, None]
        ng, nw, wide = len(count), count.max(), width.max()
        Jmap = EmbeddingRows((g * nw + wslot[self.win])[:, None] * wide + u, self.vals,
                             ng * nw * wide, compiled=self.D.compiled)
        scale = np.zeros((ng, nw))
        scale[group, wslot] = self.EA * self.xi * self.L
        U = np.zeros((ng, wide), dtype=np.int64)
        U[reach // n, np.arange(len(reach)) - first[reach // n]] = reach % n
        shape = (ng, wide, 3, wide, 3)
        inside = np.arange(wide) < width[:, None]
        inside = np.broadcast_to(inside[:, :, None, None, None] & inside[:, None, None, :, None],
                                 shape)
        jpos = np.full(shape, T.nnz)
        jpos[inside] = T.positions(
            np.broadcast_to(3 * U[:, :, None, None, None] + c[:, None, None], shape)[inside],
            np.broadcast_to(3 * U[:, None, None, :, None] + c, shape)[inside])
        return pos, Jmap, scale, jpos

    def hessian_parts(self, A):
        """∂²E_s/∂α² (3n × 3n) as two scipy matrices whose sum it is, α
        interleaved (3c + i): the points' Σ_q f_q D_qᵀ D_q ⊗ I₃ from the
        windows' constant matrices (COO, its 3 × 3 blocks' diagonals), and
        Jᵀ diag(EA ξ L) J, J_w = Σ_{q∈w} W_q/(L_w L_q²) D_qᵀ t_q (J on a
        pattern laid out at the first call)."""
        t = self._strain(A)[0]
        n = self.D.shape[1]
        blocks = self._patch_blocks(self._stress(A))
        k, c = self.keys.shape[1], np.arange(3)
        rows = (3 * np.repeat(self.keys, k, axis=1)[..., None] + c).ravel()
        cols = (3 * np.tile(self.keys, k)[..., None] + c).ravel()
        S = sparse.coo_matrix((np.repeat(blocks.ravel(), 3), (rows, cols)),
                              shape=(3 * n, 3 * n))
        Jv = (self.share / self.L2)[:, None, None] * self.vals[:, :, None] * t[:, None, :]
        if getattr(self, "J", None) is None:
            J = sparse.csr_matrix(
                (np.arange(1, Jv.size + 1, dtype=float),
                 (np.repeat(self.win, Jv[0].size),
                  (3 * self.cols[:, :, None] + c).ravel())), shape=(len(self.L), 3 * n))
            J.sum_duplicates()
            J.sort_indices()
            self.J = sparse.csr_matrix((np.zeros(J.nnz), J.indices, J.indptr),
                                       shape=J.shape)
            self.jpos = np.zeros(Jv.size, dtype=np.int64)       # summed where they meet
            coo = sparse.coo_matrix((np.arange(Jv.size), (np.repeat(self.win, Jv[0].size),
                                    (3 * self.cols[:, :, None] + c).ravel())), shape=J.shape)
            keys = coo.row.astype(np.int64) * J.shape[1] + coo.col
            jkeys = np.repeat(np.arange(J.shape[0]), np.diff(J.indptr)) * J.shape[1] \
                + J.indices
            self.jpos[coo.data] = np.searchsorted(jkeys, keys)
        self.J.data[:] = np.bincount(self.jpos, Jv.ravel(), minlength=self.J.nnz)
        return S, self.J.T @ sparse.diags(self.EA * self.xi * self.L) @ self.J

    def hessian(self, A):
        """∂²E_s/∂α² (3n × 3n, scipy CSR): the sum of ``hessian_parts``."""
        S, JJ = self.hessian_parts(A)
        return S.tocsr() + JJ

    def pattern(self):
        """The scalar pattern (n × n, scipy) of ``hessian``'s couplings: the
        volume control points that a stitch's points reach, all to all."""
        reach = abs(sparse.csr_matrix((np.ones(len(self.win)), (self.win,
                                       np.arange(len(self.win)))),
                                      shape=(len(self.L), len(self.win)))) @ abs(self.D.tocsr())
        reach.data[:] = 1.0
        return reach.T @ reach

    def add_hessian(self, A, out, convex=False):
        """out (3n × 3n, dense, C-ordered) += ∂²E_s/∂α² (``add_tangent`` on its
        entries, laid out at the first call for ``out``; ``convex`` as there)."""
        from knitfem.lod.sparse_tangent import DenseValues

        if self.dense is None or self.dense.R is not out:
            self.dense = DenseValues(out, compiled=self.D.compiled)
        self.add_tangent(A, self.dense, convex)


def patch_of(cols, win, nwin):
    """The patch of V of each window: that of its first Gauss point (rows
    ``cols`` of D, the window of each point ``win``), as an index."""
    first = np.full(nwin, len(win))
    np.minimum.at(first, win, np.arange(len(win)))
    _, patch = np.unique(cols[first], axis=0, return_inverse=True)
    return patch.ravel()


def stratified(patch, per_patch):
    """(windows, weights ξ): in every patch, ``per_patch`` of its windows
    spread evenly through it (all when it has fewer), each weighted by the
    windows of the patch it stands for: Σ_{w∈S} ξ_w = the window count."""
    order = np.argsort(patch, kind="stable")
    start = np.searchsorted(patch[order], np.arange(patch.max() + 2))
    keep, xi = [], []
    for a, b in zip(start[:-1], start[1:]):
        m = min(per_patch, b - a)
        if m:
            keep.append(order[a + (np.arange(m) * (b - a)) // m])
            xi.append(np.full(m, (b - a) / m))
    keep, xi = np.concatenate(keep), np.concatenate(xi)
    order = np.argsort(keep)
    return keep[order], xi[order]


def shell_rows(volume, params, elements, e=slice(None)):
    """Columns and values (npts, 32) of the rows D_q of the Gauss points of
    ``elements`` (those of the indices ``e``), t_q = ∇P(s̄_q, ½) ξ̄'_q, from
    their control points' parameters ``params`` (s₁, s₂, w₃); s₁ of a
    periodic volume read modulo its period (an element's points unwrapped
    first)."""
    el = elements
    xi = np.stack(params, axis=-1)[el.conn[e]]                   # (ne, 4, 3)
    if volume.periodic:
        n = volume.domain[0]
        ref = xi[:, :1, 0]
        xi[..., 0] = ref + np.mod(xi[..., 0] - ref + n / 2, n) - n / 2
    bar = np.einsum("qa,eak->eqk", el.B, xi).reshape(-1, 3)      # ξ̄_q
    dxi = np.einsum("qa,eak->eqk", el.dB, xi).reshape(-1, 3)     # ξ̄'_q
    if volume.periodic:
        bar[:, 0] = np.mod(bar[:, 0], n)
    vals = 0.0
    for k, nu in enumerate(((1, 0, 0), (0, 1, 0), (0, 0, 1))):
        cols, v = volume.weights(bar[:, 0], bar[:, 1], 0.5, nu)
        vals = vals + dxi[:, k, None] * v
    return cols, vals
