"""Sliding crossings: two yarns interlocked at a point that slides along both.

A persistent crossing of yarn a with yarn b holds one scalar constraint at a
point that moves along both yarns. With the separation and the reference
tangents

    r(ε, s) = P_a(s_a) − P_b(s_b),   T_a = P_a'(σ_a),   T_b = P_b'(σ_b),

(σ the pattern's crossing parameters at the start: T is linear in ε and
turns with the yarns) the sliding parameters s = (s_a, s_b) are eliminated: at every
evaluation s*(ε) solves the crossing conditions

    c(ε, s) = (r·T_a, r·T_b) = 0,   A = c_s = (t_i·T_j),   t = r_s,

(r along the yarns' common normal T_a × T_b) by a few vectorised Newton
iterations from the s of the last accepted state (state: s* is one
continuous function of ε within a step, so the interlock cannot jump). The
crossing holds

    g(ε) = G(ε, s*(ε)) = (|r|² − δ²) / (2δ),

δ the rest separation. At rest the crossing is the closest approach (r ⟂
t_a, t_b with t = T): A is the Gram matrix of two tangents crossing at 64°
on the jersey, well conditioned, with no curvature term. (The closest
approach itself, r·t_a = r·t_b = 0 at the current tangents, has
A = r_sᵀ r_s + r·r_ss: on the jersey's interlocks the loops wrap around
each other so that its smallest eigenvalue is 7 % of the largest at rest
and vanishes under a pull, where s* jumps.)

g depends on ε only (a holonomic constraint: its force does no work on any
motion that keeps it, so sliding dissipates nothing), and with the
multipliers η = −A⁻ᵀ G_s of the Lagrangian L = G + ηᵀc (L_s = 0 at s*)

    ∇g = L_ε = G_ε + ηᵀ c_ε,
    ∇²g = L_εε + L_εs S + (L_εs S)ᵀ + Sᵀ L_ss S,   S = ∂s*/∂ε = −A⁻¹ c_ε,

with G_ε,k = w_k r/δ, G_s = r·t/δ, c_ε,jk = w_k T_j + χ_jk r (w, χ the
weights of r and T), full 3 × 3 blocks (``BlockCurvature``). g, c and A
are dot products of vectors that turn with the fabric and do not move
under a translation, so every rigid motion keeps g. s carries no mass:
the yarn's inertia is in ε, its material moves through the crossing point.
At the two straight yarns' crossing r·t = 0, so η = 0 and the force is
w_k r/δ, along the normal.

Weights live on a window of 4 + 2m control points a yarn (m the margin in
segments either side of the segment of s), so that C(ε) keeps one sparsity
pattern while s* moves up to m segments. Inside a step's Newton iterations
s* is held in its window; a step that ends with a crossing at the end of
its window is refused (``FullModel.tunnelled``: a smaller step is tried).
A side held at its window's end does not move with ε: the other side solves
its own equation alone, and g's derivatives are those of a fixed s on the
held side (its equation leaves A, so its η and its row of S vanish).
Between steps a window whose s has strayed more than m/2 segments from its
middle (for m = 1: s left the middle segment) moves along its yarn to be
centred on s again (``centred``, ``move_windows``; round a closed yarn, up
to an open yarn's ends), and C's pattern and the tangent's are laid out
again: s, s* and g do not change, the reference tangents are taken again at
s (below), and the slide so far is banked (``slid``, the arc length from
rest to ``base``, where the window last moved), so that ``slide_lengths``
measures from rest however far the crossing went. The reference tangents
follow a crossing that slides along a loop: at an accepted state where s*
is more than half a segment from where they were taken, they are taken
again there, T_j = t_j − β_j r with β_j = r·t_j / r·r, so that r·T = 0
still holds at that state: s* and g do not move, only g's gradient tilts by
O(η) (``commit``; the summary counts these re-anchorings). Where the two yarns
come to run nearly parallel (θ ≲ 11°, as at a relaxed knit's edge) the
crossing point along them is ill-defined: A loses rank and the search for
s* stalls short of c = 0, so the gradient it gives is wrong. Such a
crossing is locked, held at its s like a fixed one, until the yarns part
again (θ ≳ 18°), when it is re-anchored there and slides on (``commit``;
``locked``).
"""

from dataclasses import dataclass, fields

