# cython: language_level=3, boundscheck=False, wraparound=False
# cython: cdivision=True, initializedcheck=False
"""Compiled yarn kernels: loops over elements × quadrature points in C.

The same mathematics as ``knitfem.yarn.elements`` (its module docstring gives the
chain rule, ``stretch_terms`` and ``bend_terms`` the point derivatives), one
point at a time. At every point (e, q), with y = (x', x'') = D_q p_e,

    gy  = Σ_energies f₁ ∂ε/∂y                                 (2 × 3),
    Hy  = Σ_energies f₁ ∂²ε/∂y² + f₂ ∂ε/∂y ∂ε/∂yᵀ              (6 × 6),

and the element sums G_{e,ai} = Σ_{q,r} D_{qra} gy_{ri},
K_{e,ai,bj} = Σ_{q,r,s} D_{qra} Hy_{ri,sj} D_{qsb} are added straight into
the caller's arrays: the gradient into control-point rows, the Hessian into
CSR values through each element entry's slot, and the reduced Hessian
Γᵀ K Γ into a dense matrix (``reduce_tangent``) or at given positions of a
sparse one's values (``reduce_tangent_into``). Nothing here allocates per
call except its work arrays; no Python object is touched inside the loops.

Built by ``pip install -e .`` (setup.py); ``knitfem.yarn.kernels`` chooses between
these kernels and the numpy reference.
"""

from libc.math cimport sqrt
from libc.stdint cimport int32_t, int64_t
from libc.string cimport memcpy, memset

from cython.view cimport array as cvarray

from knitfem.blas cimport dgemm_

# Raised whenever a kernel's arguments change: knitfem.yarn.kernels refuses an
# extension built from an older source (run make setup).
VERSION = 5


cdef inline void cross(const double *a, const double *b, double *c) nogil:
    c[0] = a[1] * b[2] - a[2] * b[1]
    c[1] = a[2] * b[0] - a[0] * b[2]
    c[2] = a[0] * b[1] - a[1] * b[0]


cdef inline double dot(const double *a, const double *b) nogil:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


cdef inline void add_outer(double *H, const double *a, const double *b,
                           double w) nogil:
    """The 3 × 3 block H (row stride 6) += w a bᵀ."""
    cdef int m, n
    for m in range(3):
        for n in range(3):
            H[6 * m + n] += w * a[m] * b[n]


