"""The sampled (hyper-reduced) reduced model: ECSW on the yarn elements.

The reduced elastic energy E^V(α) = Σ_e E_e(Γ_e α) sums over every yarn
element, so a reduced Newton iteration costs what the yarns do. Energy-
Conserving Sampling and Weighting (ECSW; Farhat, Avery, Chapman & Cortial,
IJNME 98, 2014) replaces it by a weighted sum over a sampled set S,

    E^V(α) ≈ Σ_{e∈S} ξ_e E_e(Γ_e α),   ξ_e ≥ 0,
    Q^V ≈ −Σ_{e∈S} ξ_e Γ_eᵀ ∇E_e,      K^V ≈ Σ_{e∈S} ξ_e Γ_eᵀ ∇²E_e Γ_e,

still an energy, so the tangent stays symmetric and the step stable. What
is exact in α stays exact and unsampled: M^V, gravity, damping, the holds.
Every element is stress-free at rest and under any rigid motion, so the rest
state stays force-free and rigid motions stay exact whatever S and ξ are.

Training fits ξ on the projected element forces of a library of volume
states made here, in seconds, without a simulation: the four imposed
deformations at two amounts each and random smooth displacements of the
volume's control points at three amplitudes (yarn radii), with a held-out
set of other random ones. With c_se = Γ_eᵀ ∇E_e(Γ_e α_s) and the exact
b_s = Σ_e c_se, each snapshot scaled to unit norm, a greedy non-negative
least-squares (Lawson–Hanson's active set, columns added by the largest
gradient, ECSW's sparse NNLS) stops once

    ‖Σ_e ξ_e c_·e − b‖ ≤ tol ‖b‖     (-knit_sampling_tol).

Candidates are every element of a rank up to ``CANDIDATES``, else an equal
share of each volume patch (An, Kim & James, SIGGRAPH 2008, select from
candidates too): the stitches tile the patches periodically. Each rank fits
its own yarns' sum, so the sum over ranks is fitted too.

The set is cached in ``$XDG_CACHE_HOME/knitfem/sampling`` (default
``~/.cache``) under the SHA-256 of everything it depends on: the rank's rest
control points and elements, the volume's control points, EA, EI, the
quadrature, the tolerance, the training states and seed, and the source of
the code that trains it (``TRAINED_BY``: this module, the yarn elements and
their kernels, the volume's deformations); any change is another file, so
no cached set can be stale.
"""

import functools
import hashlib
import os
import time
import zipfile

import numpy as np

from scipy import sparse

from knitfem.model.assembly import ElementPattern
from knitfem.yarn.kernels import yarn_kernels
from knitfem.lod.grouped_tangent import GroupedTangent
from knitfem.yarn.elements import YarnElements

__all__ = ["SampledElements", "sampled_set", "quadrature_set", "cached_quadrature_set",
           "over_ranks"]

TRAINED_BY = ("lod/sampling.py", "lod/volume.py", "yarn/elements.py",
              "yarn/kernels.py", "yarn/_compiled.pyx", "yarn/bspline.py")
"""The sources, under ``knitfem/``, whose content is part of a set's key (one
not installed counts as absent)."""
CANDIDATES = 4000
DENSE_FILL = 0.2            # Γ̃_S kept dense from this fraction of non-zeros