import numpy as np
import scipy.sparse as sp

from knitfem.errors import KnitError
from knitfem.yarn import bspline

__all__ = ["SlidingCrossings", "BlockCurvature", "SlidError", "crossings"]

NEWTON_STEPS = 30          # crossing conditions: quadratic, 2–3 steps near s
NEWTON_TOL = 1e-12         # |Δs| in segments (≈ 2e-15 m on the default jersey)
MAX_STEP = 0.25            # largest Newton step in segments
REANCHOR = 0.5            # slide [segments] after which the reference tangents move
LOCK = 100.0               # condition of the tangents' Gram matrix that locks a crossing
UNLOCK = 40.0              # ... and below which a locked crossing slides again
STALL = 1e-8               # |c| / (|T| δ) of a search for s* that stalled: locks it
EDGE = 1e-9                # a window's last parameter short of its end (its segment)


def inverse2(A):
    """Inverses (n, 2, 2) of 2 × 2 matrices A (n, 2, 2), in closed form
    (a batched LAPACK solve costs 100 times more at these sizes)."""
    inv = np.empty_like(A)
    inv[:, 0, 0], inv[:, 1, 1] = A[:, 1, 1], A[:, 0, 0]
    inv[:, 0, 1], inv[:, 1, 0] = -A[:, 0, 1], -A[:, 1, 0]
    return inv / (A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0])[:, None, None]


def kron_eye(v):
    """v ⊗ I₃ (n, 3K, 3) of vectors v (n, K)."""
    out = np.zeros(v.shape + (3, 3))
    for q in range(3):
        out[..., q, q] = v
    return out.reshape(len(v), -1, 3)


class SlidError(KnitError):
    """A crossing slid out of the window of control points of its pattern."""


