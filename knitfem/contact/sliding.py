"""Sliding crossings: two yarns interlocked at a point that slides along both.

A persistent crossing of yarn a with yarn b holds one scalar constraint at
the closest approach of the two centrelines. With the separation

    r(ε, s) = P_a(s_a) − P_b(s_b),   f(ε, s) = |r|² / (2δ),

the sliding parameters s = (s_a, s_b) are eliminated: at every evaluation
s*(ε) solves the closest-approach conditions f_s = 0,

    r·t_a = 0,   r·t_b = 0,   t_a = ∂r/∂s_a = P_a',   t_b = ∂r/∂s_b = −P_b',

by a few vectorised Newton iterations warm-started from the last s* (kept
as state: the crossing follows a continuous local minimum of the distance,
so the interlock cannot jump to another pair of points). The crossing holds

    g(ε) = f(ε, s*(ε)) − δ/2 = (|r|² − δ²) / (2δ),

δ the rest separation. By the envelope theorem (f_s = 0 at s*) the Jacobian
is ∂g/∂p_k = w_k r / δ, w_k the weights of r at s*: the constraint force is
along the common normal, so yarn slides through the crossing without
friction. Its exact Hessian, with ∂s*/∂ε = −f_ss⁻¹ f_sε, is

    ∇²g = (1/δ) (w wᵀ ⊗ I₃) − f_εs f_ss⁻¹ f_sε,
    f_ss = (r_sᵀ r_s + diag(r·r_ss)) / δ,   ∂f_s_i/∂p_k = (w_k r_si + w_si,k r) / δ,

full 3 × 3 blocks (``BlockCurvature``). g is a distance, so every rigid
motion keeps it; s carries no mass: the yarn's inertia is in ε, its
material moves through the crossing point.

Weights live on a window of 4 + 2m control points a yarn (m the margin in
segments either side of the rest segment), so that C(ε) keeps one sparsity
pattern while s* moves up to m segments. Inside a step's Newton iterations
s* is held in its window; a step that ends with a crossing at the end of
its window is refused (``FullModel.begin_step``), with the advice to widen
the margin.
"""

from dataclasses import dataclass, fields

import numpy as np
import scipy.sparse as sp

from knitfem.errors import KnitError
from knitfem.yarn import bspline

__all__ = ["SlidingCrossings", "BlockCurvature", "SlidError", "crossings"]

NEWTON_STEPS = 30          # closest approach: quadratic, 2–3 steps near s
NEWTON_TOL = 1e-12         # |Δs| in segments (≈ 2e-15 m on the default jersey)
MAX_STEP = 0.25            # largest Newton step in segments
CONFORMAL = 1e-3           # f_ss's eigenvalue ratio below which yarns wrap
EDGE = 1e-9                # a window's last parameter short of its end (its segment)


class SlidError(KnitError):
    """A crossing slid out of the window of control points of its pattern."""


