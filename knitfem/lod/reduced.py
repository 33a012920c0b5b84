"""The reduced model: yarns embedded in a bounding volume (parameters α).

Every yarn control point keeps constant parameters in the bounding volume V
("stitches fitting"), so ε = Γ α with Γ = Γ̃ ⊗ I₃ constant. Lagrange's
equations in α are

    M^V α̈ = Q^V + (CΓ)ᵀλ,   (CΓ) α = d,   M^V = Γᵀ M Γ,   Q^V = Γᵀ Q(Γα, Γα̇),

m^V = Γ̃ᵀ m Γ̃ formed once by PETSc's PtAP, M^V = m^V ⊗ I₃. The tangent
Γᵀ K Γ is formed densely from the values of K (``GroupedTangent``: a
compiled kernel and one GEMM a patch of V) while the volume has at most
``DENSE_LIMIT`` control points and the kernels are compiled, and by PtAP,
the symbolic product reused, otherwise; a sampled or shell-stretched model
beyond ``DENSE_LIMIT`` sums its parts into a fixed sparse pattern
(``sparse_tangent.SparseTangent``). With -knit_stretch shell the yarns'
stretch is measured on the volume read as a shell, a stitch at a time
(``shell.ShellStretch``), so that it bends and shears like a knit; with
bodies the sampled model meets them on the yarn elements near them
(``body_contact.ActiveContact``). Contacts are dropped (the embedding keeps
the stitches together); fixed
points and clamps stay, reduced to an independent set of rows (a
rank-revealing SVD of cΓ̃), because several fixed points can say the same
thing about α.
"""

import numpy as np
from petsc4py import PETSc

from knitfem.model.assembly import create_aij, kron_identity
from knitfem.model.full import EV_FORCES, applied_forces, max_over_ranks
from knitfem.errors import KnitError
from knitfem.lod.grouped_tangent import GroupedTangent
from knitfem.lod.parts import Parts, default_threads
from knitfem.lod.volume import BoundingVolume
from solvers.saddle import detect_null_pivots

__all__ = ["Embedding", "ReducedModel", "embedding_from_options", "stretch_options",
           "threads_option"]

EV_EMBED = PETSc.Log.Event("knitEmbedding")
EV_PTAP = PETSc.Log.Event("knitPtAP")


DENSE_LIMIT = 200
"""Volume control points up to which the reduced tangent is formed dense
(one GEMM a patch and LAPACK's LU), beyond which sparse (``SparseTangent``
and MUMPS)."""
SHELL_WINDOWS = 16
"""Stitches a volume patch on which a sampled model measures the shell
stretch (``shell.stratified``)."""


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
            X = fabric.X[layout.cp_start:layout.cp_end]
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


def volume_options(opts, bodies=False):
    """((n1, n2), path) from -knit_lod n1,n2 (default 5,5; 6,6 with bodies,
    which a volume of three patches a way can wrap) and -knit_volume FILE."""
    lod = opts.getInts("lod", (6, 6) if bodies else (5, 5), "bounding-volume "
                       "control points n1,n2 (6,6 with -knit_collider or drape; "
                       "a tube on bodies: a patch every 5 stitches around and "
                       "10 courses along)", 2, 4)
    path = opts.getString("volume", "", "bounding volume file (meshio; default: "
                          "a box around the fabric at rest)")
    return lod, path


def sampling_options(opts, default="sampled"):
    """(kind, tolerance) from -knit_sampling exact|sampled, -knit_sampling_tol
    (``default``: the kind when the option is not given)."""
    kind = opts.getChoice("sampling", default, ("sampled", "quadrature", "exact"),
                          "reduced model's yarn forces (and, asked for, the mixed "
                          "model's volume part): a trained weighted sample of the "
                          "yarn elements (ECSW), two stitches a volume patch "
                          "weighted by what they stand for, or every element "
                          "(with bodies: exact up to 200 volume control points, "
                          "quadrature beyond)")
    tol = opts.getReal("sampling_tol", 2e-3, "relative force error the sampled "
                       "set is trained to", positive=True)
    return kind, tol


