"""The reduced model's contact with bodies on an active set of yarn elements.

The barrier E_c and the lagged friction D against bodies (``colliders``)
act only on yarn elements within the gap ĥ of a body, so the reduced model
evaluates them, its forces Γ_Aᵀ ∇(E_c + D) and its tangent
Γ_Aᵀ ∇²(E_c + D) Γ_A, on an active set A of elements near a body: a Newton
iteration costs what the contact region does, not the yarns.

Broad phase. A yarn point is a convex combination of its element's four
control points p_a, so φ(x) ≥ min_a φ(p_a) − d_e, d_e the largest distance
between two of them (φ is 1-Lipschitz). At the start of a step, from the
control points x⁰ = Γ̃ α⁰ and the bodies at t₀, an element e is active when

    min_a φ(p_a) − d_e − r < ĥ + m_e + a_e,

m_e how far the moving bodies carry their points at the p_a over the step
and a_e the allowance for the element's own move (twice its largest in
the last step, at least 2 r): on a sleeve whose wrist swings with the
forearm, the band of yarn on the upper arm is not widened by the wrist's
move. The set is formed again when the step's end time changes (a retried
step) and at every step; after a step, an element left out whose bound at
the end state comes within the gap refuses the step (``missed``), with
every allowance doubled, and the step is solved again on the larger set; a
part of a step (a step halved) forms it about its own start too. Friction
is lagged on the set at the step's start.

Narrow phase. Within a step, the barrier is evaluated only on the elements
of the set that can have a point within the gap. At a reference state α⁰
(the first one evaluated after the bodies moved) each element's nearest
point is found, ℓ_e = min_q δ(x_q(α⁰)), the bodies where they are at the
step's end. A yarn point moves with α by |Γ̃_i (α − α⁰)| ≤ s_i max_k |α_k −
α⁰_k| over the columns k of its row (s_i = Σ_k |Γ̃_ik|, 1 for B-spline
weights), so

    δ(x_q(α)) ≥ ℓ_e − ρ_e(α − α⁰),   ρ_e(d) = max_{i ∈ e} s_i max_{k ∈ patch(i)} |d_k|,

and an element with ℓ_e − ρ_e ≥ ĥ adds nothing at α: the energy, forces,
tangent and step filter at α look at the others only (a sleeve resting on
an arm: the yarns in the gap, not the band around them).
"""

import numpy as np
from scipy import sparse

from knitfem.contact.colliders import Barrier
from knitfem.contact.motion import moving
from knitfem.lod.rows import EmbeddingRows
from knitfem.lod.sparse_tangent import QuadratureProduct, patches

__all__ = ["ActiveContact"]

PAIRS = np.array(((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))).T
"""The pairs of an element's four control points, (2, 6)."""