@dataclass
class SlidingCrossings:
    """Crossings that slide (module docstring), one scalar row each.

    owner (n,) the yarn of P_a; cols (n, 2W) global control points of the two
    windows (W = 4 + 2 margin, yarn a's then yarn b's); first (n, 2) the
    first segment of each window; nseg (n, 2) and closed (n, 2) the two
    yarns' segments and closure, start (n, 2) their first control points;
    delta (n,) the rest separation; s (n, 2) the committed sliding
    parameters (state: where every evaluation's search for s* starts
    from), s0 (n, 2) their rest values; X (n, 2W, 3) the rest control points
    of the windows (arc lengths); sT (n, 2) the parameters σ where the
    reference tangents were taken, chi (n, 2, 2W) their weights; base (n, 2)
    the s where the windows last moved and slid (n, 2) the signed arc length
    along the rest yarns from s0 to base; locked (n,) the crossings held at
    their s while their yarns run nearly parallel (``commit``). ``s_star``
    holds the last evaluation's s*.
    """

    owner: np.ndarray
    cols: np.ndarray
    first: np.ndarray
    delta: np.ndarray
    s: np.ndarray
    s0: np.ndarray
    X: np.ndarray
    sT: np.ndarray
    chi: np.ndarray
    nseg: np.ndarray
    closed: np.ndarray
    start: np.ndarray
    base: np.ndarray
    slid: np.ndarray
    locked: np.ndarray

    rows = 1                      # scalar rows a crossing
    kind = "sliding"

    def __post_init__(self):
        self.s_star, self.solved_at, self._terms_at = self.s.copy(), None, None

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
        arrays = {f.name: np.array(getattr(self, f.name)[keep]) for f in fields(self)}
        return SlidingCrossings(**arrays)

    # -- weights on the windows ------------------------------------------------
    def weights(self, s, nu=(0, 1, 2)):
        """Weights (len(nu), n, 2, W) of d^nu P/ds^nu at s (n, 2) on each
        side's window, for the derivative orders ``nu``.

        Raises ``SlidError`` where s lies outside its window."""
        W, n = self.width, len(s)
        k, u = bspline.locate(s, self.nseg, self.closed)
        o = np.where(self.closed, np.mod(k - self.first, self.nseg), k - self.first)
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

    def _geometry(self, P, s, second=True):
        """r (n, 3), its weights w (n, 2W), r_s (n, 2, 3), the weights of r_s
        (n, 2, 2W) and r_ss's diagonal (n, 2, 3) (None unless ``second``) at
        s, for points P (n, 2W, 3)."""
        W = self.width
        b = self.weights(s, (0, 1, 2) if second else (0, 1))
        sign = np.array([1.0, -1.0])[None, :, None]
        w = np.concatenate([b[0][:, 0], -b[0][:, 1]], axis=1)
        ws = np.zeros((len(s), 2, 2 * W))
        ws[:, 0, :W], ws[:, 1, W:] = b[1][:, 0], -b[1][:, 1]
        Pw = P.reshape(len(s), 2, W, 3)
        r = np.einsum("nk,nkd->nd", w, P)
        rs = sign * np.einsum("njk,njkd->njd", b[1], Pw)
        rss = sign * np.einsum("njk,njkd->njd", b[2], Pw) if second else None
        return r, w, rs, ws, rss

    def _chord_weights(self):
        """Weights χ (n, 2, 2W) of the reference tangents T = Σ_k χ_k p_k."""
        return self.chi

    def _chords(self, P):
        """The reference tangents T (n, 2, 3): directions along the two
        yarns at the crossing that depend on ε only."""
        return np.einsum("njk,nkd->njd", self.chi, P)

    def anchor(self, P, which):
        """Reference tangents of the crossings ``which`` at their s:
        T_j = t_j − β_j r, β_j = r·t_j / r·r at the points P, so that r·T = 0
        there and s* at P stays s."""
        r, w, rs, ws = (a[which] for a in self._geometry(P, self.s, False)[:4])
        beta = np.einsum("nd,njd->nj", r, rs) / np.einsum("nd,nd->n", r, r)[:, None]
        self.chi[which] = ws - beta[..., None] * w[:, None, :]
        self.sT[which] = self.s[which]

    def _along(self, ds):
        """Parameter differences ds (n, 2), the short way round a closed yarn."""
        return np.where(self.closed, np.mod(ds + 0.5 * self.nseg, self.nseg)
                        - 0.5 * self.nseg, ds)

    def clamp(self, s):
        """s held inside its window (the window's ends where it left)."""
        rel = self._along(s - self.first)
        return self.first + np.clip(rel, 0.0, self.width - 3.0 - EDGE)

    def held(self, s):
        """Sides (n, 2) whose s lies on an end of its window, where ``clamp``
        holds it."""
        rel = self._along(self.clamp(s) - self.first)
        return (rel <= 0.0) | (rel >= self.width - 3.0 - EDGE)

    def frozen(self, s):
        """Sides (n, 2) that do not move with ε: held at a window's end, or
        of a locked crossing."""
        return self.held(s) | self.locked[:, None]

    def at_edge(self):
        """Crossings (indices) whose last s* lies on an end of its window."""
        return np.flatnonzero(self.held(self.s_star).any(axis=1))

    def solve(self, P):
        """s* (n, 2): the crossing c = (r·T_a, r·T_b) = 0 reached from the
        committed s (``commit``) by Newton's method, c_s = (t_i·T_j), steps
        of at most ``MAX_STEP``, held inside the windows (a state far off,
        as a Newton iterate may be, puts s* at a window's end: ``at_edge``).
        Stored as ``s_star`` and returned; the points P of the last solve
        are kept, so that g, C and ∇²g at one state solve once."""
        if self.solved_at is not None and np.array_equal(P, self.solved_at):
            return self.s_star
        T = self._chords(P)
        s = self.s.copy()
        for _ in range(NEWTON_STEPS):
            r, _, rs = self._geometry(P, s, False)[:3]
            c = np.einsum("nd,njd->nj", r, T)
            A = np.einsum("nid,njd->nji", rs, T)
            ds = -np.einsum("nij,nj->ni", inverse2(A), c)
            new = self.clamp(s + np.clip(ds, -MAX_STEP, MAX_STEP))
            new[self.locked] = s[self.locked]
            # a side held at its window's end leaves the other side its own
            # equation, c_j = 0 for s_j alone
            held = self.frozen(new)
            n, k = np.nonzero(held[:, ::-1] & ~held)   # k free, the other held
            if len(n):
                free = s.copy()
                free[n, k] += np.clip(-c[n, k] / A[n, k, k], -MAX_STEP, MAX_STEP)
                new[n, k] = self.clamp(free)[n, k]
            ds, s = new - s, new
            if not ds.size or np.abs(ds).max() < NEWTON_TOL:
                break
        self.s_star, self.solved_at, self._terms_at = s, P.copy(), None
        return s

    def commit(self, P):
        """Take the crossing at the points P (an accepted state) as the new
        start s of the next evaluations. A crossing that has slid more than
        ``REANCHOR`` segments from its reference parameters σ takes its
        reference tangents at s (``anchor``): on a loop the tangents turn as
        the crossing slides, and A would lose rank.

        Where the two yarns run nearly parallel at a crossing, its point
        along them is ill-defined (A → the Gram matrix of t_a, t_b loses
        rank, and the search for s* stalls short of c = 0): a crossing whose
        Gram matrix's condition (1 + |cos θ|)/(1 − |cos θ|), θ the angle of
        t_a and t_b, exceeds ``LOCK`` (θ ≈ 11°), or whose search stalled
        (|c| > ``STALL`` |T| δ with neither side held at a window's end), is
        locked, held at its s as a fixed crossing (``frozen``: g and its
        derivatives those of a fixed s), and slides again, re-anchored at s,
        where the condition falls below ``UNLOCK`` (θ ≈ 18°). Returns how
        many were re-anchored."""
        self.s = self.solve(P).copy()
        r, _, rs = self._geometry(P, self.s, False)[:3]
        t = rs / np.linalg.norm(rs, axis=-1, keepdims=True)
        T = self._chords(P)
        Tn = np.linalg.norm(T, axis=-1)
        cos = np.abs(np.einsum("nd,nd->n", t[:, 0], t[:, 1]))
        cond = (1 + cos) / np.maximum(1 - cos, 1e-300)
        stalled = np.abs(np.einsum("nd,njd->nj", r, T)).max(axis=1) \
            > STALL * (Tn.max(axis=1) * self.delta)
        freed = self.locked & (cond < UNLOCK)
        stalled &= ~self.locked & ~self.held(self.s).any(axis=1)
        self.locked = (self.locked & ~freed) | (cond > LOCK) | stalled
        far = np.flatnonzero(((np.abs(self.s - self.sT).max(axis=1) > REANCHOR)
                              | freed) & ~self.locked)
        if far.size:
            self.anchor(P, far)
        self.solved_at = None
        return len(far)

    # -- constraint, Jacobian, Hessian -------------------------------------------
    def values(self, P):
        """g (n, 1) = (|r|² − δ²)/(2δ) at s*, for the points P (n, 2W, 3)."""
        r = self._geometry(P, self.solve(P), False)[0]
        d = self.delta
        return ((np.einsum("nd,nd->n", r, r) - d * d) / (2 * d))[:, None]

    def _terms(self, P):
        """What ∇g and ∇²g are made of at s* (module docstring): r, w, r_s,
        its weights, r_ss, T, χ, A = c_s (n, 2, 2), c_ε (n, 2, 3K) and the
        multipliers η = −A⁻ᵀ G_s (n, 2); kept for the P of the last solve."""
        self.solve(P)
        if self._terms_at is None:
            self._terms_at = self._evaluate_terms(P)
        return self._terms_at

    def _evaluate_terms(self, P):
        """``_terms`` at s* (solved at P)."""
        r, w, rs, ws, rss = self._geometry(P, self.s_star)
        T, chi = self._chords(P), self._chord_weights()
        n, K = w.shape
        A = np.einsum("nid,njd->nji", rs, T)
        c_eps = (w[:, None, :, None] * T[:, :, None, :]
                 + chi[..., None] * r[:, None, None, :]).reshape(n, 2, 3 * K)
        G_s = np.einsum("nd,nid->ni", r, rs) / self.delta[:, None]
        held = self.frozen(self.s_star)
        if held.any():
            # a side held at its window's end (or locked) does not move with ε: its
            # equation leaves A (its row and column become the identity's),
            # so that its η and its row of S = ∂s*/∂ε vanish
            A = np.where(held[:, None, :] | held[:, :, None], 0.0, A)
            A[:, [0, 1], [0, 1]] += held
            c_eps = np.where(held[:, :, None], 0.0, c_eps)
            G_s = np.where(held, 0.0, G_s)
        eta = -np.einsum("nji,nj->ni", inverse2(A), G_s)
        return r, w, rs, ws, rss, T, chi, A, c_eps, eta

    def gradients(self, P):
        """∂g/∂p (n, 1, 2W, 3) = G_ε + ηᵀ c_ε at s*."""
        r, w, _, _, _, _, _, _, c_eps, eta = self._terms(P)
        n, K = w.shape
        G_eps = w[:, :, None] * r[:, None, :] / self.delta[:, None, None]
        return (G_eps.reshape(n, 3 * K) + np.einsum("nj,nja->na", eta, c_eps)
                ).reshape(n, 1, K, 3)

    def hessians(self, P):
        """∇²g (n, 6W, 6W) at s*, entry (3k + p, 3l + q):
        L_εε + L_εs S + (L_εs S)ᵀ + Sᵀ L_ss S, S = ∂s*/∂ε = −A⁻¹ c_ε
        (module docstring)."""
        r, w, rs, ws, rss, T, chi, A, c_eps, eta = self._terms(P)
        n, K = w.shape
        d = self.delta
        L_es = ((ws.transpose(0, 2, 1)[:, :, None, :] * r[:, None, :, None]
                 + w[:, :, None, None] * rs.transpose(0, 2, 1)[:, None])
                / d[:, None, None, None]
                + np.einsum("nj,nik,njp->nkpi", eta, ws, T)
                + np.einsum("nj,njk,nip->nkpi", eta, chi, rs)).reshape(n, 3 * K, 2)
        L_ss = np.einsum("nid,njd->nij", rs, rs) / d[:, None, None]
        L_ss[:, [0, 1], [0, 1]] += (np.einsum("nd,nid->ni", r, rss) / d[:, None]
                                    + np.einsum("nj,nid,njd->ni", eta, rss, T))
        Ai = inverse2(A)
        S = -(Ai[:, :, :1] * c_eps[:, None, 0] + Ai[:, :, 1:] * c_eps[:, None, 1])
        # L_εs S + (L_εs S)ᵀ + Sᵀ L_ss S = U S + Sᵀ Uᵀ, U = L_εs + ½ Sᵀ L_ss, and
        # L_εε = (w wᵀ/δ + w cᵀ + c wᵀ) ⊗ I₃, c = ηᵀχ: one product of rank 10
        U = L_es + 0.5 * (S.transpose(0, 2, 1) @ L_ss)
        c = np.einsum("nj,njl->nl", eta, chi)
        left = np.concatenate([U, S.transpose(0, 2, 1), kron_eye(w), kron_eye(c)],
                              axis=2)
        right = np.concatenate([S, U.transpose(0, 2, 1),
                                kron_eye(w / d[:, None] + c).transpose(0, 2, 1),
                                kron_eye(w).transpose(0, 2, 1)], axis=1)
        return left @ right

    # -- how far the crossings slid ------------------------------------------------
    def _arcs(self, s, nq=8):
        """Signed arc length (n, 2) along each rest yarn from s0 to s (inside
        the windows): slid + ∫_base^s |X'(σ)| dσ (nq-point Gauss)."""
        x, wq = bspline.gauss(nq)
        ds = self._along(s - self.base)
        speed = np.zeros(self.s.shape)
        Xw = self.X.reshape(self.count, 2, self.width, 3)
        for xq, w in zip(x, wq):
            tq = np.einsum("njk,njkd->njd", self.weights(self.base + xq * ds, (1,))[0],
                           Xw)
            speed += w * np.linalg.norm(tq, axis=-1)
        return self.slid + ds * speed

    def slide_lengths(self):
        """Arc length (n, 2) along each rest yarn from s0 to the last s*."""
        return np.abs(self._arcs(self.s_star))

    # -- windows that follow the crossings -------------------------------------------
    def centred(self):
        """First segments (n, 2) of the windows: centred on the committed s
        (its segment the m-th) where s lies more than m/2 segments from its
        window's middle (m the margin), as they are elsewhere. An open yarn's
        window stops at the yarn's ends."""
        m = (self.width - 4) // 2
        far = np.abs(self._along(self.s - self.first) - (m + 0.5)) > 0.5 * m
        k, _ = bspline.locate(self.s, self.nseg, self.closed)
        centre = np.where(self.closed, np.mod(k - m, self.nseg),
                          np.clip(k - m, 0, self.nseg - self.width + 3))
        return np.where(far, centre, self.first)

    def move_windows(self, first, X, P):
        """Move the windows to start at the segments ``first`` (n, 2), for
        the rest control points X and the points P (N, 3) of every yarn.
        A crossing whose window moved keeps s and s* (g does not change): its
        slide so far is banked (slid ← arc length from s0 to s, base ← s)
        and its reference tangents are taken at s on the new windows
        (``anchor``). Returns the indices of the crossings that moved."""
        moved = np.flatnonzero((first != self.first).any(axis=1))
        if not moved.size:
            return moved
        self.slid[moved] = self._arcs(self.s)[moved]
        self.base[moved] = self.s[moved]
        self.first[moved] = first[moved]
        self.cols[moved] = window_cols(self.start, first, self.width, self.nseg,
                                         self.closed)[moved]
        self.X[moved] = X[self.cols[moved]]
        self.s_star, self.solved_at = self.s.copy(), None
        self.anchor(P[self.cols], moved)
        return moved

    def state(self):
        """The committed state (n, 11 + 4W): s, σ, first, base, slid, locked,
        χ."""
        return np.concatenate([self.s, self.sT, self.first, self.base, self.slid,
                               self.locked[:, None], self.chi.reshape(self.count, -1)],
                              axis=1)

    def set_state(self, state, X):
        """Commit a ``state`` (windows, where they moved, with the rest
        control points X (N, 3) of every yarn)."""
        state = np.asarray(state, dtype=float)
        self.s, self.sT = state[:, 0:2].copy(), state[:, 2:4].copy()
        self.first = np.rint(state[:, 4:6]).astype(self.first.dtype)
        self.base, self.slid = state[:, 6:8].copy(), state[:, 8:10].copy()
        self.locked = state[:, 10] > 0.5
        self.chi = state[:, 11:].reshape(self.count, 2, -1).copy()
        self.cols = window_cols(self.start, self.first, self.width, self.nseg,
                                self.closed)
        self.X = X[self.cols]
        self.s_star, self.solved_at = self.s.copy(), None


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