class SampledElements:
    """The weighted yarn elements of S and their points' rows of Γ̃.

    Its own ``YarnElements`` over the points S touches, with the rest line
    elements W scaled by ξ (E_e is linear in W), give ξ-weighted gradients
    and Hessians from the same kernels as the full model.
    """

    def __init__(self, full, embedding, elements, weights):
        el = full.elements
        self.elements, self.weights = np.asarray(elements), np.asarray(weights)
        pts, local = np.unique(el.conn[self.elements], return_inverse=True)
        self.points = pts
        self.sub = YarnElements(el.X[pts], local.reshape(-1, 4), el.rho, el.EA,
                                el.EI, nq=len(el.weights), natural=el.natural)
        self.sub.W = self.sub.W * self.weights[:, None]
        self.sub.delta = el.delta
        self.kernels = yarn_kernels(self.sub, full.kernels.kind)
        cols = np.ascontiguousarray(embedding.cols[pts])
        vals = np.ascontiguousarray(embedding.vals[pts])
        self.nvolume = n = embedding.volume.size
        rows = np.repeat(np.arange(len(pts)), cols.shape[1])
        self.G = sparse.csr_matrix((vals.ravel(), (rows, cols.ravel())),
                                   shape=(len(pts), n))            # Γ̃_S
        # Γ̃_S is mostly full (a point depends on 32 of a 5x5x2 volume's 50
        # control points): dense products cost a fifth of sparse ones
        if self.G.nnz >= DENSE_FILL * len(pts) * n:
            self.rows = self.G.toarray()
            self.rows_t = np.ascontiguousarray(self.rows.T)
        else:
            self.rows, self.rows_t = self.G, self.G.T.tocsr()
        self.G3 = sparse.kron(self.G, sparse.identity(3), format="csr")
        pattern = ElementPattern(self.sub.conn, 0, len(pts))
        self.indptr3, self.indices3, (slot3,) = pattern.blocks3()
        self.slot3 = np.ascontiguousarray(slot3, dtype=np.int64)
        self.values = np.zeros(len(self.indices3))
        self.grouped = (GroupedTangent(pattern, cols, vals, n)
                        if full.kernels.kind == "compiled" else None)

    def points_of(self, alpha):
        """x_p = Σ_c Γ̃_pc α_c for the points of S, (npts, 3)."""
        return self.rows @ alpha

    def energy(self, alpha):
        """Σ_{e∈S} ξ_e E_e(Γ_e α): the energy the sampled model conserves."""
        return self.sub.energy(self.points_of(alpha))

    def add_forces(self, alpha, out):
        """out (nvolume, 3) += −Σ_{e∈S} ξ_e Γ_eᵀ ∇E_e(Γ_e α)."""
        g = np.zeros((len(self.points), 3))
        self.kernels.add_gradient(self.points_of(alpha), g, -1.0)
        out += self.rows_t @ g

    def hessian_values(self, alpha, alpha_ref=None):
        """The values of Σ_{e∈S} ξ_e ∇²E_e at the points of S (their pattern
        ``indptr3``, ``indices3``)."""
        ref = None if alpha_ref is None else self.points_of(alpha_ref)
        self.kernels.hessian_values(self.points_of(alpha), self.slot3, self.values, ref)
        return self.values

    def tangent(self, alpha, out, alpha_ref=None):
        """out (3 nvolume, 3 nvolume) = Σ_{e∈S} ξ_e Γ_eᵀ ∇²E_e Γ_e (with
        ``alpha_ref``, its axial force linearised from that state: MIP)."""
        values = self.hessian_values(alpha, alpha_ref)
        if self.grouped is not None:
            return self.grouped(values, out)
        out[:] = self.sparse_tangent(alpha, alpha_ref, values).toarray()
        return out

    def sparse_tangent(self, alpha, alpha_ref=None, values=None):
        """Σ_{e∈S} ξ_e Γ_eᵀ ∇²E_e Γ_e as a scipy sparse matrix, Γ_Sᵀ K_S Γ_S."""
        if values is None:
            values = self.hessian_values(alpha, alpha_ref)
        n3 = self.G3.shape[0]
        K = sparse.csr_matrix((values, self.indices3, self.indptr3), shape=(n3, n3))
        return self.G3.T @ (K @ self.G3)

    def move(self, dalpha):
        """max |Γ̃_p δα| over the points of S: how far an update moves them."""
        return float(np.abs(self.points_of(dalpha)).max()) if len(self.points) else 0.0


def over_ranks(comm, report):
    """A rank's sampled-set ``report`` for every rank (collective): |S| and
    the elements it stands for summed, the force errors and the largest
    weight the worst of any rank."""
    from mpi4py import MPI

    comm = comm.tompi4py()
    out = dict(report, elements=comm.allreduce(int(report["elements"])),
               of=comm.allreduce(int(report["of"])))
    for key in ("training_error", "held_out_error", "max_weight"):
        out[key] = comm.allreduce(float(report[key]), op=MPI.MAX)
    return out


