"""Yarn elements: mass, stretching and bending of uniform cubic B-spline yarns.

A yarn is a uniform cubic B-spline whose control points p are the generalised
coordinates. Element (segment) e uses the control points conn[e] = (k, …, k+3)
and, at local parameter u,

    x(u) = Σ_a b_a(u) p_{conn[e, a]},   x' = Σ_a b_a'(u) p_a,   x'' = Σ_a b_a''(u) p_a,

derivatives being taken with respect to the spline parameter (one unit per
segment). X is the rest curve. With Gauss weights w_q on [0, 1] and the rest
line element W = w_q |X'|, the energies are

    E_s = ½ Σ_{e,q} W EA e²,          e = (|x'|² − |X'|²) / (2|X'|²),
    E_b = ½ Σ_{e,q} W EI (κ − κ₀)²,   κ = |x' × x''| / |x'|³,

κ₀ the curvature of X. Both depend on x only through |x'|, |x''| and x'·x'',
so they are invariant under rigid motions.

One chain rule serves both. At each (e, q) an energy density ψ(ε) depends on a
scalar measure ε of y = (x', x'') ∈ ℝ^{2×3}, and y = D p is linear in the
element's control points, D_q = [b'(u_q); b''(u_q)] (2, 4). With f₁ = W ψ'(ε),
f₂ = W ψ''(ε),

    ∂E/∂p_{ai}        = Σ_q Σ_r D_{qra} f₁ ∂ε/∂y_{ri},
    ∂²E/∂p_{ai}∂p_{bj} = Σ_q Σ_{rs} D_{qra} (f₂ ∂ε/∂y_{ri} ∂ε/∂y_{sj}
                                             + f₁ ∂²ε/∂y_{ri}∂y_{sj}) D_{qsb}.

Stretching uses ε = e, ψ = ½ EA e². Bending uses ε = c = κ² (smooth in y even
where the yarn is straight) and ψ = ½ EI (√c − κ₀)², so f₁ = ½ W EI (1 − κ₀/√c),
f₂ = ¼ W EI κ₀ c^{−3/2}: where κ₀ = 0 the density is ½ EI c, a polynomial
over |x'|⁶, and its Hessian is finite at straight configurations. Where
κ₀ > 0, ψ' and ψ'' use √(c + δ²) with a negligible δ (see ``bend_terms``).

Every point Hessian ∂²ε/∂y² is handed over in structured form,

    ∂²ε/∂y² = C ⊗ I₃ + Σ_k w_k (a_k b_kᵀ + b_k a_kᵀ),   C (2, 2), a_k, b_k ∈ ℝ^{2×3},

which costs a handful of passes over the points instead of one per entry
block.

Element DOFs are interleaved, local index 3a + i (control point a, component
i), and the assembled gradient is laid out like the control points (ncp, 3).
Everything is vectorised over elements × quadrature points; no PETSc here.
"""

import numpy as np

from knitfem.yarn import bspline

__all__ = ["YarnElements", "chain_rule", "stretch_terms", "bend_terms"]