cdef inline void point_terms(const double *y, double Xp2, double W, double kappa0,
                             double EA, double EI, double delta, double *gy,
                             double *Hy, bint hessian, const double *r) nogil:
    """gy (6) and Hy (6 × 6, symmetric) at one point; y = (u, v).

    Stretching: f₁ = EA W e, f₂ = EA W, ∂e/∂y = (u/|X'|², 0),
    with e = (u·r − ½|r|² − ½|X'|²)/|X'|² in Hy (not gy) when the reference
    tangent r = r' is given (not NULL): the MIP axial force of
    ``yarn.stretch_terms``,
    ∂²e/∂y² = diag(1/|X'|², 0) ⊗ I₃. Bending (EI ≠ 0): f₁, f₂, c' and c'' of
    ``yarn.bend_terms``; c'' = C ⊗ I₃ − 2P zzᵀ + 4P (UVᵀ + VUᵀ)
    − 6B⁻⁴ (A'Uᵀ + UA'ᵀ) + 48AB⁻⁵ UUᵀ, z = (v, u), U = (u, 0), V = (0, v),
    added by 3 × 3 blocks H₀₀, H₀₁ (H₁₀ = H₀₁ᵀ) and H₁₁.
    """
    cdef const double *u = y
    cdef const double *v = y + 3
    cdef double w[3]
    cdef double dA[6]
    cdef double g[6]
    cdef double e, f1, f2, A, B, P, T, c, s, vv, uv, c00, c01, c11, wz
    cdef double *H00 = Hy
    cdef double *H01 = Hy + 3
    cdef double *H11 = Hy + 21
    cdef int i, m, n
    # stretching
    if r == NULL:
        e = 0.5 * (dot(u, u) - Xp2) / Xp2
    else:
        e = (dot(u, r) - 0.5 * dot(r, r) - 0.5 * Xp2) / Xp2
    f1 = EA * W * e
    f2 = EA * W / (Xp2 * Xp2)
    for i in range(3):
        gy[i] = f1 * u[i] / Xp2
        gy[3 + i] = 0.0
    if hessian:
        memset(Hy, 0, 36 * sizeof(double))
        add_outer(H00, u, u, f2)
        for i in range(3):
            H00[7 * i] += f1 / Xp2
    if EI != 0.0:
        # bending
        cross(u, v, w)
        A = dot(w, w)
        B = dot(u, u)
        P = 1.0 / (B * B * B)
        c = A * P
        s = sqrt(c + delta * delta)
        f1 = 0.5 * EI * W * (1.0 - kappa0 / s)
        f2 = 0.25 * EI * W * kappa0 / (s * s * s)
        T = 6.0 * c / B
        cross(v, w, dA)
        cross(w, u, dA + 3)
        for m in range(6):
            dA[m] *= 2.0
            g[m] = dA[m] * P
        for i in range(3):
            g[i] -= T * u[i]
        for m in range(6):
            gy[m] += f1 * g[m]
        if hessian:
            vv = dot(v, v)
            uv = dot(u, v)
            c00 = f1 * (2.0 * P * vv - T)
            c01 = -f1 * 2.0 * P * uv
            c11 = f1 * 2.0 * P * B
            for i in range(3):
                H00[7 * i] += c00
                H01[7 * i] += c01
                H11[7 * i] += c11
            wz = -2.0 * f1 * P                   # −2P zzᵀ
            add_outer(H00, v, v, wz)
            add_outer(H01, v, u, wz)
            add_outer(H11, u, u, wz)
            add_outer(H01, u, v, 4.0 * f1 * P)   # 4P (UVᵀ + VUᵀ)
            wz = -6.0 * f1 * P / B               # −6B⁻⁴ (A'Uᵀ + UA'ᵀ)
            add_outer(H00, dA, u, wz)
            add_outer(H00, u, dA, wz)
            add_outer(H01, u, dA + 3, wz)
            add_outer(H00, u, u, 8.0 * f1 * T / B)   # 48AB⁻⁵ UUᵀ
            add_outer(H00, g, g, f2)             # f₂ c'c'ᵀ
            add_outer(H01, g, g + 3, f2)
            add_outer(H11, g + 3, g + 3, f2)
    if hessian:
        for m in range(3):                       # H₁₀ = H₀₁ᵀ
            for n in range(3):
                Hy[6 * (3 + n) + m] = H01[6 * m + n]


cdef inline void element_y(const double *x, const int64_t *ce, const double *d,
                           double *y) nogil:
    """y = (x', x'') = D_q p_e at one point; ce the element's control points,
    d = D_q (2 × 4)."""
    cdef int r, a, i, m
    cdef const double *p
    for m in range(6):
        y[m] = 0.0
    for a in range(4):
        p = x + 3 * ce[a]
        for r in range(2):
            for i in range(3):
                y[3 * r + i] += d[4 * r + a] * p[i]


cdef void element_hessian(const double *x, const int64_t *ce, const double *D,
                          const double *Xp2, const double *W, const double *kappa0,
                          Py_ssize_t nq, double EA, double EI, double delta,
                          double *K, const double *xref) nogil:
    """K_e (12 × 12, exactly symmetric) of one element: at every point
    Z = Hy (D_q ⊗ I₃) (6 × 12), then K += (D_q ⊗ I₃)ᵀ Z on the 3 × 3 blocks
    (a, b ≥ a), mirrored at the end. D (nq, 2, 4); Xp2, W, kappa0 (nq);
    xref the MIP reference state (ncp, 3) or NULL."""
    cdef double y[6]
    cdef double yr[6]
    cdef const double *r = NULL
    cdef double gy[6]
    cdef double Hy[36]
    cdef double Z[72]
    cdef const double *d
    cdef double h
    cdef Py_ssize_t q
    cdef int a, b, m, n, i, j
    memset(K, 0, 144 * sizeof(double))
    for q in range(nq):
        d = D + 8 * q
        element_y(x, ce, d, y)
        if xref != NULL:
            element_y(xref, ce, d, yr)
            r = yr
        point_terms(y, Xp2[q], W[q], kappa0[q], EA, EI, delta, gy, Hy, True, r)
        for m in range(6):
            for b in range(4):
                for j in range(3):
                    Z[12 * m + 3 * b + j] = d[b] * Hy[6 * m + j] + d[4 + b] * Hy[6 * m + 3 + j]
        for a in range(4):                       # blocks b >= a
            for i in range(3):
                for n in range(3 * a, 12):
                    K[12 * (3 * a + i) + n] += d[a] * Z[12 * i + n] + d[4 + a] * Z[12 * (3 + i) + n]
    for m in range(12):                          # exactly symmetric
        for n in range(m):
            if m // 3 == n // 3:
                h = 0.5 * (K[12 * m + n] + K[12 * n + m])
                K[12 * n + m] = h
            K[12 * m + n] = K[12 * n + m]