def threads_option(opts):
    """-knit_threads: the threads a rank forms a sampled reduced model's
    parts on (``parts.Parts``); 0, the default, for ``default_threads``."""
    return opts.getInt("threads", 0, "threads on which a rank forms a sampled "
                       "reduced model's parts (its sampled yarns, shell stretch "
                       "and contact with bodies) side by side; 0: the cores the "
                       "process may run on over the ranks on its machine",
                       minimum=0)


def stretch_options(opts, bodies=False):
    """How the reduced model measures its yarns' stretch, -knit_stretch
    yarn|shell (default: shell where there are bodies to bend round)."""
    return opts.getChoice("stretch", "shell" if bodies else "yarn",
                          ("yarn", "shell"), "the reduced model's yarn stretch: "
                          "of the yarn curves, or with the volume read as a "
                          "shell (mid-surface and thickness), so that it bends "
                          "without stretching its yarns (default: shell with "
                          "-knit_collider, yarn otherwise)")


def body_sampling(size):
    """The default -knit_sampling of a reduced model on bodies whose volume
    has ``size`` control points: exact up to ``DENSE_LIMIT`` (a small
    garment's yarns cost less than the sampled model's contact set and
    ECSW's training; the drape at 12 × 12 took 4.4 s a step exact, 6.5 s
    sampled, on a loaded machine), the training-free quadrature beyond
    (ECSW's training grows with the volume squared times its candidates)."""
    return "exact" if size <= DENSE_LIMIT else "quadrature"


def reduced_from_options(opts, full, embedding):
    """The ReducedModel of -knit_sampling: sampled (the set trained or read
    from the cache, said in one line; its shell stretch, -knit_stretch
    shell, on ``SHELL_WINDOWS`` stitches a volume patch; its contact with
    bodies on the elements near them) unless exact is asked for, which
    sums every yarn element (``full`` was built without its own stretch
    under -knit_stretch shell, ``stretch_options``)."""
    from knitfem.lod.body_contact import ActiveContact
    from knitfem.lod.sampling import (SampledElements, cached_quadrature_set, over_ranks,
                                      sampled_set)
    from knitfem.lod.shell import ShellStretch

    size = embedding.volume.size
    kind, tol = sampling_options(
        opts, "sampled" if full.barrier is None else body_sampling(size))
    shell = None
    if not full.stretch:
        if size > DENSE_LIMIT and full.kernels.kind != "compiled":
            raise KnitError(f"-knit_stretch shell on more than {DENSE_LIMIT} volume "
                            f"control points needs -knit_kernels compiled")
        shell = ShellStretch(full, embedding,
                             per_patch=None if kind == "exact" else SHELL_WINDOWS)
    if kind == "exact":
        return ReducedModel(full, embedding, shell=shell)
    if kind == "quadrature":
        elements, weights, report = cached_quadrature_set(full, embedding)
        made = "measured"
    else:
        elements, weights, report = sampled_set(full, embedding, tol)
        made = "trained"
    report["source"] = f"{'cached' if report['cached'] else made} {report['cache']}"
    contact = ActiveContact(full, embedding) if full.barrier is not None else None
    model = ReducedModel(full, embedding,
                         SampledElements(full, embedding, elements, weights),
                         shell=shell, contact=contact,
                         threads=threads_option(opts) or default_threads(full.comm))
    model.sampling = dict(over_ranks(full.comm, report), kind=kind)
    return model


def threads_note(system):
    """The run header's words on the threads a rank forms the model's parts
    on (``parts.Parts``; '' for one)."""
    threads = getattr(getattr(system, "parts", None), "threads", 1)
    return f"{threads} threads a rank, " if threads > 1 else ""


def sampling_note(system):
    """The run header's words on a sampled model (|S|, the largest weight,
    the force errors and where the set came from) or a shell-stretched one
    ('' for other models)."""
    rep = getattr(system, "sampling", None)
    shell = getattr(system, "shell", None)
    if not rep:
        return (" (every yarn element, its stretch the shell's, a stitch at a time)"
                if shell is not None else "")
    words = (f"{rep['kind']}: {rep['elements']} of {rep['of']} yarn elements, largest "
             f"weight {rep['max_weight']:.3g}, force error {rep['training_error']:.2g} "
             f"training, {rep['held_out_error']:.2g} held out; {rep['source']}")
    if shell is not None:
        words += (f"; its stretch the shell's, on {len(shell.L)} of {shell.windows} "
                  f"stitches")
    if getattr(system, "contact", None) is not None:
        words += "; bodies on the elements near them"
    return f" ({words})"