def chain_rule(D, terms, hessian=True):
    """Element gradient and Hessian of Σ_q ψ(ε), summed over energies.

    For every energy, from its point derivatives with respect to y = (x', x''),

        G_{e,ai}    = Σ_{q,r} D_{qra} f₁ g_{eqri},
        K_{e,ai,bj} = Σ_{q,r,s} D_{qra} (f₂ g_{eqri} g_{eqsj} + f₁ H_{eqrisj}) D_{qsb},

    with H = C ⊗ I₃ + Σ_k w_k (a_k b_kᵀ + b_k a_kᵀ) and f₂ g gᵀ one more pair
    (g, g, f₂/2). The point Hessians of all energies are added first (the
    pairs by one batched product of (6, npairs) matrices) and expanded once:
    K is one matrix product with the (4nq, 16) table D_{qra} D_{qsb}.

    Parameters
    ----------
    D : (nq, 2, 4)
        Maps the element's control points to y = (x', x''): y_{qri} = D_{qra} p_{ai}.
    terms : iterable of (f1, f2, g, H), at least one
        One tuple per energy: f1, f2 (ne, nq) are W ψ'(ε) and W ψ''(ε), with
        W = w_q |X'| the rest line element; g (ne, nq, 2, 3) is ∂ε/∂y and
        H = (C, pairs) is ∂²ε/∂y²: C (ne, nq, 2, 2), pairs a list of
        (a, b, w), a and b (ne, nq, 2, 3), w (ne, nq) (ignored unless
        ``hessian``).
    hessian : bool
        Form K as well as G.

    Returns
    -------
    G : (ne, 12)
        ∂E/∂p, local DOF 3a + i.
    K : (ne, 12, 12) or None
        ∂²E/∂p∂p, exactly symmetric.
    """
    gy, C, pairs = 0.0, 0.0, []
    for f1, f2, g, H in terms:
        gy = gy + f1[..., None, None] * g
        if hessian:
            C = C + f1[..., None, None] * H[0]
            pairs += [(a, b, f1 * w) for a, b, w in H[1]] + [(g, g, 0.5 * f2)]
    ne, nq = gy.shape[:2]
    G = np.matmul(D.reshape(-1, 4).T, gy.reshape(ne, -1, 3)).reshape(ne, 12)
    if not hessian:
        return G, None
    # point Hessians Hy = C ⊗ I₃ + S + Sᵀ, S = Σ_k w_k a_k b_kᵀ (6×6 at each point)
    w = np.stack([w for _, _, w in pairs], axis=2)[..., None, None]
    a = (np.stack([a for a, _, _ in pairs], axis=2) * w).reshape(ne * nq, -1, 6)
    b = np.stack([b for _, b, _ in pairs], axis=2).reshape(ne * nq, -1, 6)
    S = np.matmul(a.transpose(0, 2, 1), b)
    Hy = (S + S.transpose(0, 2, 1)).reshape(ne, nq, 2, 3, 2, 3)
    for i in range(3):
        Hy[:, :, :, i, :, i] += C
    DD = np.einsum("qra,qsb->qrsab", D, D).reshape(4 * nq, 16)
    Hy = Hy.transpose(0, 3, 5, 1, 2, 4).reshape(9 * ne, 4 * nq)  # (e i j, q r s)
    K = (Hy @ DD).reshape(ne, 3, 3, 4, 4).transpose(0, 3, 1, 4, 2).reshape(ne, 12, 12)
    return G, 0.5 * (K + K.transpose(0, 2, 1))      # symmetric to the last bit


def stretch_terms(y, Xp2, W, EA, hessian=True, yref=None):
    """Stretching: ε = e = (|x'|² − |X'|²)/(2|X'|²), ψ = ½ EA e².

        ∂e/∂x' = x'/|X'|²,   ∂²e/∂x'² = I/|X'|²,   ∂e/∂x'' = 0,

    so ∂²e/∂y² = diag(1/|X'|², 0) ⊗ I₃ and no pairs.

    With ``yref`` = (r', r'') of a reference state r (the last Newton
    iterate), the axial force of the geometric term f₁ ∂²e/∂y² is the mixed
    integration point (MIP) one of Magisano, Leonetti & Garcea (CMAME 313,
    2017), EA ē with the strain linearised from r,

        ē = e(r) + ∂e/∂x'(r)·(x' − r') = (x'·r' − ½|r'|² − ½|X'|²)/|X'|²
          = e(x) − ½|x' − r'|²/|X'|²:

    the Newton matrix of the stretch with its axial force an unknown of its
    own at each point, condensed (the residual is unchanged). ē = e at x = r,
    so the solution is the same; Newton no longer sees the axial force that
    the linearisation of a turn would give a stiff yarn.

    Parameters
    ----------
    y : (ne, nq, 2, 3)
        (x', x'') at every quadrature point.
    Xp2, W : (ne, nq)
        |X'|² and the rest line element w_q |X'|.
    EA : float

    Returns
    -------
    f1, f2, g, H
        Arguments of ``chain_rule`` (H is None unless ``hessian``).
    """
    u = y[:, :, 0]
    if yref is None:
        e = 0.5 * (np.einsum("eqi,eqi->eq", u, u) - Xp2) / Xp2
    else:
        r = yref[:, :, 0]
        e = (np.einsum("eqi,eqi->eq", u, r) - 0.5 * np.einsum("eqi,eqi->eq", r, r)
             - 0.5 * Xp2) / Xp2
    g = np.zeros_like(y)
    g[:, :, 0] = u / Xp2[..., None]
    H = None
    if hessian:
        C = np.zeros(Xp2.shape + (2, 2))
        C[..., 0, 0] = 1.0 / Xp2
        H = (C, [])
    return EA * W * e, EA * W, g, H