cdef void element_gradient(const double *x, const int64_t *ce, const double *D,
                           const double *Xp2, const double *W, const double *kappa0,
                           Py_ssize_t nq, double EA, double EI, double delta,
                           double *G) nogil:
    """G_e (12) of one element: G_{ai} = Σ_{q,r} D_{qra} gy_{ri}."""
    cdef double y[6]
    cdef double gy[6]
    cdef double Hy[36]
    cdef const double *d
    cdef Py_ssize_t q
    cdef int a, i
    memset(G, 0, 12 * sizeof(double))
    for q in range(nq):
        d = D + 8 * q
        element_y(x, ce, d, y)
        point_terms(y, Xp2[q], W[q], kappa0[q], EA, EI, delta, gy, Hy, False, NULL)
        for a in range(4):
            for i in range(3):
                G[3 * a + i] += d[a] * gy[i] + d[4 + a] * gy[3 + i]


# Arguments common to the kernels below: x (ncp, 3) the control points;
# conn (ne, 4) the elements' control points; D (nq, 2, 4) = [b'; b''] at the
# Gauss points; Xp2, W, kappa0 (ne, nq) = |X'|², w_q |X'|, κ₀; EA, EI, delta
# the stiffnesses and the curvature regularisation of ``yarn.bend_terms``;
# xref (ncp, 3) or None the MIP reference state of ``yarn.stretch_terms``.

def add_gradient(const double[:, ::1] x, const int64_t[:, ::1] conn,
                 const double[:, :, ::1] D, const double[:, ::1] Xp2,
                 const double[:, ::1] W, const double[:, ::1] kappa0,
                 double EA, double EI, double delta, double scale,
                 double[:, ::1] out):
    """out[conn[e, a], i] += scale · ∂E/∂p_{e,ai}, summed over all elements."""
    cdef double G[12]
    cdef Py_ssize_t e, ne = conn.shape[0], nq = D.shape[0]
    cdef int a, i
    if ne == 0:
        return
    with nogil:
        for e in range(ne):
            element_gradient(&x[0, 0], &conn[e, 0], &D[0, 0, 0], &Xp2[e, 0],
                             &W[e, 0], &kappa0[e, 0], nq, EA, EI, delta, G)
            for a in range(4):
                for i in range(3):
                    out[conn[e, a], i] += scale * G[3 * a + i]


def element_gradients(const double[:, ::1] x, const int64_t[:, ::1] conn,
                      const double[:, :, ::1] D, const double[:, ::1] Xp2,
                      const double[:, ::1] W, const double[:, ::1] kappa0,
                      double EA, double EI, double delta, double[:, ::1] out):
    """out[e] = ∂E/∂p_e (ne, 12), local DOF 3a + i."""
    cdef Py_ssize_t e, ne = conn.shape[0], nq = D.shape[0]
    if ne == 0:
        return
    with nogil:
        for e in range(ne):
            element_gradient(&x[0, 0], &conn[e, 0], &D[0, 0, 0], &Xp2[e, 0],
                             &W[e, 0], &kappa0[e, 0], nq, EA, EI, delta,
                             &out[e, 0])