def window_cols(start, first, W, nseg, closed):
    """Global control points (n, 2W) of the windows of W control points
    starting at segments ``first`` (n, 2) of yarns whose first control
    points are ``start`` (n, 2) (modulo a closed yarn's control points)."""
    span = first[..., None] + np.arange(W)
    ncp = np.where(closed, nseg, nseg + 3)[..., None]
    span = np.where(closed[..., None], np.mod(span, ncp), span)
    return (start[..., None] + span).reshape(len(first), 2 * W)


def crossings(fabric, margin=1):
    """Sliding crossings of a ``Fabric``'s contacts, each starting at its
    pattern parameters (the closest approach at rest), with windows of
    margin segments either side, holding the fabric's ``separation`` where
    it has one (else the rest's)."""
    ya, sa, yb, sb = fabric.contacts
    yarn = np.stack([ya, yb], axis=1).astype(np.int64)
    nseg = fabric.yarn_nseg[yarn]
    closed = fabric.closed[yarn]
    W = 4 + 2 * margin
    short = ~closed & (nseg < W - 3)
    if short.any():
        raise KnitError(f"sliding crossings need yarns of at least {W - 3} "
                        f"segments (margin {margin}); one has {nseg[short].min()}")
    s0 = np.stack([sa, sb], axis=1).astype(float)
    k, _ = bspline.locate(s0, nseg, closed)
    first = np.where(closed, np.mod(k - margin, nseg),
                     np.clip(k - margin, 0, nseg - W + 3))
    start = fabric.yarn_start[yarn]
    cols = window_cols(start, first, W, nseg, closed)
    X = fabric.X[cols]
    c = SlidingCrossings(np.asarray(ya), cols, first, np.ones(len(s0)), s0, s0, X,
                         s0.copy(), np.zeros((len(s0), 2, 2 * W)), nseg, closed,
                         start, s0.copy(), np.zeros(s0.shape),
                         np.zeros(len(s0), bool))
    c.anchor(X, np.arange(len(s0)))
    if fabric.separation is not None:
        c.delta = np.full(len(s0), float(fabric.separation))
    else:
        c.delta = np.linalg.norm(c._geometry(X, c.s0, False)[0], axis=1)
    return c