def bend_terms(y, kappa0, W, EI, delta, hessian=True):
    """Bending: ε = c = κ² = A/B³, ψ = ½ EI (√c − κ₀)², with u = x', v = x'',

        A = |u × v|² = |u|²|v|² − (u·v)²,      B = |u|²,
        ∂A/∂u = 2 v × (u × v) = 2|v|²u − 2(u·v)v,
        ∂A/∂v = 2 (u × v) × u = 2|u|²v − 2(u·v)u,
        ∂²A/∂u² = 2|v|²I − 2vvᵀ,   ∂²A/∂v² = 2|u|²I − 2uuᵀ,
        ∂²A/∂u∂v = 4uvᵀ − 2vuᵀ − 2(u·v)I,
        B' = (2u, 0),   B'' = diag(2I, 0),
        c'  = A'B⁻³ − 3AB⁻⁴B',
        c'' = A''B⁻³ − 3B⁻⁴(A'B'ᵀ + B'A'ᵀ) + 12AB⁻⁵B'B'ᵀ − 3AB⁻⁴B'',
        ψ'(c) = ½ EI (1 − κ₀/√c),   ψ''(c) = ¼ EI κ₀ c^{−3/2}.

    In ψ' and ψ'' only, √c is regularised as s = √(c + δ²) so that nothing is
    divided by zero where κ₀ > 0 and the yarn is straight (the energy itself
    has a cone point there, |κ| − κ₀). δ is far below any curvature that
    matters, so s = √c to rounding elsewhere; where κ₀ = 0, ψ' = ½ EI and
    ψ'' = 0 exactly.

    Parameters
    ----------
    y : (ne, nq, 2, 3)
        (x', x'') at every quadrature point.
    kappa0, W : (ne, nq)
        Rest curvature and rest line element w_q |X'|.
    EI, delta : float

    Returns
    -------
    f1, f2, g, H
        Arguments of ``chain_rule`` (H is None unless ``hessian``).
    """
    u, v = y[:, :, 0], y[:, :, 1]
    w = np.cross(u, v)
    A = np.einsum("eqi,eqi->eq", w, w)
    B = np.einsum("eqi,eqi->eq", u, u)
    c = A / B**3
    s = np.sqrt(c + delta**2)
    f1 = 0.5 * EI * W * (1.0 - kappa0 / s)
    f2 = 0.25 * EI * W * kappa0 / s**3

    dA = np.stack([2.0 * np.cross(v, w), 2.0 * np.cross(w, u)], axis=2)
    g = dA / B[..., None, None] ** 3                  # c' = A'B⁻³ − 3AB⁻⁴B'
    g[:, :, 0] -= (6.0 * A / B**4)[..., None] * u
    if not hessian:
        return f1, f2, g, None

    # c'' = A''/B³ − 3B⁻⁴(A'B'ᵀ + B'A'ᵀ) + 12AB⁻⁵B'B'ᵀ − 3AB⁻⁴B'' in parts:
    # A'' = 2 G̃ ⊗ I₃ − 2zzᵀ + 4(UVᵀ + VUᵀ), G̃ = [|v|² −u·v; −u·v |u|²],
    # z = (v, u), U = (u, 0), V = (0, v); B' = 2U, B'' = 2 diag(1, 0) ⊗ I₃
    vv = np.einsum("eqi,eqi->eq", v, v)
    uv = np.einsum("eqi,eqi->eq", u, v)
    P, T = 1.0 / B**3, 6.0 * A / B**4
    C = np.empty(B.shape + (2, 2))
    C[..., 0, 0] = 2.0 * P * vv - T
    C[..., 0, 1] = C[..., 1, 0] = -2.0 * P * uv
    C[..., 1, 1] = 2.0 * P * B
    zero = np.zeros_like(u)
    z = np.stack([v, u], axis=2)
    U = np.stack([u, zero], axis=2)
    V = np.stack([zero, v], axis=2)
    pairs = [(z, z, -P), (U, V, 4.0 * P), (dA, U, -6.0 / B**4), (U, U, 24.0 * A / B**5)]
    H = (C, pairs)
    return f1, f2, g, H