@dataclass
class SlidingCrossings:
    """Crossings that slide (module docstring), one scalar row each.

    owner (n,) the yarn of P_a; cols (n, 2W) global control points of the two
    windows (W = 4 + 2 margin, yarn a's then yarn b's); first (n, 2) the
    first segment of each window; nseg and closed the yarns' segments and
    closure; delta (n,) the rest separation; s (n, 2) the committed sliding
    parameters (state: where every evaluation's closest approach starts
    from), s0 (n, 2) their rest values; X (n, 2W, 3) the rest control points
    of the windows (arc lengths). ``s_star`` holds the last evaluation's s*.
    """

    owner: np.ndarray
    cols: np.ndarray
    first: np.ndarray
    delta: np.ndarray
    s: np.ndarray
    s0: np.ndarray
    X: np.ndarray
    nseg: int
    closed: bool

    rows = 1                      # scalar rows a crossing
    kind = "sliding"

    def __post_init__(self):
        self.s_star, self.solved_at = self.s.copy(), None

    @property
    def count(self):
        return len(self.owner)

    @property
    def width(self):
        """Control points of a window, W = 4 + 2 margin."""
        return self.cols.shape[1] // 2

    def select(self, keep):
        """The crossings where ``keep`` (bool or index array) is true (their
        own copy of the state s)."""
        arrays = {f.name: np.array(getattr(self, f.name)[keep]) for f in fields(self)
                  if f.name not in ("nseg", "closed")}
        return SlidingCrossings(**arrays, nseg=self.nseg, closed=self.closed)

    # -- weights on the windows ------------------------------------------------
    def weights(self, s, nu=(0, 1, 2)):
        """Weights (len(nu), n, 2, W) of d^nu P/ds^nu at s (n, 2) on each
        side's window, for the derivative orders ``nu``.

        Raises ``SlidError`` where s lies outside its window."""
        W, n = self.width, len(s)
        k, u = bspline.locate(s, self.nseg, self.closed)
        o = k - self.first
        if self.closed:
            o = np.mod(o, self.nseg)
        out = (o < 0) | (o > W - 4)
        if out.any():
            c = int(np.flatnonzero(out.any(axis=1))[0])
            raise SlidError(f"crossing {c} slid out of its window of {W} control "
                            f"points (s = {s[c].round(3).tolist()}, rest "
                            f"{self.s0[c].round(3).tolist()}): widen it with "
                            f"-knit_slide_margin")
        w = np.zeros((len(nu), n, 2, W))
        w[:, np.arange(n)[:, None, None], np.arange(2)[:, None], o[..., None]
          + np.arange(4)] = [bspline.basis(u, d) for d in nu]
        return w

    def _geometry(self, P, s):
        """r (n, 3), its weights w (n, 2W), r_s (n, 2, 3), the weights of r_s
        (n, 2, 2W) and r_ss's diagonal (n, 2, 3) at s, for points P (n, 2W, 3)."""
        W = self.width
        b0, b1, b2 = self.weights(s)
        sign = np.array([1.0, -1.0])[None, :, None]
        w = np.concatenate([b0[:, 0], -b0[:, 1]], axis=1)
        ws = np.zeros((len(s), 2, 2 * W))
        ws[:, 0, :W], ws[:, 1, W:] = b1[:, 0], -b1[:, 1]
        Pw = P.reshape(len(s), 2, W, 3)
        r = np.einsum("nk,nkd->nd", w, P)
        rs = sign * np.einsum("njk,njkd->njd", b1, Pw)
        rss = sign * np.einsum("njk,njkd->njd", b2, Pw)
        return r, w, rs, ws, rss

    @staticmethod
    def _second(r, rs, rss):
        """δ f_ss = r_sᵀ r_s + diag(r·r_ss), (n, 2, 2)."""
        H = np.einsum("nid,njd->nij", rs, rs)
        H[:, [0, 1], [0, 1]] += np.einsum("nd,njd->nj", r, rss)
        return H

    def clamp(self, s):
        """s held inside its window (the window's ends where it left)."""
        rel = s - self.first
        if self.closed:
            rel = np.mod(rel + 0.5 * self.nseg, self.nseg) - 0.5 * self.nseg
        return self.first + np.clip(rel, 0.0, self.width - 3.0 - EDGE)

    def at_edge(self):
        """Crossings (indices) whose last s* lies on an end of its window."""
        s = self.clamp(self.s_star)
        rel = s - self.first
        if self.closed:
            rel = np.mod(rel + 0.5 * self.nseg, self.nseg) - 0.5 * self.nseg
        return np.flatnonzero(((rel <= 0.0) | (rel >= self.width - 3.0 - EDGE))
                              .any(axis=1))

    def conformal(self, P):
        """Crossings (indices) whose yarns wrap around each other at the
        points P: the closest approach is hardly a minimum any more (f_ss's
        smallest eigenvalue below ``CONFORMAL`` times its largest), so s*
        is about to jump and a point cannot stand for the contact."""
        r, _, rs, _, rss = self._geometry(P, self.solve(P))
        lam = np.linalg.eigvalsh(self._second(r, rs, rss))
        return np.flatnonzero(lam[:, 0] < CONFORMAL * lam[:, 1])

    def solve(self, P):
        """s* (n, 2): the closest approach r·r_s = 0 reached from the
        committed s (``commit``), so that s*(ε) is one function of ε during
        a step whatever the states evaluated before. Newton's method on the
        distance, its Hessian's eigenvalues kept positive (every step goes
        down, to a minimum), steps of at most ``MAX_STEP``, held inside the
        windows (a state far off, as a Newton iterate may be, puts s* at a
        window's end: ``at_edge``). Stored as ``s_star`` and returned; the
        points P of the last solve are kept, so that g, C and ∇²g at one
        state solve once."""
        if self.solved_at is not None and np.array_equal(P, self.solved_at):
            return self.s_star
        s = self.s.copy()
        for _ in range(NEWTON_STEPS):
            r, _, rs, _, rss = self._geometry(P, s)
            F = np.einsum("nd,njd->nj", r, rs)
            lam, V = np.linalg.eigh(self._second(r, rs, rss))
            lam = np.maximum(np.abs(lam), 1e-3 * np.abs(lam).max(axis=1, keepdims=True))
            ds = -np.einsum("nij,nj,nkj,nk->ni", V, 1 / lam, V, F)
            new = self.clamp(s + np.clip(ds, -MAX_STEP, MAX_STEP))
            ds, s = new - s, new
            if not ds.size or np.abs(ds).max() < NEWTON_TOL:
                break
        self.s_star, self.solved_at = s, P.copy()
        return s

    def commit(self, P):
        """Take the closest approach at the points P as the new start s of
        the next evaluations (an accepted state)."""
        self.s = self.solve(P).copy()
        self.solved_at = None

    # -- constraint, Jacobian, Hessian -------------------------------------------
    def values(self, P):
        """g (n, 1) = (|r|² − δ²)/(2δ) at s*, for the points P (n, 2W, 3)."""
        r = self._geometry(P, self.solve(P))[0]
        d = self.delta
        return ((np.einsum("nd,nd->n", r, r) - d * d) / (2 * d))[:, None]

    def gradients(self, P):
        """∂g/∂p_k (n, 1, 2W, 3) = w_k r / δ at s*."""
        r, w = self._geometry(P, self.solve(P))[:2]
        return (w[:, :, None] * r[:, None, :] / self.delta[:, None, None])[:, None]

    def hessians(self, P):
        """∇²g (n, 6W, 6W) at s*, entry (3k + p, 3l + q) (module docstring)."""
        r, w, rs, ws, rss = self._geometry(P, self.solve(P))
        n, K = w.shape
        d = self.delta[:, None, None]
        inv = np.linalg.inv(self._second(r, rs, rss) / d)
        F = (w[:, :, None, None] * rs.transpose(0, 2, 1)[:, None]
             + ws.transpose(0, 2, 1)[:, :, None, :] * r[:, None, :, None]) / d[..., None]
        F = F.reshape(n, 3 * K, 2)
        H = -(F @ inv) @ F.transpose(0, 2, 1)
        H.reshape(n, K, 3, K, 3)[...] += \
            (np.einsum("nk,nl->nkl", w, w) / d)[:, :, None, :, None] * np.eye(3)[:, None]
        return H

    # -- how far the crossings slid ------------------------------------------------
    def slide_lengths(self, nq=8):
        """Arc length (n, 2) along each rest yarn from s0 to the last s*."""
        x, wq = bspline.gauss(nq)
        ds = self.s_star - self.s0
        if self.closed:                          # the short way round
            ds = np.mod(ds + 0.5 * self.nseg, self.nseg) - 0.5 * self.nseg
        speed = np.zeros(self.s.shape)
        Xw = self.X.reshape(self.count, 2, self.width, 3)
        for xq, w in zip(x, wq):
            tq = np.einsum("njk,njkd->njd", self.weights(self.s0 + xq * ds, (1,))[0],
                           Xw)
            speed += w * np.linalg.norm(tq, axis=-1)
        return np.abs(ds) * speed


