"""The reduced model: yarns embedded in a bounding volume (parameters α).

Every yarn control point keeps constant parameters in the bounding volume V
("stitches fitting"), so ε = Γ α with Γ = Γ̃ ⊗ I₃ constant. Lagrange's
equations in α are

    M^V α̈ = Q^V + (CΓ)ᵀλ,   (CΓ) α = d,   M^V = Γᵀ M Γ,   Q^V = Γᵀ Q(Γα, Γα̇),

M^V formed once by PETSc's PtAP. The tangent Γᵀ K Γ is formed densely
(``DenseTangent``) while the volume has at most ``DENSE_LIMIT`` control
points — Γ̃ is then nearly dense and BLAS beats a sparse product — and by
PtAP, the symbolic product reused, beyond. Contacts are dropped (the embedding keeps the
stitches together); fixed points and clamps stay, reduced to an independent
set of rows (a rank-revealing SVD of cΓ̃), because several fixed points can
say the same thing about α.
"""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from .assembly import create_aij, kron_identity
from .options import KnitError
from .volume import BoundingVolume

__all__ = ["Embedding", "ReducedModel", "embedding_from_options"]

EV_EMBED = PETSc.Log.Event("knitEmbedding")
EV_PTAP = PETSc.Log.Event("knitPtAP")


DENSE_LIMIT = 200


def even_split(comm, n):
    """Local size of n items split evenly over the ranks of comm."""
    return n // comm.size + (comm.rank < n % comm.size)


class Embedding:
    """Γ̃ and Γ = Γ̃ ⊗ I₃ as PETSc matrices, rows distributed with the yarns.

    Collective. Columns (the volume's control points) are split evenly.
    """

    def __init__(self, comm, layout, fabric, volume):
        self.comm, self.volume = comm, volume
        with EV_EMBED:
            X = fabric.X[layout.yarn_start:layout.yarn_end].reshape(-1, 3)
            try:
                self.params = volume.embed(X)
            except ValueError as err:
                raise KnitError(f"bounding volume: {err}") from None
            cols, vals = volume.weights(*self.params)
        order = np.argsort(cols, axis=1)
        cols = np.take_along_axis(cols, order, 1)
        vals = np.take_along_axis(vals, order, 1)
        self.cols, self.vals = cols, vals
        n, N = layout.ncp_local, layout.ncp
        nv, NV = even_split(comm, volume.size), volume.size
        csr = (np.arange(0, cols.size + 1, cols.shape[1]), cols.ravel(), vals.ravel())
        self.Gamma_scalar = create_aij(comm, (n, N), (nv, NV), csr)
        self.Gamma = create_aij(comm, (3 * n, 3 * N), (3 * nv, 3 * NV),
                                kron_identity(*csr), bsize=3)
        self.Gamma_scalar.setOptionsPrefix("reduced_Gammascalar_")
        self.Gamma.setOptionsPrefix("reduced_Gamma_")

    def scalar_dense(self):
        """The local rows of Γ̃ as a dense (local control points, n) array."""
        G = np.zeros((len(self.cols), self.volume.size))
        np.put_along_axis(G, self.cols, self.vals, axis=1)
        return G

    def destroy(self):
        self.Gamma.destroy()
        self.Gamma_scalar.destroy()


class DenseTangent:
    """Γᵀ K Γ as a dense (3n, 3n) array from the values of K (local rows).

    With Γ = Γ̃ ⊗ I₃ and K in 3×3 blocks K_pq,

        (Γᵀ K Γ)_{(b,i),(c,j)} = Σ_p Γ̃_pb Y_{(p,i),(c,j)},   Y_{·,(c,j)} = K_{·,j} Γ̃_{·c},

    where K_{·,j} holds the columns of K for component j: three sparse ×
    dense products and one dense product Γ̃ᵀ Y. K couples no two yarns, so
    every rank forms the sum over its own yarns.
    """

    def __init__(self, full, embedding):
        lo = 3 * full.layout.cp_start
        n3 = len(full.indptr3) - 1
        slot = sp.csr_matrix((np.arange(1, len(full.indices3) + 1), full.indices3 - lo,
                              full.indptr3), shape=(n3, n3))
        self.columns = []
        for j in range(3):
            Kj = slot[:, j::3].tocsr()
            self.columns.append((Kj.indptr, Kj.indices, Kj.data - 1))
        self.G = embedding.scalar_dense()
        self.n3 = n3

    def __call__(self, values):
        n, nv = self.G.shape
        Y = np.empty((n, 3, nv, 3))
        for j, (indptr, indices, slots) in enumerate(self.columns):
            Kj = sp.csr_matrix((values[slots], indices, indptr), shape=(self.n3, n))
            Y[..., j] = (Kj @ self.G).reshape(n, 3, nv)
        return (self.G.T @ Y.reshape(n, -1)).reshape(3 * nv, 3 * nv)