class YarnElements:
    """Cubic B-spline yarn elements: constant mass, stretching and bending.

    Parameters
    ----------
    X : (ncp, 3)
        Rest control points (several yarns may be concatenated).
    conn : (ne, 4) int
        Control points of every element, (k, k+1, k+2, k+3) within one yarn.
    rho : float
        Linear density ρ (kg/m).
    EA : float
        Axial stiffness (N).
    EI : float
        Bending stiffness (N m²).
    nq : int
        Gauss points per element (4 integrates b_a b_b exactly).

    Attributes
    ----------
    B, dB, ddB : (nq, 4)
        Basis functions and their first and second derivatives at the points.
    weights : (nq,)
        Gauss weights on [0, 1].
    D : (nq, 2, 4)
        [dB; ddB]: (x', x'') = D p at each point (see ``chain_rule``).
    dof : (ne, 12)
        Global interleaved DOF 3 conn[e, a] + i of local DOF 3a + i.
    Xp : (ne, nq, 3)
        Rest tangent X'.
    Xp2, jac : (ne, nq)
        |X'|² and |X'|.
    W : (ne, nq)
        Rest line element w_q |X'|.
    kappa0 : (ne, nq)
        Natural curvature κ₀: 0 for a ``natural`` (straight) yarn, else the
        rest curve's, |X' × X''| / |X'|³.
    delta : float
        Curvature regularisation of ``bend_terms``: 10⁻¹² / mean |X'|.
    """

    def __init__(self, X, conn, rho, EA, EI, nq=4, natural=False):
        self.X = np.asarray(X, dtype=float)
        self.conn = np.asarray(conn, dtype=np.int64).reshape(-1, 4)
        self.ncp, self.ne, self.nq = len(self.X), len(self.conn), nq
        self.rho, self.EA, self.EI = float(rho), float(EA), float(EI)
        uq, self.weights = bspline.gauss(nq)
        self.B, self.dB, self.ddB = (bspline.basis(uq, nu) for nu in range(3))
        self.D = np.stack([self.dB, self.ddB], axis=1)
        self.dof = (3 * self.conn[:, :, None] + np.arange(3)).reshape(-1, 12)
        Y = self.tangents(self.X)
        self.Xp = Y[:, :, 0]
        self.Xp2 = np.einsum("eqi,eqi->eq", self.Xp, self.Xp)
        self.jac = np.sqrt(self.Xp2)
        self.W = self.weights * self.jac
        self.natural = natural
        self.kappa0 = np.zeros_like(self.W) if natural else self._curvature(Y)
        self.delta = 1e-12 / self.jac.mean() if self.ne else 1e-12
        self._sampler = None                 # of ``points``

    # -- geometry ------------------------------------------------------------
    def tangents(self, x):
        """y = (x', x'') at every quadrature point, (ne, nq, 2, 3).

        y_{eqri} = Σ_a D_{qra} x_{conn[e, a], i}, D_q = [b'(u_q); b''(u_q)].
        """
        nq = len(self.D)
        y = np.matmul(self.D.reshape(2 * nq, 4), np.asarray(x)[self.conn])
        return y.reshape(-1, nq, 2, 3)

    def points(self, x):
        """Curve points x(u_q) = Σ_a b_a(u_q) p_{e,a} at every quadrature
        point, (ne, nq, 3): one product with the sparse (ne nq, ncp) matrix
        of the b_a, made at the first call."""
        if self._sampler is None:
            from scipy import sparse

            ne, nq = self.ne, len(self.B)
            self._sampler = sparse.csr_matrix(
                (np.broadcast_to(self.B, (ne, nq, 4)).ravel(),
                 (np.repeat(np.arange(ne * nq), 4),
                  np.repeat(self.conn, nq, axis=0).ravel())), shape=(ne * nq, self.ncp))
        return (self._sampler @ np.asarray(x)).reshape(self.ne, -1, 3)

    @staticmethod
    def _curvature(y):
        w = np.cross(y[:, :, 0], y[:, :, 1])
        u2 = np.einsum("eqi,eqi->eq", y[:, :, 0], y[:, :, 0])
        return np.sqrt(np.einsum("eqi,eqi->eq", w, w)) / u2**1.5

    def strain(self, x):
        """Green–Lagrange strain e = (|x'|² − |X'|²)/(2|X'|²), (ne, nq)."""
        u = self.tangents(x)[:, :, 0]
        return 0.5 * (np.einsum("eqi,eqi->eq", u, u) - self.Xp2) / self.Xp2

    def curvature(self, x):
        """Curvature κ = |x' × x''| / |x'|³, (ne, nq)."""
        return self._curvature(self.tangents(x))

    def rest_length(self):
        """Rest length Σ_{e,q} w_q |X'| of all elements."""
        return float(self.W.sum())

    # -- mass ----------------------------------------------------------------
    def mass_elements(self):
        """Scalar element mass m_ab = Σ_q w_q ρ |X'| b_a b_b, (ne, 4, 4).

        The 3-D element mass is m ⊗ I₃ in the interleaved DOFs 3a + i.
        """
        return np.einsum("eq,qa,qb->eab", self.rho * self.W, self.B, self.B)

    # -- energies ------------------------------------------------------------
    def stretch_energy(self, x):
        """E_s = ½ Σ_{e,q} w_q |X'| EA e²."""
        return 0.5 * self.EA * float(np.sum(self.W * self.strain(x) ** 2))

    def bend_energy(self, x):
        """E_b = ½ Σ_{e,q} w_q |X'| EI (κ − κ₀)²."""
        dk = self.curvature(x) - self.kappa0
        return 0.5 * self.EI * float(np.sum(self.W * dk**2))

    def energy(self, x):
        """E = E_s + E_b."""
        return self.stretch_energy(x) + self.bend_energy(x)

    def _terms(self, y, hessian, yref=None):
        """Point derivatives of every energy with a non-zero stiffness
        (``yref``: the stretch's MIP reference, see ``stretch_terms``).

        Stretching is always included (it is all zeros when EA = 0), so that
        ``chain_rule`` receives at least one energy.
        """
        yield stretch_terms(y, self.Xp2, self.W, self.EA, hessian, yref)
        if self.EI != 0.0:
            yield bend_terms(y, self.kappa0, self.W, self.EI, self.delta, hessian)

    def element_gradient(self, x):
        """∂E/∂p per element, (ne, 12), local DOF 3a + i."""
        terms = self._terms(self.tangents(x), hessian=False)
        return chain_rule(self.D, terms, hessian=False)[0]

    def element_hessian(self, x, xref=None):
        """∂²E/∂p∂p per element, (ne, 12, 12), symmetric, local DOF 3a + i;
        with ``xref``, the MIP Newton matrix whose axial force is linearised
        from the state xref (``stretch_terms``)."""
        yref = None if xref is None else self.tangents(xref)
        return chain_rule(self.D, self._terms(self.tangents(x), True, yref))[1]

    def assemble_vector(self, Ge):
        """Σ_e of element vectors (ne, 12) into control-point rows, (ncp, 3).

        One ``np.bincount`` over the global DOFs ``dof``.
        """
        return np.bincount(self.dof.ravel(), weights=np.ravel(Ge),
                           minlength=3 * self.ncp).reshape(self.ncp, 3)

    def gradient(self, x):
        """Assembled ∂E/∂p, (ncp, 3) like the control points."""
        return self.assemble_vector(self.element_gradient(x))