# -- training ------------------------------------------------------------------
def training_states(volume, radius, seed, held_out=False):
    """Volume control point sets (k, nvolume, 3) to train on (or, with
    ``held_out``, to test on): imposed deformations at two amounts each and
    smooth random displacements (a random field on the control net, 1, 2
    and 4 yarn radii RMS)."""
    rng = np.random.default_rng(seed + (1000 if held_out else 0))
    rest = volume.flat
    states = []
    if not held_out:
        for mode, amounts in (("flexion", (20.0, 60.0)), ("torsion", (15.0, 45.0)),
                              ("shear", (5.0, 15.0)), ("traction", (1.02, 1.06))):
            for a in amounts:
                try:
                    states.append(volume.deformed(mode, a).flat)
                except ValueError:        # a thin volume would fold
                    pass
    for amplitude in (1.0, 2.0, 4.0) * (1 if held_out else 2):
        d = rng.standard_normal(rest.shape)
        states.append(rest + amplitude * radius * d / np.sqrt(np.mean(d ** 2)))
    return np.array(states)


def _gradients(full, embedding, alpha):
    """∇E_e(Γ_e α) of every element of the rank, (ne, 12)."""
    X = np.einsum("pk,pki->pi", embedding.vals, alpha[embedding.cols])
    return full.kernels.element_gradient(X)


def _projected(full, embedding, grad, elements, weights=None):
    """Σ_e w_e Γ_eᵀ ∇E_e over ``elements`` (w_e = 1 without ``weights``),
    (3 nvolume,), from the element gradients ``grad``."""
    kept = np.zeros_like(grad)
    kept[elements] = grad[elements] if weights is None else \
        weights[:, None] * grad[elements]
    g = full.elements.assemble_vector(kept)
    n = embedding.volume.size
    return np.stack([np.bincount(embedding.cols.ravel(), weights=(
        embedding.vals * g[:, i:i + 1]).ravel(), minlength=n) for i in range(3)],
        -1).ravel()


def element_forces(full, embedding, elements, alpha, subset=None):
    """c_e = Γ_eᵀ ∇E_e(Γ_e α) of ``elements`` as a dense (3 nvolume, ne) array,
    and the exact b = Σ_e c_e over all the rank's elements (over ``subset``,
    element indices, when given)."""
    el = full.elements
    grad = _gradients(full, embedding, alpha)                # (ne_all, 12)
    n = embedding.volume.size
    b = _projected(full, embedding, grad, slice(None) if subset is None else subset)
    g = grad[elements].reshape(-1, 4, 3)                     # (ns, 4, 3)
    pts = el.conn[elements]                                  # (ns, 4)
    cols, vals = embedding.cols[pts], embedding.vals[pts]    # (ns, 4, k)
    slot = (np.arange(len(elements))[:, None, None] * n + cols).ravel()
    c = np.stack([np.bincount(slot, weights=(vals * g[:, :, None, i]).ravel(),
                              minlength=len(elements) * n) for i in range(3)], -1)
    return c.reshape(len(elements), -1).T, b