def element_hessians(const double[:, ::1] x, const int64_t[:, ::1] conn,
                     const double[:, :, ::1] D, const double[:, ::1] Xp2,
                     const double[:, ::1] W, const double[:, ::1] kappa0,
                     double EA, double EI, double delta, double[:, :, ::1] out,
                     const double[:, ::1] xref=None):
    """out[e] = ∂²E/∂p_e² (ne, 12, 12), local DOF 3a + i."""
    cdef Py_ssize_t e, ne = conn.shape[0], nq = D.shape[0]
    cdef const double *pref = NULL if xref is None else &xref[0, 0]
    if ne == 0:
        return
    with nogil:
        for e in range(ne):
            element_hessian(&x[0, 0], &conn[e, 0], &D[0, 0, 0], &Xp2[e, 0],
                            &W[e, 0], &kappa0[e, 0], nq, EA, EI, delta,
                            &out[e, 0, 0], pref)


def hessian_values(const double[:, ::1] x, const int64_t[:, ::1] conn,
                   const double[:, :, ::1] D, const double[:, ::1] Xp2,
                   const double[:, ::1] W, const double[:, ::1] kappa0,
                   double EA, double EI, double delta,
                   const int64_t[:, :, ::1] block, const int64_t[:, ::1] stride,
                   double[::1] values, const double[:, ::1] xref=None):
    """values = Σ_e K_e, zeroed first: the 3 × 3 block (a, b) of K_e is added
    at values[block[e, a, b] + stride[e, a] i + j] (CSR rows of one control
    point are ``stride`` apart)."""
    cdef double K[144]
    cdef Py_ssize_t e, ne = conn.shape[0], nq = D.shape[0]
    cdef int a, b, i, j
    cdef double *v
    cdef const double *pref = NULL if xref is None else &xref[0, 0]
    if values.shape[0]:
        memset(&values[0], 0, values.shape[0] * sizeof(double))
    if ne == 0:
        return
    with nogil:
        for e in range(ne):
            element_hessian(&x[0, 0], &conn[e, 0], &D[0, 0, 0], &Xp2[e, 0],
                            &W[e, 0], &kappa0[e, 0], nq, EA, EI, delta, K, pref)
            for a in range(4):
                for b in range(4):
                    v = &values[block[e, a, b]]
                    for i in range(3):
                        for j in range(3):
                            v[stride[e, a] * i + j] += K[12 * (3 * a + i) + 3 * b + j]



DEF CHUNK = 64             # points whose rows Y are formed, then multiplied


cdef void chunk_rows(const double *values, const int64_t *indptr,
                     const int64_t *neighbour, const int64_t *gcols,
                     const double *gvals, int nw, const int32_t *gmap, int w,
                     bint own, const int64_t *points, int count, double *Y,
                     double *G) nogil:
    """Y_p = Σ_q K_pq Γ̃_q (w × 6 a point, see ``reduce_tangent``) and the
    row Γ̃_p (G, nw a point) for ``count`` points."""
    cdef int c, t, ij
    cdef int64_t p, k, q, at, length
    cdef double gv
    cdef double kv[6]
    cdef double *y
    cdef const int64_t *cq
    cdef const double *vq
    memset(Y, 0, count * 6 * w * sizeof(double))
    for c in range(count):
        p = points[c]
        memcpy(G + c * nw, gvals + p * nw, nw * sizeof(double))
        length = indptr[p + 1] - indptr[p]
        y = Y + c * 6 * w
        for k in range(indptr[p], indptr[p + 1]):
            q = neighbour[k]
            at = 9 * indptr[p] + 3 * (k - indptr[p])
            kv[0] = values[at]
            kv[1] = values[at + 1]
            kv[2] = values[at + 2]
            kv[3] = values[at + 3 * length + 1]
            kv[4] = values[at + 3 * length + 2]
            kv[5] = values[at + 6 * length + 2]
            vq = gvals + q * nw
            if own:                              # q's columns are the group's
                for t in range(nw):
                    gv = vq[t]
                    for ij in range(6):
                        y[6 * t + ij] += kv[ij] * gv
            else:
                cq = gcols + q * nw
                for t in range(nw):
                    gv = vq[t]
                    for ij in range(6):
                        y[6 * gmap[cq[t]] + ij] += kv[ij] * gv