def garment_lod(fabric, lod, stitches=(5, 10)):
    """Control points (around, along) of a tube's volume on bodies: a patch
    of the volume for every ``stitches`` = (around, along) stitches (n1
    patches around a periodic volume, n2 − 3 along), at least ``lod``; a
    sleeve of 60 × 120 stitches gets 12 × 15 × 2 = 360."""
    from knitfem.knit.pattern import SEGMENTS_PER_STITCH

    around = int(np.max(fabric.yarn_nseg)) // SEGMENTS_PER_STITCH
    return (max(lod[0], -(-around // stitches[0])),
            max(lod[1], -(-fabric.nyarn // stitches[1]) + 3))


def embedding_from_options(opts, comm, fabric, layout=None):
    """The bounding volume of -knit_lod n1,n2 (or -knit_volume FILE) and Γ;
    a tube on bodies, without -knit_lod, gets ``garment_lod``'s."""
    from knitfem.model.assembly import YarnLayout

    lod, path = volume_options(opts, bool(fabric.bodies))
    if fabric.closed.any() and fabric.bodies and not PETSc.Options().hasName("knit_lod"):
        lod = garment_lod(fabric, lod)
    if path:
        try:
            volume = BoundingVolume.load(path)
        except (OSError, ValueError) as err:
            raise KnitError(f"-knit_volume {path}: {err}") from None
    else:
        around = BoundingVolume.tube if fabric.closed.any() else BoundingVolume.around
        volume = around(fabric.X, *lod, margin=fabric.radius,
                        frame=fabric.frame)
    layout = layout or YarnLayout(comm, fabric.yarn_start)
    return Embedding(comm, layout, fabric, volume)


class EmbeddedModel:
    """What a mechanical system whose yarn coordinates are ε = Γ q offers
    through its full model: ε, the gathered control points, the elastic
    energy and the strain. Subclasses hold ``Gamma``, ``full`` and work
    vectors ``eps`` and ``eps_ref``."""

    def _embed(self, full, G, Gs, prefix):
        """What both share: the full model's data, m = Γ̃ᵀ m Γ̃ by PtAP and
        M = Γᵀ M Γ = m ⊗ I₃ from it, Q_g = Γᵀ Q_g, and work vectors for ε and ε̇."""
        self.full = full
        self.comm, self.material = full.comm, full.material
        self.total_mass = full.total_mass
        self.fabric, self.layout = full.fabric, full.layout
        with EV_PTAP:
            self.m = full.m.PtAP(Gs)
            indptr, indices, values = self.m.getValuesCSR()
            (n, N), _ = self.m.getSizes()
            self.M = create_aij(self.comm, (3 * n, 3 * N), (3 * n, 3 * N),
                                kron_identity(indptr, indices, values), bsize=3)
        self.M.setOptionsPrefix(prefix)
        self.Qg = G.createVecRight()
        G.multTranspose(full.Qg, self.Qg)
        self.eps, self.epsdot = G.createVecLeft(), G.createVecLeft()
        self.dq, self.deps = G.createVecRight(), G.createVecLeft()
        self.eps_ref = G.createVecLeft()         # Γ q of a MIP reference

    def _summed(self, a):
        """a summed over the ranks (in place; collective)."""
        if self.comm.size > 1:
            from mpi4py import MPI

            self.comm.tompi4py().Allreduce(MPI.IN_PLACE, a, op=MPI.SUM)
        return a

    def full_state(self, q, out=None):
        """ε = Γ q."""
        out = out or self.Gamma.createVecLeft()
        self.Gamma.mult(q, out)
        return out

    def tunnelled(self, q0, q1):
        """The full model's verdict on the step from Γq0 to Γq1 (collective)."""
        if self.full.barrier is None:
            return None
        return self.full.tunnelled(self.full_state(q0, self.eps),
                                   self.full_state(q1, self.deps))

    def step_limit(self, q, dq):
        """The full model's limit on the update Γ dq from Γ q (collective)."""
        if self.full.barrier is None:
            return 1.0
        return self.full.step_limit(self.full_state(q, self.eps),
                                    self.full_state(dq, self.deps))

    def begin_step(self, q, t=None):
        """A step starts from q at time t: the full model's lagged friction
        at Γ q (ε is formed only when there are bodies)."""
        if self.full.barrier is not None:
            self.full.begin_step(self.full_state(q, self.eps), t)

    def move_bodies(self, t0, t1, q=None):
        self.full.move_bodies(t0, t1)

    def yarn_move(self, dq):
        """max |Γ δq| for the local part ``dq`` (array) of an update δq: how far
        it moves a yarn control point (collective)."""
        self.dq.getArray()[:] = dq
        self.Gamma.mult(self.dq, self.deps)
        return self.deps.norm(PETSc.NormType.INFINITY)

    def gather_points(self, q):
        return self.full.gather_points(self.full_state(q, self.eps))

    def elastic_energy(self, q):
        return self.full.elastic_energy(self.full_state(q, self.eps))

    def strain(self, q):
        return self.full.strain(self.full_state(q, self.eps))

    def start_state(self):
        """The state at the start: the rest turned by ``fabric.start``, in
        range(Γ) since Γ reproduces rigid motions exactly."""
        return self.rest_state(turned=True)

    def project(self, eps, q):
        """Mass-weighted least squares q = (ΓᵀMΓ)⁻¹ Γᵀ M ε (yarn level → this
        model), by a Cholesky factorisation of ΓᵀMΓ (``-<kind>_project_``);
        where Γ may have a null space (``null_space``, the mixed model's Γ_mix)
        MUMPS detects null pivots (``solvers.saddle.detect_null_pivots``, as
        for the model's own systems)."""
        if getattr(self, "_proj", None) is None:
            prefix = f"{self.kind}_project_"
            self._proj = PETSc.KSP().create(comm=self.comm)
            self._proj.setOptionsPrefix(prefix)
            self._proj.setOperators(self.M)
            self._proj.setType("preonly")
            pc = self._proj.getPC()
            pc.setType("cholesky")
            pc.setFactorSolverType("mumps")
            self._proj.setFromOptions()
            if getattr(self, "null_space", False):
                detect_null_pivots(pc, prefix)
        Me = self.full.M.createVecLeft()
        self.full.M.mult(eps, Me)
        rhs = self.M.createVecRight()
        self.Gamma.multTranspose(Me, rhs)
        self._proj.solve(rhs, q)
        Me.destroy()
        rhs.destroy()
        return q


class LinearConstraints:
    """Constraints linear in the system's state q: g = C q − d, C constant."""

    nonlinear_constraints = False

    def constraint_residual(self, q, g):
        """g = C q − d into g (collective)."""
        self.C.mult(q, g)
        g.axpy(-1.0, self.d)

    def constraint_jacobian(self, q):
        """C (constant)."""
        return self.C


class ReducedModel(LinearConstraints, EmbeddedModel):
    """The reduced mechanical system of a ``FullModel`` through an ``Embedding``.

    Offers the interface the integrators use (M, m, C, d, Qg, forces,
    stiffness, …). Its constraints are the world holds only, linear in α.
    Collective.
    """

    kind = "reduced"
    moving_body_rtol = 1e-4
    """Newton's tolerance on |F|, relative to its start, where it backtracks
    on a moving body (``NewtonStepper``): its error a tenth of the time
    step's. The 60×120 sleeve's bend (0.5 s, 1e-2 s steps) ends 0.155 mm RMS
    from the same run to 1e-7 in 389 Newton iterations (1e-5: 0.046 mm, 460;
    1e-6: 0.055 mm, 495; 1e-7: 693); the time step's own error, 1e-2
    against 2e-2 s, is 1.46 mm."""

    @property
    def Gamma(self):
        return self.embedding.Gamma

    def __init__(self, full, embedding, sampled=None, shell=None, contact=None,
                 threads=1):
        self.embedding, self.sampled, self.shell = embedding, sampled, shell
        self.contact = contact
        self.parts = Parts(threads)          # the sampled model's parts side by side
        self.tangent_parts = None
        G = embedding.Gamma
        self._embed(full, G, embedding.Gamma_scalar, "reduced_MV_")
        self._world_constraints()
        self.Qfull = G.createVecLeft()
        self.K = None
        size = embedding.volume.size
        compiled = full.kernels.kind == "compiled"
        self.dense = (GroupedTangent(full.pattern, embedding.cols, embedding.vals, size)
                      if sampled is None and compiled and
                      (size <= DENSE_LIMIT or shell is not None) else None)
        self.sparse = self.yarns = self.exact_kept = None
        if size > DENSE_LIMIT and (sampled is not None or shell is not None):
            from knitfem.lod.sparse_tangent import SparseTangent, scalar_pattern

            pattern = scalar_pattern(self.m)
            if shell is not None:
                pattern = pattern + self._summed_pattern(shell.pattern())
            self.sparse = SparseTangent(self.comm, pattern, self.M.getOwnershipRange(),
                                        compiled=self.full.kernels.kind == "compiled")
        if sampled is not None or shell is not None:   # every α on every rank
            self.gather, self.alpha_all = PETSc.Scatter.toAll(self.Qg)
        # the integrators' Newton matrices, too, are dense on one rank
        self.dense_saddle = self.sparse is None and \
            (self.dense is not None or sampled is not None) and self.comm.size == 1

    def _summed_pattern(self, P):
        """The union over the ranks of the scalar patterns P (collective)."""
        if self.comm.size == 1:
            return P
        P = P.tocoo()
        comm = self.comm.tompi4py()
        rows, cols = (np.concatenate(comm.allgather(a)) for a in (P.row, P.col))
        from scipy import sparse

        return sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=P.shape)

    def _world_constraints(self):
        """(CΓ) α = d for fixed points and clamps, as independent rows."""
        from knitfem.contact import constraints as cons

        _, allc = cons.build(self.fabric)
        vol = self.embedding.volume
        rows = np.zeros((allc.count, vol.size))
        X = self.fabric.X
        for r in range(allc.count):
            sl = slice(allc.indptr[r], allc.indptr[r + 1])
            cols, vals = vol.weights(*vol.embed(X[allc.indices[sl]]))
            np.add.at(rows[r], cols.ravel(), (allc.values[sl, None] * vals).ravel())
        d = allc.rhs
        if allc.count:
            U, S, Vt = np.linalg.svd(rows, full_matrices=False)
            rank = int(np.sum(S > 1e-10 * S[0]))
            c, d = Vt[:rank], (U[:, :rank].T @ d) / S[:rank, None]
        else:
            c, d = rows, d
        self.world_rank, self.world_rows = len(c), allc.count
        comm, NV = self.comm, vol.size
        nrow = len(c) if comm.rank == 0 else 0
        nv = even_split(comm, NV)
        cc = c if comm.rank == 0 else c[:0]
        nz = np.abs(cc) > 0
        csr = (np.concatenate([[0], np.cumsum(nz.sum(1))]), np.nonzero(nz)[1],
               cc[nz])
        self.C = create_aij(comm, (3 * nrow, 3 * len(c)), (3 * nv, 3 * NV),
                            kron_identity(*csr), bsize=3)
        self.d = self.C.createVecLeft()
        if comm.rank == 0:
            self.d.getArray()[:] = d.ravel()

    def rest_state(self, turned=False):
        """α at rest: the volume's control points (Vec, block size 3); turned
        as the fabric starts (``start_state``) with ``turned``."""
        a = self.M.createVecRight()
        lo, hi = a.getOwnershipRange()
        flat = self.embedding.volume.flat
        a.getArray()[:] = (self.fabric.turn(flat) if turned else flat).ravel()[lo:hi]
        return a

    def _all(self, alpha):
        """Every component of α on this rank, (nvolume, 3) (collective)."""
        if self.comm.size == 1:
            return alpha.getArray(readonly=True).reshape(-1, 3)
        self.gather.scatter(alpha, self.alpha_all)
        return self.alpha_all.getArray(readonly=True).reshape(-1, 3)

    def yarn_move(self, dq):
        """max |Γ δq| over the yarn points that S and the contact set touch
        when sampled (the whole of Γ δq would cost what the yarns do), else
        over all."""
        if self.sampled is None:
            return super().yarn_move(dq)
        self.dq.getArray()[:] = dq
        d = self._all(self.dq)
        move = self.sampled.move(d)
        if self.contact is not None:
            move = max(move, float(np.abs(self.contact.Ga @ d).max(initial=0.0)))
        return max_over_ranks(self.comm, move)

    # -- bodies: the contact set's when sampled, the full model's otherwise ---
    def begin_step(self, q, t=None):
        self.exact_kept = None                  # friction lagged anew
        if self.contact is None:
            return super().begin_step(q, t)
        self.contact.begin(self._all(q), t)
        return False

    def move_bodies(self, t0, t1, q=None):
        self.exact_kept = None                  # the bodies elsewhere
        if self.contact is None:
            return super().move_bodies(t0, t1)
        self.contact.move(t0, t1, None if q is None else self._all(q))

    def carry(self, q, t0, t1, v, scale):
        """v += ``scale`` × the move of the volume's control points α = q with
        the moving bodies near them from t0 to t1 (``FullModel.add_carried``):
        the embedded yarns, Γα, go along (v a Vec like q)."""
        self.full.add_carried(q.getArray(readonly=True).reshape(-1, 3), t0, t1, v, scale)

    def step_limit(self, q, dq):
        if self.contact is None:
            return super().step_limit(q, dq)
        from mpi4py import MPI

        a = self._all(q).copy()
        return self.comm.tompi4py().allreduce(
            self.contact.step_limit(a, self._all(dq)), op=MPI.MIN)

    def tunnelled(self, q0, q1):
        """Why the step from q0 to q1 must be refused, or None: the contact
        set missed an element (``ActiveContact.missed``), or a yarn point of
        it went deeper than one yarn radius into a body (collective)."""
        if self.contact is None:
            return super().tunnelled(q0, q1)
        from mpi4py import MPI

        a0 = self._all(q0).copy()
        a1 = self._all(q1)
        comm = self.comm.tompi4py()
        if comm.allreduce(self.contact.missed(a0, a1), op=MPI.LOR):
            return "the contact region grew beyond its set (formed again)"
        depth = comm.allreduce(self.contact.swept_depth(a0, a1), op=MPI.MIN)
        if depth >= -self.fabric.radius:
            return None
        return f"a yarn point went {-depth / self.fabric.radius:.2g} r into a body"

    def elastic_energy(self, q):
        """E(Γq), or, sampled, Σ_{e∈S} ξ_e E_e: the energy this model's
        forces derive from, so that its energy balance is its own."""
        if self.sampled is None:
            E = super().elastic_energy(q)
            if self.shell is not None:
                E += self.comm.tompi4py().allreduce(self.shell.energy(self._all(q)))
            return E
        A = self._all(q)
        E = sum(self.parts.map([lambda part=part: part.energy(A) for part in
                                (self.sampled, self.shell, self.contact)
                                if part is not None]))
        return self.comm.tompi4py().allreduce(E)

    def potential(self, q):
        """Π(α) = E + D − Q_gᵀ α, as ``FullModel.potential`` with this model's
        E (``elastic_energy``; sampled, with the contact set's barrier and
        friction; else the lagged friction of every yarn element)."""
        E = self.elastic_energy(q)
        if self.contact is None and self.full.barrier is not None:
            # every yarn element: elastic_energy has just formed Γq in self.eps
            E += self.full.friction_potential(self.eps)
        return E - self.Qg.dot(q)

    def forces(self, alpha, alphadot, Q):
        """Q^V = Γᵀ Q(Γα, Γα̇) = −Γᵀ ∂E/∂ε(Γα) + Γᵀ Q_g − c_d M^V α̇ (collective):
        the elastic forces of the yarns through Γᵀ (or of the sampled set,
        ``sampling.SampledElements``), the applied ones on the reduced side
        (``model.applied_forces``)."""
        G = self.embedding.Gamma
        with EV_FORCES:
            applied_forces(self, alphadot, Q)
            if self.sampled is not None:
                A = self._all(alpha)
                shape = (self.embedding.volume.size, 3)

                def part(add):
                    f = np.zeros(shape)
                    add(f)
                    return f
                jobs = [lambda: part(lambda f: self.sampled.add_forces(A, f))]
                if self.shell is not None:
                    jobs.append(lambda: part(lambda f: self.shell.add_gradient(A, f, -1.0)))
                if self.contact is not None:
                    jobs.append(lambda: part(lambda f: self.contact.add_forces(A, f)))
                f, *rest = self.parts.map(jobs)
                for g in rest:
                    f += g
                self._add_summed(f, Q)
                return
            G.mult(alpha, self.eps)
            self.Qfull.zeroEntries()
            self.full.add_elastic_forces(self.eps, self.Qfull)
            G.multTransposeAdd(self.Qfull, Q, Q)
            if self.shell is not None:
                f = np.zeros((self.embedding.volume.size, 3))
                self.shell.add_gradient(self._all(alpha), f, -1.0)
                self._add_summed(f, Q)

    def _add_summed(self, f, Q):
        """Q += f (every volume control point's, (n, 3)) summed over the ranks."""
        lo, hi = Q.getOwnershipRange()
        Q.getArray()[:] += self._summed(f).ravel()[lo:hi]

    @property
    def convex_tangent(self):
        """Whether ``stiffness(..., convex=True)`` differs from the exact
        tangent: with the shell stretch, whose compressed stitches it drops
        (``ShellStretch.add_tangent``)."""
        return self.shell is not None

    def stiffness(self, alpha, mu=None, weight=1.0, xref=None, convex=False):
        """Γᵀ K(Γα) Γ: sampled, dense (``GroupedTangent``) or by PtAP,
        reusing the symbolic product (linear constraints: no curvature, μ
        unused); ``xref`` the MIP reference state (``FullModel.stiffness``);
        ``convex``: the shell stretch's compressed stitches' geometric
        stiffness left out (``convex_tangent``)."""
        if self.sampled is not None:
            ref = None if xref is None else self._all(xref).copy()
            A = self._all(alpha)
            if self.sparse is not None:
                return self._sparse_stiffness(
                    A, lambda T: self._add_yarns(T, self.sampled.hessian_values(A, ref)),
                    convex, ref)

            def reduce(R):
                self.sampled.tangent(A, R, ref)
                if self.shell is not None:
                    self.shell.add_hessian(A, R, convex)
                if self.contact is not None:
                    self.contact.add_hessian(A, self.R_values)
            return self._dense_stiffness(reduce)
        x = self.full_state(alpha, self.eps)
        ref = None if xref is None else self.full_state(xref, self.eps_ref)
        if self.dense is not None:
            if self.sparse is not None:         # the shell's, on a large volume
                N = 3 * self.embedding.volume.size
                return self._sparse_stiffness(
                    self._all(alpha), lambda T: T.add_dense(self.dense(
                        self.full.stiffness_values(x, ref), np.zeros((N, N)))),
                    convex, None if xref is None else self._all(xref).copy())
            values = self.full.stiffness_values(x, ref)

            def reduce(R):
                self.dense(values, R)
                if self.shell is not None:
                    self.shell.add_hessian(self._all(alpha), R, convex)
            return self._dense_stiffness(reduce)
        K = self.full.stiffness(x, xref=ref)
        with EV_PTAP:
            if self.K is None:
                self.K = K.PtAP(self.embedding.Gamma)
                self.K.setBlockSize(3)
            else:
                K.PtAP(self.embedding.Gamma, self.K)
        return self.K

    def _sparse_stiffness(self, A, yarns, convex=False, ref=None):
        """Γᵀ K Γ on the fixed sparse pattern (``SparseTangent``): the yarn
        elements' part added by ``yarns(T)``, the shell's (``convex`` as in
        ``stiffness``) and the contact set's added, every rank's summed.
        The convex tangent at the state (α, the MIP reference ``ref``) of
        the last exact one is that one's values (this rank's) less the
        shell's compressed stitches' part (``ShellStretch.add_compressed``):
        the integrator asks for it right after the exact one, whose
        factorisation found negative pivots."""
        T = self.sparse
        with EV_PTAP:
            kept = self.exact_kept
            if convex and kept is not None and np.array_equal(kept[0], A) and \
                    (ref is None if kept[1] is None else np.array_equal(kept[1], ref)):
                T.values[:] = kept[2]
                self.shell.add_compressed(A, T, -1.0)
            else:
                self._add_parts(T, A, yarns, convex)
                self.exact_kept = (A.copy(), ref, T.values.copy()) \
                    if self.shell is not None and not convex else None
            self.K = T.assemble()
        return self.K

    def _add_parts(self, T, A, yarns, convex):
        """T's values = the yarn elements' part (``yarns(part)``), the
        shell's and the contact set's, each formed into a ``TangentPart`` of
        its own (side by side, ``parts``) and added in that order."""
        from knitfem.lod.sparse_tangent import TangentPart

        if self.tangent_parts is None or self.tangent_parts[0] is not T:
            self.tangent_parts = (T, [TangentPart(T) for _ in range(3)])
        Y, S, C = self.tangent_parts[1]
        jobs = [(Y, lambda: yarns(Y))]
        if self.shell is not None:
            jobs.append((S, lambda: self.shell.add_tangent(A, S, convex)))
        if self.contact is not None:
            jobs.append((C, lambda: self.contact.add_hessian(A, C)))
        for P, _ in jobs:
            P.zero()
        self.parts.map([job for _, job in jobs])
        T.values[:] = Y.values
        for P, _ in jobs[1:]:
            T.values += P.values

    def _add_yarns(self, T, values):
        """T's values += the sampled elements' Γ_Sᵀ K_S Γ_S, K_S given by its
        ``values``: by the compiled ``GroupedTangent.add_into``, or by
        ``PatchProduct`` (numpy), laid out at the first call."""
        from knitfem.lod.sparse_tangent import PatchProduct

        s = self.sampled
        if s.grouped is not None:
            s.grouped.add_into(values, T)
            return
        if self.yarns is None or self.yarns.T is not T:
            emb = self.embedding
            self.yarns = PatchProduct(T, s.indptr3, s.indices3, emb.cols[s.points],
                                      emb.vals[s.points])
        self.yarns.add(values)

    def _dense_stiffness(self, reduce):
        """Γᵀ K Γ into R by ``reduce(R)`` over this rank's yarns, every rank's
        summed (one Allreduce). K is an AIJ matrix with a dense pattern whose
        values, on one rank, are R's own storage; on several, each rank's
        rows of R are copied in."""
        with EV_PTAP:
            if self.K is None:
                from knitfem.lod.sparse_tangent import DenseValues

                N = 3 * self.embedding.volume.size
                self.R = np.zeros((N, N))
                self.R_values = DenseValues(
                    self.R, compiled=self.full.kernels.kind == "compiled")
            reduce(self.R)
            self._summed(self.R)
            lo, hi = self.M.getOwnershipRange()
            if self.K is None:
                self._create_dense(lo, hi)
            elif self.comm.size > 1:
                self.K.setValuesCSR(*self.dense_csr, self.R[lo:hi].ravel())
            self.K.assemble()                  # a new state: factorisations redo
        return self.K

    def _create_dense(self, lo, hi):
        N = len(self.R)
        self.dense_csr = (np.arange(hi - lo + 1, dtype=PETSc.IntType) * N,
                          np.tile(np.arange(N, dtype=PETSc.IntType), hi - lo))
        if self.comm.size > 1:
            self.K = create_aij(self.comm, (hi - lo, N), (hi - lo, N),
                                (*self.dense_csr, self.R[lo:hi].ravel()), bsize=3)
        else:
            self.K = PETSc.Mat().createAIJWithArrays(
                (N, N), (*self.dense_csr, self.R.reshape(-1)), comm=self.comm)
            self.K.setBlockSize(3)
            self.K.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)

    def destroy(self):
        if self.sampled is not None or self.shell is not None:
            self.gather.destroy()
            self.alpha_all.destroy()
        if self.sparse is not None:
            self.sparse.destroy()
            self.K = None
        self.parts.close()
        for A in (self.M, self.m, self.C, self.d, self.Qg, self.K, self.dq, self.deps,
                  self.eps_ref):
            if A is not None:
                A.destroy()