def element_patches(patch, spread):
    """Each element's distinct patches and the largest s_i of its points in
    each, from its points' ``patch`` and ``spread`` (m, 4): two (k, m)
    arrays, k the most patches an element's points lie in (rows past an
    element's own repeat its first), so that ρ_e(d) = max over k of
    spread × far[patch] (most elements lie in one patch)."""
    m = len(patch)
    if not m:
        return np.zeros((1, 0), dtype=int), np.zeros((1, 0))
    order = np.argsort(patch, axis=1, kind="stable")
    patch = np.take_along_axis(patch, order, 1).ravel()
    spread = np.take_along_axis(spread, order, 1).ravel()
    starts = np.flatnonzero(np.r_[True, patch[1:] != patch[:-1]]
                            | (np.arange(4 * m) % 4 == 0))       # runs within a row
    count = np.bincount(starts // 4, minlength=m)
    first = np.cumsum(count) - count
    run = first + np.minimum(np.arange(count.max())[:, None], count - 1)
    return patch[starts[run]], np.maximum.reduceat(spread, starts)[run]


class ElementView:
    """Some yarn elements ``e`` of ``elements`` over their own control points
    (``points_index``, rows of the rank's), as ``colliders.Barrier`` uses
    them: the basis B, the weights W, the connectivity and ``points``."""

    def __init__(self, elements, e):
        self.points_index, local = np.unique(elements.conn[e], return_inverse=True)
        self.conn = local.reshape(-1, 4)
        self.B, self.W = elements.B, elements.W[e]
        self.ne = len(e)
        self.sampler = sparse.csr_matrix(
            (np.broadcast_to(self.B, (self.ne, len(self.B), 4)).ravel(),
             (np.repeat(np.arange(self.ne * len(self.B)), 4),
              np.repeat(self.conn, len(self.B), axis=0).ravel())),
            shape=(self.ne * len(self.B), len(self.points_index)))

    def points(self, x):
        """Curve points at every quadrature point, (ne, nq, 3)."""
        return (self.sampler @ np.asarray(x)).reshape(self.ne, len(self.B), 3)


class ActiveContact:
    """E_c + D of a ``FullModel``'s yarns (this rank's) against its bodies,
    embedded by ``embedding``, on an active set of elements (module
    docstring). α is given as every volume control point, (n, 3)."""

    def __init__(self, full, embedding):
        self.full, self.el = full, full.elements
        whole = full.barrier
        self.bodies, self.radius = whole.bodies, whole.radius
        self.gap, self.friction = whole.gap, whole.mu
        self.weight = full.material.rho * full.material.gravity
        n = embedding.volume.size
        self.product = None
        self.G = EmbeddingRows(embedding.cols, embedding.vals, n,
                               compiled=full.kernels.kind == "compiled")  # Γ̃ (rank's)
        self.columns, self.patch = patches(embedding.cols)
        self.spread = np.abs(embedding.vals).sum(axis=1)                # s_i
        self.allowance, self.step_h = 2 * self.radius, None
        self.active = np.zeros(0, dtype=int)
        self.barrier, self.start, self.window, self.refusals = None, None, None, 0
        self.bound_kept = None
        self._use(np.zeros(0, dtype=int))

    # -- the set ---------------------------------------------------------------
    def _bound(self, X):
        """min_a φ(p_a) − d_e − r of every element at control points X, the
        bodies as they are posed (kept for the last X and poses: a step's
        ``missed`` and the next step's ``move`` ask at the same state). Not
        to be written to."""
        pose = [(b.R.tobytes(), b.s.tobytes()) if moving(b) else None
                for b in self.bodies]
        kept = self.bound_kept
        if kept is not None and kept[1] == pose and np.array_equal(kept[0], X):
            return kept[2]
        phi = np.min([self.barrier.phi(body, X) for body in self.bodies], axis=0)
        P = np.take(X, self.el.conn.T, axis=0)                      # (4, ne, 3)
        D = P[PAIRS[0]] - P[PAIRS[1]]
        d = np.sqrt(np.einsum("pei,pei->pe", D, D).max(axis=0, initial=0.0))
        bound = phi[self.el.conn].min(axis=1, initial=np.inf) - d - self.radius
        self.bound_kept = (np.array(X), pose, bound)
        return bound

    def _use(self, e):
        """The barrier on the elements e (sorted)."""
        self.active = e
        self.view = ElementView(self.el, e)
        self.Ga = self.G.rows(self.view.points_index)
        points = self.view.points_index[self.view.conn]
        self.reach_patch, self.reach_spread = element_patches(self.patch[points],
                                                              self.spread[points])
        self.kept, self.reference = None, None
        self.barrier = Barrier(self.bodies, self.view, self.radius, self.weight,
                               gap=self.gap / self.radius, friction=self.friction,
                               compiled=self.full.kernels.kind == "compiled")

    def begin(self, alpha, t0):
        """A step starts from α⁰ = ``alpha`` at t₀: the set is formed again at
        its first ``move``."""
        self.start = (np.array(alpha), t0)
        self.window, self.step_h = None, None

    def move(self, t0, t1, alpha=None):
        """The step (or a part of it, from α = ``alpha``) runs from t0 to t1:
        the bodies posed at t1; the set formed again for a new step end,
        about the step's start and the part's, and friction lagged on it
        from the step's start."""
        alpha0, ts = self.start
        if self.window is None or self.window[1] != t1:
            self.barrier.at(ts)
            X0 = self.G @ alpha0
            reach = 0.0
            if self.barrier.moves:
                reach = self.barrier.carried(ts, max(t1, ts), X0)[self.el.conn].max(axis=1)
            bound = self._bound(X0)
            if alpha is not None:
                bound = np.minimum(bound, self._bound(self.G @ alpha))
            e = np.flatnonzero(bound < self.gap + reach + self.allowance)
            if not np.array_equal(e, self.active):
                self._use(e)
            self.barrier.lag(self.Ga @ alpha0, ts)
            self.step_h = self.step_h or t1 - t0        # the step as first tried
            self.barrier.set_step(self.step_h)
            self.window = (t0, t1)
        self.barrier.step_to(t0, t1)
        self.reference = None

    def missed(self, alpha0, alpha1):
        """After a step from α⁰ to α¹: whether an element outside the set may
        have come within the gap (its bound at α¹, the bodies where they
        are now); the allowances are then doubled and the set formed again
        at the next ``move``. Else each element's allowance is twice its
        move in the step, at least 2 r."""
        bound = self._bound(self.G @ alpha1).copy()
        bound[self.active] = np.inf
        move = np.linalg.norm(self.G @ (alpha1 - alpha0), axis=1)[self.el.conn].max(axis=1)
        if bound.min(initial=np.inf) >= self.gap:
            self.allowance = np.maximum(2 * self.radius, 2 * move)
            return False
        self.allowance = 2 * np.maximum(self.allowance, move)
        self.window, self.refusals = None, self.refusals + 1
        return True

    # -- the narrow phase --------------------------------------------------------
    def _reach(self, d):
        """ρ_e(d) of every element of the set: how far a move d of α (n, 3)
        can move its yarn points at most (module docstring)."""
        far = np.linalg.norm(d, axis=1)[self.columns].max(axis=1)    # each patch's
        return np.max(self.reach_spread * far[self.reach_patch], axis=0, initial=0.0)

    def near(self, alpha, step=None):
        """The elements of the set (indices into it) that can have a point
        within the gap at α, or anywhere along the update α + τ ``step``
        (τ ∈ [0, 1]); the reference taken at α if there is none since the
        bodies last moved."""
        if self.reference is None:
            lo = self.barrier.surface_distance(self._x(alpha))[0].min(axis=1, initial=np.inf)
            self.reference = (np.array(alpha), lo)
        ref, lo = self.reference
        bound = lo - self._reach(alpha - ref)
        if step is not None:
            bound -= self._reach(step)
        return np.flatnonzero(bound < self.gap)

    # -- energy, forces, tangent ---------------------------------------------
    def _x(self, alpha):
        """The set's control points Γ_A α, kept for the last α: the energy,
        forces, tangent and step filter at one state share them."""
        if self.kept is None or not np.array_equal(self.kept[0], alpha):
            self.kept = (np.array(alpha), self.Ga @ alpha)
        return self.kept[1]

    def energy(self, alpha):
        """E_c + D on the set."""
        x = self._x(alpha)
        return self.barrier.energy(x, self.near(alpha)) + self.barrier.friction_potential(x)

    def add_forces(self, alpha, out):
        """out (n, 3) += −Γ_Aᵀ ∇(E_c + D)."""
        g = np.zeros((len(self.view.points_index), 3))
        self.barrier.add_gradient(self._x(alpha), g, -1.0, self.near(alpha))
        out += self.Ga.T @ g

    def add_hessian(self, alpha, T):
        """T's values += Γ_Aᵀ ∇²(E_c + D) Γ_A (``T`` a ``SparseTangent``, a
        ``TangentPart`` or a ``DenseValues``), as

            Σ_q (c_q c_qᵀ) ⊗ H_q,   c_q = Σ_a B_qa Γ̃_{p_a},

        over the quadrature points of the elements within the gap or lagged
        (``Barrier.quadrature_hessian``; the others' H_q vanish) by
        ``QuadratureProduct``: the cost follows the contact region, not the
        set."""
        if self.product is None or self.product.T is not T.layout:
            self.product = QuadratureProduct(T.layout, self.G.cols, self.G.vals,
                                             self.el.B, (self.columns, self.patch))
        e, Hq = self.barrier.quadrature_hessian(self._x(alpha), self.near(alpha))
        self.product.add(self.view.points_index[self.view.conn[e]], Hq, T)

    def step_limit(self, alpha, dalpha):
        """``Barrier.step_limit`` on the set's points."""
        return self.barrier.step_limit(self._x(alpha), self.Ga @ dalpha,
                                       elements=self.near(alpha, dalpha))

    def swept_depth(self, alpha0, alpha1):
        """``Barrier.swept_depth`` on the set's points."""
        return self.barrier.swept_depth(self._x(alpha0), self._x(alpha1))

    def min_distance(self, alpha):
        return self.barrier.min_distance(self._x(alpha))