cdef void group_product(Py_ssize_t g, const double *values, const int64_t *indptr,
                        const int64_t *neighbour, const int64_t *gcols,
                        const double *gvals, int nw, const int64_t *order,
                        const int64_t *start, const int32_t *gmap, int nvolume,
                        int w, double *Y, double *G, double *B) nogil:
    """B (nw × 6w, row-major) = Σ_p Γ̃_pᵀ Y_p over group g's points (the
    R^{ij}[key, reach] of ``reduce_tangent``), CHUNK points at a time."""
    cdef int m = 6 * w, count
    cdef double one = 1.0
    cdef double beta = 0.0
    cdef int64_t b0
    for b0 in range(start[g], start[g + 1], CHUNK):
        count = <int>min(CHUNK, start[g + 1] - b0)
        chunk_rows(values, indptr, neighbour, gcols, gvals, nw, gmap + g * nvolume,
                   w, w == nw, order + b0, count, Y, G)
        # B (nw × m, row-major) (+)= Gᵀ Y: column-major Bᵀ = Yᵀ G
        dgemm_("N", "T", &m, &nw, &count, &one, Y, &m, G, &nw, &beta, B, &m)
        beta = 1.0


cdef void all_groups(const double *values, const int64_t *indptr,
                     const int64_t *neighbour, const int64_t *gcols, const double *gvals,
                     int nw, const int64_t *order, const int64_t *start,
                     const int64_t *width, const int32_t *gmap, int nvolume,
                     Py_ssize_t ng, double *Y, double *G, double *B,
                     double *R6, const int64_t *key, const int64_t *reach,
                     Py_ssize_t maxw, const int64_t *first, const int64_t *pos,
                     double *out, Py_ssize_t n) nogil:
    """Every group's B (``group_product``) added where it goes: into R6
    (nvolume × nvolume × 6) at [key, reach] where R6 is given
    (``reduce_tangent``), else into out at ``pos`` from first[g]
    (``reduce_tangent_into``, its docstring the layout)."""
    cdef Py_ssize_t g, c, u
    cdef int w, m, ij
    cdef int64_t at, p
    cdef int lower[3]
    lower[0] = 1
    lower[1] = 2
    lower[2] = 4
    for g in range(ng):
        w = <int>width[g]
        m = 6 * w
        group_product(g, values, indptr, neighbour, gcols, gvals, nw, order, start,
                      gmap, nvolume, w, Y, G, B)
        for c in range(nw):
            for u in range(w):
                if R6 != NULL:
                    at = 6 * (key[g * nw + c] * nvolume + reach[g * maxw + u])
                    for ij in range(6):
                        R6[at + ij] += B[c * m + 6 * u + ij]
                    continue
                at = first[g] + 9 * (c * w + u)
                for ij in range(9):
                    p = pos[at + ij]
                    if p < n:
                        out[p] += B[c * m + 6 * u + (ij if ij < 6 else lower[ij - 6])]