class BlockCurvature:
    """Σ_i μ_i ∇²g_i of sliding crossings added into a tangent's values.

    ∇²g_i depends on ε through s* and has full 3 × 3 blocks: at every call
    the crossings' Hessians (n, 3K, 3K) go to their slots (``slots``, same
    shape, −1 off this rank's rows) through a constant 0/1 matrix S
    (nnz × 9K² n), built once."""

    def __init__(self, crossings, slots, nnz):
        self.crossings = crossings
        flat = slots.reshape(-1)
        keep = np.flatnonzero(flat >= 0)
        self.S = sp.csc_matrix((np.ones(len(keep)), (flat[keep], keep)),
                               shape=(nnz, flat.size))

    def add(self, mu, weight, values, P):
        """values += weight · Σ_i μ_i ∇²g_i at the crossings' points P."""
        H = self.crossings.hessians(P)
        values += self.S @ ((weight * np.asarray(mu))[:, None, None] * H).ravel()


def crossings(fabric, margin=2):
    """Sliding crossings of a ``Fabric``'s contacts, each at the closest
    approach near its pattern parameters at rest, with windows of margin
    segments either side."""
    ya, sa, yb, sb = fabric.contacts
    ncp, nseg, closed = fabric.ncp, fabric.nseg, fabric.closed
    W = 4 + 2 * margin
    if not closed and nseg < W - 3:
        raise KnitError(f"sliding crossings need yarns of at least {W - 3} "
                        f"segments (margin {margin}); these have {nseg}")
    s0 = np.stack([sa, sb], axis=1).astype(float)
    k, _ = bspline.locate(s0, nseg, closed)
    first = k - margin
    first = np.mod(first, nseg) if closed else np.clip(first, 0, nseg - W + 3)
    span = first[..., None] + np.arange(W)
    if closed:
        span = np.mod(span, ncp)
    yarn = np.stack([ya, yb], axis=1)
    cols = (yarn[..., None] * ncp + span).reshape(len(s0), 2 * W)
    X = fabric.X.reshape(-1, 3)[cols]
    c = SlidingCrossings(np.asarray(ya), cols, first, np.ones(len(s0)), s0, s0, X,
                         nseg, closed)
    c.commit(X)
    c.s0 = c.s.copy()
    r = c._geometry(X, c.s0)[0]
    c.delta = np.linalg.norm(r, axis=1)
    return c