def candidates(full, embedding, rng, subset=None):
    """The rank's elements (those of ``subset`` when given) if at most
    CANDIDATES, else an equal share of each volume patch (the patch of an
    element's first point)."""
    pool = np.arange(full.elements.ne) if subset is None else np.asarray(subset)
    if len(pool) <= CANDIDATES:
        return pool
    first = embedding.cols[full.elements.conn[pool, 0]]
    _, patch = np.unique(first, axis=0, return_inverse=True)
    patch = patch.ravel()
    share = -(-CANDIDATES // (patch.max() + 1))
    chosen = [pool[rng.permutation(np.flatnonzero(patch == p))[:share]]
              for p in range(patch.max() + 1)]
    return np.sort(np.concatenate(chosen))


def greedy_nnls(A, b, tol, most=None):
    """Sparse ξ ≥ 0 with ‖A ξ − b‖ ≤ tol ‖b‖: Lawson–Hanson's active set,
    entering columns chosen by the largest gradient Aᵀ r, a few at a time
    (ECSW's sparse NNLS). Returns (ξ, relative residual)."""
    from scipy.optimize import nnls

    most = most or min(A.shape)
    norm_b = np.linalg.norm(b)
    S, xi, r = np.zeros(0, dtype=int), np.zeros(0), b.copy()
    while np.linalg.norm(r) > tol * norm_b and len(S) < most:
        grad = A.T @ r
        grad[S] = -np.inf
        step = max(1, len(S) // 10)
        enter = np.argsort(grad)[::-1][:step]
        enter = enter[grad[enter] > 0]
        if not len(enter):
            break
        S = np.concatenate([S, enter])
        xi, _ = nnls(A[:, S], b, maxiter=50 * len(S))
        keep = xi > 0
        S, xi = S[keep], xi[keep]
        r = b - A[:, S] @ xi
    out = np.zeros(A.shape[1])
    out[S] = xi
    return out, np.linalg.norm(r) / norm_b


def fit_system(full, embedding, elements, states, subset=None):
    """(A, b): the projected forces c_se of ``elements`` in the columns of A
    and their exact sum b (over ``subset`` when given), snapshot by snapshot
    scaled to ‖b_s‖ = 1."""
    blocks = [element_forces(full, embedding, elements, a, subset) for a in states]
    scale = [1.0 / max(np.linalg.norm(b), 1e-300) for _, b in blocks]
    A = np.vstack([c * s for (c, _), s in zip(blocks, scale)])
    b = np.concatenate([bb * s for (_, bb), s in zip(blocks, scale)])
    return A, b


def relative_error(full, embedding, elements, weights, states, subset=None):
    """‖Σ_e ξ_e c_·e − b‖ / ‖b‖ over ``states`` (b over ``subset``), each
    state scaled as in ``fit_system``, without forming its columns."""
    miss = norm = 0.0
    for alpha in states:
        grad = _gradients(full, embedding, alpha)
        b = _projected(full, embedding, grad, slice(None) if subset is None else subset)
        scale = 1.0 / max(np.linalg.norm(b), 1e-300)
        miss += np.sum((scale * (_projected(full, embedding, grad, elements, weights)
                                 - b)) ** 2)
        norm += np.sum((scale * b) ** 2)
    return float(np.sqrt(miss / norm))


def quadrature_set(full, embedding, stitches=2, seed=0):
    """The training-free baseline: in every volume patch, the elements of
    ``stitches`` whole stitches (8 consecutive elements of a yarn) spread
    over the patch, each weighted by the patch's elements it stands for
    (the stitches tile a patch periodically). Its force errors are measured
    on the training and held-out states of ``train``."""
    t0 = time.perf_counter()
    first = embedding.cols[full.elements.conn[:, 0]]
    _, patch = np.unique(first, axis=0, return_inverse=True)
    patch = patch.ravel()
    elements, weights = [], []
    for p in range(patch.max() + 1):
        members = np.flatnonzero(patch == p)
        runs = max(1, min(stitches, len(members) // 8))
        starts = np.linspace(0, max(0, len(members) - 8), runs).astype(int)
        chosen = np.unique(np.concatenate([members[a:a + 8] for a in starts]))
        elements.append(chosen)
        weights.append(np.full(len(chosen), len(members) / len(chosen)))
    elements, weights = np.concatenate(elements), np.concatenate(weights)
    vol, radius = embedding.volume, full.fabric.radius
    report = dict(elements=int(len(elements)), of=int(full.elements.ne),
                  candidates=int(full.elements.ne), max_weight=float(weights.max()),
                  training_error=relative_error(full, embedding, elements, weights,
                                                training_states(vol, radius, seed)),
                  held_out_error=relative_error(
                      full, embedding, elements, weights,
                      training_states(vol, radius, seed, held_out=True)),
                  tol=0.0, training_s=time.perf_counter() - t0)
    return elements, weights, report


def train(full, embedding, tol, seed=0, subset=None):
    """(elements, weights, report) of the rank's sampled set: to ``tol``, or
    as many elements as the volume has coordinates (3 n), whichever comes
    first (ECSW's sets scale with the reduced unknowns; beyond them the
    greedy fit's cost grows faster than its error falls). With ``subset``
    (element indices) the set is drawn from those elements and fits their
    sum only (the mixed model's embedded elements); an empty one is an
    empty set."""
    t0 = time.perf_counter()
    of = full.elements.ne if subset is None else len(subset)
    if subset is not None and not len(subset):
        return np.zeros(0, dtype=int), np.zeros(0), dict(
            elements=0, of=0, candidates=0, max_weight=0.0, training_error=0.0,
            held_out_error=0.0, tol=tol, training_s=time.perf_counter() - t0)
    rng = np.random.default_rng(seed)
    cand = candidates(full, embedding, rng, subset)
    radius = full.fabric.radius
    vol = embedding.volume
    A, b = fit_system(full, embedding, cand, training_states(vol, radius, seed),
                      subset)
    xi, err = greedy_nnls(A, b, tol, most=3 * vol.size)
    S = np.flatnonzero(xi)
    held = relative_error(full, embedding, cand[S], xi[S],
                          training_states(vol, radius, seed, held_out=True), subset)
    report = dict(elements=int(len(S)), of=int(of),
                  candidates=int(len(cand)), max_weight=float(xi.max(initial=0.0)),
                  training_error=float(err), held_out_error=float(held),
                  tol=tol, training_s=time.perf_counter() - t0)
    return cand[S], xi[S], report


@functools.lru_cache(maxsize=1)
def training_code():
    """SHA-256 of the sources in ``TRAINED_BY`` (read once a process)."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    h = hashlib.sha256()
    for name in TRAINED_BY:
        try:
            with open(os.path.join(here, name), "rb") as f:
                h.update(name.encode() + b"\0" + f.read())
        except FileNotFoundError:
            h.update(name.encode() + b"\0absent")
    return h.hexdigest()


def cache_key(full, embedding, tol, subset=None, seed=0):
    """SHA-256 of everything the rank's sampled set depends on: its problem,
    the training code and states (``seed``), and the element ``subset`` it
    is drawn from, when given."""
    el, h = full.elements, hashlib.sha256()
    vol, radius = embedding.volume, full.fabric.radius
    for a in (el.X, el.conn, vol.flat, embedding.cols, embedding.vals,
              training_states(vol, radius, seed),
              training_states(vol, radius, seed, held_out=True)):
        h.update(np.ascontiguousarray(a).tobytes())
    if subset is not None:
        h.update(b"subset")
        h.update(np.ascontiguousarray(subset, dtype=np.int64).tobytes())
    h.update(repr((el.EA, el.EI, len(el.weights), tol, seed, full.kernels.kind,
                   training_code())).encode())
    return h.hexdigest()


def cache_dir():
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(
        os.path.expanduser("~"), ".cache")
    return os.path.join(base, "knitfem", "sampling")


def sampled_set(full, embedding, tol, subset=None):
    """(elements, weights, report) of the rank's sampled set (drawn from the
    elements ``subset`` when given, see ``train``): from the cache when it
    holds this problem's, else trained and cached (``cached_set``)."""
    return cached_set(cache_key(full, embedding, tol, subset),
                      lambda: train(full, embedding, tol, subset=subset))


def cached_quadrature_set(full, embedding):
    """``quadrature_set`` with its report: from the cache when it holds
    this problem's (the force errors it reports cost what a few Newton
    iterations of a large garment do), else made and cached."""
    return cached_set(cache_key(full, embedding, "quadrature"),
                      lambda: quadrature_set(full, embedding))


def cached_set(key, make):
    """(elements, weights, report) from the cache file of ``key``, else
    ``make()``'s, written there (a cache that cannot be written is only
    not used); the report says where (``cache``) and whether it was read
    (``cached``)."""
    from knitfem.io import atomic_write

    path = os.path.join(cache_dir(), key + ".npz")
    try:
        with np.load(path) as f:
            report = dict(zip(f["keys"].tolist(), f["values"].tolist()))
            report.update((k, int(report[k])) for k in ("elements", "of", "candidates")
                          if k in report)
            report.update(cache=path, cached=True)
            return f["elements"], f["weights"], report
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        pass                          # none, or unreadable: made again
    elements, weights, report = make()
    keys = [k for k, v in report.items() if isinstance(v, (int, float))]
    try:
        os.makedirs(cache_dir(), exist_ok=True)
        atomic_write(path, lambda tmp: np.savez(
            tmp, elements=elements, weights=weights, keys=np.array(keys),
            values=np.array([float(report[k]) for k in keys])))
        report.update(cache=path, cached=False)
    except OSError as err:
        report.update(cache=f"not written: {err.strerror}", cached=False)
    return elements, weights, report