def volume_options(opts):
    """((n1, n2), path) from -knit_lod n1,n2 and -knit_volume FILE."""
    lod = opts.getInts("lod", (5, 5), "bounding-volume control points n1,n2", 2, 4)
    path = opts.getString("volume", "", "bounding volume file (meshio; default: "
                          "a box around the fabric at rest)")
    return lod, path


def embedding_from_options(opts, comm, fabric, layout=None):
    """The bounding volume of -knit_lod n1,n2 (or -knit_volume FILE) and Γ."""
    from .assembly import YarnLayout

    lod, path = volume_options(opts)
    if path:
        try:
            volume = BoundingVolume.load(path)
        except (OSError, ValueError) as err:
            raise KnitError(f"-knit_volume {path}: {err}") from None
    else:
        volume = BoundingVolume.around(fabric.X.reshape(-1, 3), *lod,
                                       margin=fabric.radius, frame=fabric.frame)
    layout = layout or YarnLayout(comm, fabric.nyarn, fabric.ncp)
    return Embedding(comm, layout, fabric, volume)


class ReducedModel:
    """The reduced mechanical system of a ``FullModel`` through an ``Embedding``.

    Offers the interface the integrators use (M, m, C, c, d, Qg, forces,
    stiffness, …). Collective.
    """

    kind = "reduced"

    def __init__(self, full, embedding):
        self.full, self.embedding = full, embedding
        self.comm, self.material = full.comm, full.material
        self.total_mass = full.total_mass
        self.fabric, self.layout = full.fabric, full.layout
        G, Gs = embedding.Gamma, embedding.Gamma_scalar
        with EV_PTAP:
            self.M = full.M.PtAP(G)
            self.m = full.m.PtAP(Gs)
        self.M.setOptionsPrefix("reduced_MV_")
        self.M.setBlockSize(3)
        self.Qg = G.createVecRight()
        G.multTranspose(full.Qg, self.Qg)
        self._world_constraints()
        self.eps, self.epsdot = G.createVecLeft(), G.createVecLeft()
        self.Qfull = G.createVecLeft()
        self.K = None
        self.dense = (DenseTangent(full, embedding)
                      if embedding.volume.size <= DENSE_LIMIT else None)
        # the integrators' Newton matrices, too, are dense on one rank
        self.dense_saddle = self.dense is not None and self.comm.size == 1

    def _world_constraints(self):
        """(CΓ) α = d for fixed points and clamps, as independent rows."""
        from . import constraints as cons

        allc = cons.build(self.fabric)
        world = np.flatnonzero(allc.kind != "contact")
        vol = self.embedding.volume
        rows = np.zeros((len(world), vol.size))
        X = self.fabric.X.reshape(-1, 3)
        for r, i in enumerate(world):
            sl = slice(allc.indptr[i], allc.indptr[i + 1])
            cols, vals = vol.weights(*vol.embed(X[allc.indices[sl]]))
            np.add.at(rows[r], cols.ravel(), (allc.values[sl, None] * vals).ravel())
        d = allc.rhs[world]
        if len(world):
            U, S, Vt = np.linalg.svd(rows, full_matrices=False)
            rank = int(np.sum(S > 1e-10 * S[0]))
            c, d = Vt[:rank], (U[:, :rank].T @ d) / S[:rank, None]
        else:
            c, d = rows, d
        self.world_rank, self.world_rows = len(c), len(world)
        comm, NV = self.comm, vol.size
        nrow = len(c) if comm.rank == 0 else 0
        nv = even_split(comm, NV)
        cc = c if comm.rank == 0 else c[:0]
        nz = np.abs(cc) > 0
        csr = (np.concatenate([[0], np.cumsum(nz.sum(1))]), np.nonzero(nz)[1],
               cc[nz])
        self.c = create_aij(comm, (nrow, len(c)), (nv, NV), csr)
        self.C = create_aij(comm, (3 * nrow, 3 * len(c)), (3 * nv, 3 * NV),
                            kron_identity(*csr), bsize=3)
        self.d = self.C.createVecLeft()
        if comm.rank == 0:
            self.d.getArray()[:] = d.ravel()

    def rest_state(self):
        """α at rest: the volume's control points (Vec, block size 3)."""
        a = self.M.createVecRight()
        lo, hi = a.getOwnershipRange()
        a.getArray()[:] = self.embedding.volume.flat.ravel()[lo:hi]
        return a

    def full_state(self, alpha, out=None):
        """ε = Γ α."""
        out = out or self.embedding.Gamma.createVecLeft()
        self.embedding.Gamma.mult(alpha, out)
        return out

    def gather_points(self, alpha):
        return self.full.gather_points(self.full_state(alpha, self.eps))

    def elastic_energy(self, alpha):
        return self.full.elastic_energy(self.full_state(alpha, self.eps))

    def strain(self, alpha):
        return self.full.strain(self.full_state(alpha, self.eps))

    def forces(self, alpha, alphadot, Q):
        """Q^V = Γᵀ Q(Γα, Γα̇)."""
        G = self.embedding.Gamma
        G.mult(alpha, self.eps)
        G.mult(alphadot, self.epsdot)
        self.full.forces(self.eps, self.epsdot, self.Qfull)
        G.multTranspose(self.Qfull, Q)

    def stiffness(self, alpha):
        """Γᵀ K(Γα) Γ: dense (``DenseTangent``) or by PtAP, reusing the
        symbolic product."""
        x = self.full_state(alpha, self.eps)
        if self.dense is not None:
            return self._dense_stiffness(x)
        K = self.full.stiffness(x)
        with EV_PTAP:
            if self.K is None:
                self.K = K.PtAP(self.embedding.Gamma)
                self.K.setBlockSize(3)
            else:
                K.PtAP(self.embedding.Gamma, self.K)
        return self.K

    def _dense_stiffness(self, x):
        """Γᵀ K Γ: every rank's yarns summed (one Allreduce), rows set in place
        into a dense-pattern AIJ."""
        from mpi4py import MPI

        values = self.full.stiffness_values(x)
        with EV_PTAP:
            R = self.dense(values)
            if self.comm.size > 1:
                self.comm.tompi4py().Allreduce(MPI.IN_PLACE, R, op=MPI.SUM)
            lo, hi = self.M.getOwnershipRange()
            if self.K is None:
                N = R.shape[0]
                self.dense_csr = (np.arange(hi - lo + 1, dtype=PETSc.IntType) * N,
                                  np.tile(np.arange(N, dtype=PETSc.IntType), hi - lo))
                self.K = create_aij(self.comm, (hi - lo, N), (hi - lo, N),
                                    (*self.dense_csr, R[lo:hi].ravel()), bsize=3)
            else:
                self.K.setValuesCSR(*self.dense_csr, R[lo:hi].ravel())
                self.K.assemble()
        return self.K

    def project(self, eps, alpha):
        """Mass-weighted least squares α = (ΓᵀMΓ)⁻¹ Γᵀ M ε (full → reduced)."""
        if not hasattr(self, "_proj"):
            self._proj = PETSc.KSP().create(comm=self.comm)
            self._proj.setOptionsPrefix("reduced_project_")
            self._proj.setOperators(self.M)
            self._proj.setType("preonly")
            self._proj.getPC().setType("cholesky")
            self._proj.getPC().setFactorSolverType("mumps")
            self._proj.setFromOptions()
        Me = self.full.M.createVecLeft()
        self.full.M.mult(eps, Me)
        rhs = self.M.createVecRight()
        self.embedding.Gamma.multTranspose(Me, rhs)
        self._proj.solve(rhs, alpha)
        return alpha

    def destroy(self):
        for A in (self.M, self.m, self.C, self.c, self.d, self.Qg, self.K):
            if A is not None:
                A.destroy()