def reduce_tangent(const double[::1] values, const int64_t[::1] indptr,
                   const int64_t[::1] neighbour, const int64_t[:, ::1] gcols,
                   const double[:, ::1] gvals, const int64_t[::1] order,
                   const int64_t[::1] start, const int64_t[:, ::1] key,
                   const int64_t[:, ::1] reach, const int64_t[::1] width,
                   const int32_t[:, ::1] gmap, double[:, ::1] out):
    """out (3nv × 3nv) = Γᵀ K Γ, K (local rows) given by its CSR values.

    K's values are in the layout of ``ElementPattern.blocks3`` over the
    scalar pattern (indptr, neighbour): block K_pq[i, j] of the k-th
    neighbour q of p sits at 9 indptr[p] + 3 i len(p) + 3k + j. Γ̃ has the
    rows (gcols, gvals) (ncp, nw). The points are grouped, group g being
    order[start[g]:start[g + 1]]: points whose rows of Γ̃ have the columns
    key[g] (nw), and whose neighbours q reach the width[g] columns
    reach[g, :width[g]] (numbered by gmap[g, column]). For each group and
    each of the component pairs ij = (0,0), (0,1), (0,2), (1,1), (1,2), (2,2),

        Y^{ij}_p = Σ_q K_pq[i, j] Γ̃_q   (over the reached columns),
        R^{ij}[key, reach] += Σ_p Γ̃_pᵀ Y^{ij}_p   (dgemm, CHUNK points at once),

    then out[(c,i), (d,j)] = R^{ij}_{cd} and R^{ji} = (R^{ij})ᵀ (K symmetric).
    """
    cdef Py_ssize_t ng = start.shape[0] - 1, nw = gcols.shape[1]
    cdef Py_ssize_t nv = out.shape[0] // 3, maxw = reach.shape[1]
    cdef Py_ssize_t c, d
    cdef double[:, :, ::1] R6 = cvarray((nv, nv, 6), sizeof(double), "d")
    cdef double[::1] Y = cvarray((CHUNK * 6 * maxw,), sizeof(double), "d")
    cdef double[::1] G = cvarray((CHUNK * nw,), sizeof(double), "d")
    cdef double[::1] B = cvarray((nw * 6 * maxw,), sizeof(double), "d")
    cdef int pair_i[6]
    cdef int pair_j[6]
    cdef int ij
    pair_i[:] = [0, 0, 0, 1, 1, 2]
    pair_j[:] = [0, 1, 2, 1, 2, 2]
    with nogil:
        memset(&R6[0, 0, 0], 0, nv * nv * 6 * sizeof(double))
        all_groups(&values[0], &indptr[0], &neighbour[0], &gcols[0, 0], &gvals[0, 0],
                   <int>nw, &order[0], &start[0], &width[0], &gmap[0, 0],
                   <int>gmap.shape[1], ng, &Y[0], &G[0], &B[0], &R6[0, 0, 0],
                   &key[0, 0], &reach[0, 0], maxw, NULL, NULL, NULL, 0)
        for c in range(nv):
            for d in range(nv):
                for ij in range(6):
                    out[3 * c + pair_i[ij], 3 * d + pair_j[ij]] = R6[c, d, ij]
                    out[3 * d + pair_j[ij], 3 * c + pair_i[ij]] = R6[c, d, ij]


def reduce_tangent_into(const double[::1] values, const int64_t[::1] indptr,
                        const int64_t[::1] neighbour, const int64_t[:, ::1] gcols,
                        const double[:, ::1] gvals, const int64_t[::1] order,
                        const int64_t[::1] start, const int64_t[::1] width,
                        const int32_t[:, ::1] gmap, const int64_t[::1] first,
                        const int64_t[::1] pos, double[::1] out):
    """out[pos] += the entries of Γᵀ K Γ, group by group (the arguments as
    ``reduce_tangent``'s): group g's R^{ij}_{cd} (c its key's k-th column,
    d its reach's u-th) goes to pos[first[g] + 9 (k w + u) + s], s < 6 its
    place (3c + i, 3d + j) for the pair ij, and s = 6, 7, 8 the transposed
    place (3d + j, 3c + i) of the pairs i < j (0,1), (0,2), (1,2); positions
    at or past len(out) are dropped."""
    cdef Py_ssize_t ng = start.shape[0] - 1, nw = gcols.shape[1], maxw = 1, g
    for g in range(ng):
        maxw = max(maxw, width[g])
    cdef double[::1] Y = cvarray((CHUNK * 6 * maxw,), sizeof(double), "d")
    cdef double[::1] G = cvarray((CHUNK * nw,), sizeof(double), "d")
    cdef double[::1] B = cvarray((nw * 6 * maxw,), sizeof(double), "d")
    if ng == 0:
        return
    with nogil:
        all_groups(&values[0], &indptr[0], &neighbour[0], &gcols[0, 0], &gvals[0, 0],
                   <int>nw, &order[0], &start[0], &width[0], &gmap[0, 0],
                   <int>gmap.shape[1], ng, &Y[0], &G[0], &B[0], NULL, NULL, NULL,
                   0, &first[0], &pos[0], &out[0], out.shape[0])
