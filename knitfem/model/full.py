"""The full yarn-level model assembled in PETSc (generalised coordinates ε).

    M ε̈ = Q(ε, ε̇) + C(ε)ᵀλ,   g(ε) = 0,

M = m ⊗ I₃ the constant mass, Q = −∂E/∂ε + Q_g − c_d M ε̇ (elastic, gravity,
mass-proportional damping), g the frame-indifferent contacts and the world
holds (``constraints``), C = ∂g/∂ε. Every rank owns whole yarns, so element
kernels need no ghost values; only the constraints couple ranks (contacts
between neighbouring courses, ``constraint_assembly``).

The model is a "mechanical system" for ``solvers/``: mass M (and its scalar
factor m), the constraints (``constraint_residual``, ``constraint_jacobian``
C, whose pattern is fixed) and the callbacks ``forces`` and ``stiffness``
(K + w Σ μ_i ∇²g_i). The reduced model in ``reduced.py`` offers the same
interface.

The element loops run in the kernels of ``kernels.py`` (compiled by default,
the numpy reference with ``kernels="numpy"``); they add the elastic forces
into Q's array and write K's values in place: K is created on the model's
own value array (``solvers.aij.OwnAIJ``, on several ranks as PETSc's two
blocks of a rank's rows), so no copy reaches PETSc.
"""

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
from solvers.aij import OwnAIJ
from solvers.integrators import SimulationError

from knitfem.contact import constraints as cons
from knitfem.model.assembly import (ElementPattern, YarnLayout, create_aij, csr_rows,
                                    kron_identity)
from knitfem.contact.colliders import Barrier
from knitfem.contact.motion import carried
from knitfem.contact import sliding
from knitfem.contact.constraint_assembly import ConstraintAssembly
from knitfem.errors import KnitError
from knitfem.yarn import bspline
from knitfem.contact.yarn_contact import YarnContact
from knitfem.yarn.kernels import yarn_kernels
from knitfem.yarn.elements import YarnElements

__all__ = ["Material", "FullModel", "applied_forces"]

CARRY_LENGTH, CARRY_REACH = 10.0, 10.0
"""The soft minimum's length and reach of ``motion.carried`` [yarn radii]: a
point 20 r further from a moving body than from one at rest goes with the
moving one by about 12 %; a knit with a point within 10 r of a body goes
with the bodies, one 15 r from every body stays."""

EV_FORCES = PETSc.Log.Event("knitForces")
EV_TANGENT = PETSc.Log.Event("knitTangent")
EV_ASSEMBLY = PETSc.Log.Event("knitAssembly")


@dataclass
class Material:
    """Yarn data in SI units (the defaults and their source: docs/guide/scenes.md).

    rho: linear density (kg/m); EA: axial stiffness (N); EI: bending
    stiffness (N m²); gravity: g (m/s², along −y); damping: c_d (1/s),
    Q_d = −c_d M ε̇.
    """

    rho: float = 2.5e-4
    EA: float = 250.0
    EI: float = 1.5e-8
    gravity: float = 9.81
    damping: float = 0.0


def max_over_ranks(comm, local):
    """The largest of every rank's ``local`` (collective; no message on one
    rank, where a Newton convergence test calls it every iteration)."""
    if comm.size == 1:
        return local
    return comm.tompi4py().allreduce(local, op=MPI.MAX)


def applied_forces(system, v, Q):
    """Q = Q_g − c_d M v: gravity and damping of a mechanical system (collective).

    Written in the system's own M and Q_g, so that it serves the full model
    and, exactly, the reduced one: Γᵀ (Q_g − c_d M Γα̇) = Γᵀ Q_g − c_d M^V α̇.
    A term added here must keep that form (an operator of the system times
    its state or velocity).
    """
    c_d = system.material.damping
    if c_d:
        system.M.mult(v, Q)
        Q.scale(-c_d)
        Q.axpy(1.0, system.Qg)
    else:
        system.Qg.copy(Q)


class FullModel:
    """Full model of a ``Fabric``: yarn elements, M, C assembled in PETSc.

    Collective on ``comm``. ``nq`` Gauss points a segment, at least
    ``bspline.fewest_gauss_points`` (KnitError otherwise); ``kernels`` one of
    ``kernels.KINDS`` ("compiled" or "numpy"); ``stretch`` False leaves the
    yarns' stretching energy out (for an embedded model that measures it its
    own way, ``shell.ShellStretch``); ``yarn_contact`` adds the barrier
    E_y that keeps yarns apart (``contact.yarn_contact``), whose tangent
    pattern follows the active pairs (``begin_step``); ``contacts`` "fixed"
    (crossings at fixed spline parameters, ``constraints``) or "sliding"
    (``sliding``, windows of ``slide_margin`` segments either side).
    """

    kind = "full"

    def __init__(self, comm, fabric, material, nq=4, kernels="compiled",
                 stretch=True, yarn_contact=False, contacts="fixed", slide_margin=1):
        self.comm, self.fabric, self.material = comm, fabric, material
        self.stretch = stretch
        nseg, closed = fabric.yarn_nseg, fabric.closed
        fewest = max((bspline.fewest_gauss_points(n, c) for n, c in zip(nseg, closed)),
                     default=1)
        if nq < fewest:
            raise KnitError(f"-knit_quadrature {nq} leaves the mass matrix singular "
                            f"(a yarn of {int(nseg.min())} segment(s) needs at least "
                            f"{fewest} Gauss points a segment): use "
                            f"-knit_quadrature {fewest} or more")
        self.layout = lay = YarnLayout(comm, fabric.yarn_start)
        with EV_ASSEMBLY:
            self.conn = fabric.connectivity(lay.yarn_start, lay.yarn_end)
            Xloc = fabric.X[lay.cp_start:lay.cp_end]
            self.elements = YarnElements(Xloc, self.conn - lay.cp_start,
                                         material.rho, material.EA if stretch else 0.0,
                                         material.EI, nq=nq,
                                         natural=fabric.natural)
            self.kernels = yarn_kernels(self.elements, kernels)
            self.barrier = Barrier(fabric.bodies, self.elements, fabric.radius,
                                   material.rho * material.gravity,
                                   friction=fabric.friction,
                                   compiled=self.kernels.kind == "compiled") \
                if fabric.bodies else None
            self.yarn_contact = YarnContact(fabric, material.EI, kernels=kernels) \
                if yarn_contact else None
            self.all_conn = fabric.connectivity(0, fabric.nyarn)
            self.pattern_rebuilds = 0
            self.pattern = ElementPattern(self.conn, lay.cp_start, lay.ncp_local)
            n, N = lay.ncp_local, lay.ncp
            m_csr = (self.pattern.indptr, self.pattern.indices,
                     self.pattern.assemble(self.elements.mass_elements()))
            self.m = create_aij(comm, (n, N), (n, N), m_csr)
            self.M = create_aij(comm, (3 * n, 3 * N), (3 * n, 3 * N),
                                kron_identity(*m_csr), bsize=3)
            crossings, self.holds = cons.build(fabric)
            # sliding crossings, all of them on every rank (their windows move)
            self.sliding = sliding.crossings(fabric, slide_margin) \
                if contacts == "sliding" else None
            self.window_moves = 0        # times the sliding windows moved
            self._relayout = False       # C's pattern changed since the last step
            self._pairs_given = False    # the tangent's pairs restored, not found
            if self.sliding is not None:
                crossings = self.sliding
            self.constraints = cons_asm = ConstraintAssembly(comm, lay, crossings,
                                                             self.holds)
            self.C = cons_asm.C
            x = self.start_state()
            cons_asm.jacobian(x)                 # C valid from the start
            x.destroy()
            self.nonlinear_constraints = cons_asm.nonlinear
            self.ncon, self.constraint_kind = cons_asm.count, cons_asm.kind
            self.K, self._slot3, self._tangent = None, None, None
            self._contact_slots = None         # the contact Hessian's places in K
            self.Qg = self.M.createVecLeft()
            G = self.M.createVecRight()
            G.getArray().reshape(-1, 3)[:, 1] = -material.gravity
            self.M.mult(G, self.Qg)
            self.Qg.getArray()[:] += fabric.load_vector(   # point loads
                lay.yarn_start, lay.yarn_end).ravel()
            G.destroy()
            self.total_mass = self.m.getRowSum().sum()
        for A, name in ((self.m, "full_m_"), (self.M, "full_M_")):
            A.setOptionsPrefix(name)

    # -- state ---------------------------------------------------------------
    def rest_state(self):
        """ε at rest (Vec, block size 3)."""
        return self._state(self.fabric.X)

    def start_state(self):
        """ε at the start: the rest turned by ``fabric.start`` (Vec)."""
        return self._state(self.fabric.start_points())

    def _state(self, X):
        x = self.M.createVecRight()
        lay = self.layout
        x.getArray()[:] = X[lay.cp_start:lay.cp_end].ravel()
        return x

    def yarn_points(self, x):
        """Local control points (ncp_local, 3) of the state x (a view)."""
        return x.getArray(readonly=True).reshape(-1, 3)

    def full_state(self, x, out=None):
        """ε of the state x: the identity for the full model."""
        if out is None:
            return x.copy()
        x.copy(out)
        return out

    def yarn_move(self, dx):
        """max |δε_i| of the local part ``dx`` (array) of an update (collective)."""
        return max_over_ranks(self.comm, np.abs(dx).max() if dx.size else 0.0)

    def gather_points(self, x):
        """All control points on rank 0 (None elsewhere), as open splines
        (``Fabric.curves``: closed yarns repeat three at their end)."""
        local = x.getArray(readonly=True)
        parts = self.comm.tompi4py().gather(local, root=0)
        if self.comm.rank:
            return None
        return self.fabric.curves(np.concatenate(parts))

    # -- mechanics -----------------------------------------------------------
    def begin_step(self, x, t=None):
        """A step starts from the state x at time t: friction's normal forces
        and reference points are taken there (lagged, ``colliders``); sliding
        crossings start the search for their point from there, and their
        windows move to follow them (``move_windows``); the tangent's pattern
        is laid out again around x when the yarn pairs near contact no longer
        fit it. Returns whether C's or K's pattern changed (the Newton matrix
        must then be made again). Collective."""
        if self.barrier is not None:
            self.barrier.lag(self.yarn_points(x), t)
        move, stuck = self.constraints.commit(x)
        if move:
            self.move_windows(x)
        if stuck:
            raise SimulationError(f"{stuck} sliding crossing(s) slid to the end of "
                                  f"their yarn", curable=False)
        relayout, self._relayout = self._relayout, False
        yc = self.yarn_contact
        if yc is None or self._tangent is None or yc.fits(self.all_points(x)):
            return relayout
        self.drop_tangent()
        return True

    def contact_state(self):
        """What of the yarn contact a run's path depends on, for a checkpoint:
        the tangent's pairs and the Verlet list's anchor (None without yarn
        contact; the same on every rank)."""
        yc = self.yarn_contact
        if yc is None:
            return None
        return dict(pairs=yc.pairs.copy(), anchor=None if yc.candidates_at is None
                    else yc.candidates_at.copy())

    def set_contact_state(self, state):
        """Continue with a checkpoint's ``contact_state``: the tangent's
        pattern is laid out on its pairs at the next ``stiffness`` (and the
        next ``begin_step`` asks for a new Newton matrix), its Verlet list
        made at its anchor."""
        if self.yarn_contact is None or state is None:
            return
        self.yarn_contact.restore(state["pairs"], state["anchor"])
        self._tangent, self._relayout, self._pairs_given = None, True, True

    def move_windows(self, x, first=None):
        """Move the sliding crossings' windows to start at the segments
        ``first`` (ncontacts, 2; default: centred on the crossings that
        strayed, ``SlidingCrossings.centred``) with the state x committed,
        and lay C and its ghosts out again on them (the tangent's pattern at
        the next ``stiffness``; ``begin_step`` then asks for a new Newton
        matrix). Counted in ``window_moves``; returns how many crossings
        moved. Collective."""
        cross = self.sliding
        cross.set_state(self.constraints.sliding_parameters(), self.fabric.X)
        moved = cross.move_windows(cross.centred() if first is None else first,
                                   self.fabric.X, self.all_points(x))
        if len(moved):
            self._lay_out_constraints()
            self.window_moves += 1
        return len(moved)

    def set_sliding_parameters(self, state):
        """Commit the sliding crossings' state (``SlidingCrossings.state``
        of all crossings, as ``ConstraintAssembly.sliding_parameters`` gave
        it), windows included. Collective."""
        windows = self.sliding.first.copy()
        self.sliding.set_state(state, self.fabric.X)
        if np.array_equal(self.sliding.first, windows):
            self.constraints.set_sliding_parameters(state, self.fabric.X)
        else:
            self._lay_out_constraints()

    def _lay_out_constraints(self):
        """The constraints' assembly made again from ``self.sliding``."""
        old = self.constraints
        with EV_ASSEMBLY:
            self.constraints = ConstraintAssembly(self.comm, self.layout, self.sliding,
                                                  self.holds)
        self.constraints.reanchored = old.reanchored
        self.C = self.constraints.C
        old.destroy()
        self._tangent, self._relayout = None, True

    def tangent_missed(self):
        """How many tangent entries the yarn contact has found outside K's
        pattern so far (they were left out)."""
        return self.yarn_contact.missed if self.yarn_contact is not None else 0

    def forget_path(self, x):
        """The yarn contact taken afresh at x, as a model started at x would
        take it: the Verlet list made at x and the tangent's pattern laid out
        around x at the next ``stiffness``, so that what follows depends on x
        alone, not on the path that led there (``run.relax``). Collective."""
        yc = self.yarn_contact
        if yc is None:
            return
        P = self.all_points(x)
        yc.restore(yc.segment_pairs(P, yc.margin), yc.samples(P))
        self.drop_tangent()

    def drop_tangent(self):
        """K's pattern to be laid out again, at the next ``stiffness``, around
        its state (counted in ``pattern_rebuilds``)."""
        self._tangent = None
        self.pattern_rebuilds += 1

    def all_points(self, x):
        """Every rank's control points (ncp_total, 3) on every rank
        (collective): the yarn contact couples any two yarns."""
        local = x.getArray(readonly=True) if isinstance(x, PETSc.Vec) else x
        if self.comm.size == 1:
            return local.reshape(-1, 3)
        return np.concatenate(self.comm.tompi4py().allgather(local)).reshape(-1, 3)

    def step_fraction(self, x0, x1):
        """The fraction of the straight move from x0 to x1 (local arrays)
        that keeps the yarns apart (1 without yarn contact; collective)."""
        if self.yarn_contact is None:
            return 1.0
        return self.yarn_contact.step_fraction(self.all_points(x0), self.all_points(x1))

    def min_yarn_distance(self, x):
        """Smallest centreline distance of two yarn pieces that may touch
        (inf beyond the contact's reach or without it; collective)."""
        if self.yarn_contact is None:
            return np.inf
        return self.yarn_contact.min_distance(self.all_points(x))

    def move_bodies(self, t0, t1, x=None):
        """The step (or a part of it, from the state x) runs from t0 to t1:
        moving bodies go where they are at t1 (``colliders.Barrier.step_to``)."""
        if self.barrier is not None:
            self.barrier.step_to(t0, t1)

    def add_carried(self, points, t0, t1, v, scale):
        """v += ``scale`` × how far ``points`` (n, 3, this rank's, v's local
        layout) go with the moving bodies near them from t0 to t1
        (``motion.carried``; collective)."""
        if self.barrier is None:
            return
        r, comm = self.fabric.radius, self.comm.tompi4py()
        d = carried(self.barrier.bodies, points, t0, t1, CARRY_LENGTH * r,
                    CARRY_REACH * r, lambda m: comm.allreduce(m, op=MPI.MIN))
        if d is not None:
            v.getArray()[:] += scale * d.ravel()

    def carry(self, x, t0, t1, v, scale):
        """v += ``scale`` × the state x's move with the moving bodies from t0
        to t1 (``add_carried``; v a Vec like x)."""
        self.add_carried(self.yarn_points(x), t0, t1, v, scale)

    def elastic_energy(self, x):
        """E(ε) = E_s + E_b (+ E_c, the colliders' barrier, + E_y, the yarn
        contact's) (collective)."""
        P = self.yarn_points(x)
        e = self.elements.energy(P)
        if self.barrier is not None:
            e += self.barrier.energy(P)
        if self.yarn_contact is not None:
            Pall = self.all_points(x)
            e += self.yarn_contact.energy(Pall) if self.comm.rank == 0 else 0.0
        return self.comm.tompi4py().allreduce(e)

    def friction_potential(self, x):
        """D at the state x: the lagged friction's potential against the
        bodies (``colliders``; 0 without; collective)."""
        d = 0.0 if self.barrier is None else \
            self.barrier.friction_potential(self.yarn_points(x))
        return self.comm.tompi4py().allreduce(d)

    def potential(self, x):
        """Π(ε) = E(ε) + D(ε) − Q_gᵀ ε, whose gradient is −Q but for damping
        (``forces``): the elastic energy with the barriers, the lagged
        friction, gravity and the point loads (collective)."""
        return self.elastic_energy(x) + self.friction_potential(x) - self.Qg.dot(x)

    def add_elastic_forces(self, x, Q):
        """Q += −∂E/∂ε (E = E_s + E_b + E_c + E_y; local, but for the yarn
        contact's gather of all control points)."""
        P, out = self.yarn_points(x), Q.getArray().reshape(-1, 3)
        self.kernels.add_gradient(P, out, -1.0)
        if self.barrier is not None:
            self.barrier.add_gradient(P, out, -1.0)
        if self.yarn_contact is not None:
            g = self.yarn_contact.gradient(self.all_points(x))
            lay = self.layout
            out -= g[3 * lay.cp_start:3 * lay.cp_end].reshape(-1, 3)

    def min_collider_distance(self, x):
        """Smallest distance of a yarn surface from a body (collective; inf
        without bodies)."""
        d = self.barrier.min_distance(self.yarn_points(x)) if self.barrier else np.inf
        return self.comm.tompi4py().allreduce(d, op=MPI.MIN)

    def step_limit(self, x, dx):
        """The largest τ ≤ 1 by which the update dx of the state x may be
        taken without a yarn surface passing into a body
        (``colliders.Barrier.step_limit``; collective; 1 without bodies)."""
        if self.barrier is None:
            return 1.0
        local = self.barrier.step_limit(self.yarn_points(x), self.yarn_points(dx))
        return self.comm.tompi4py().allreduce(local, op=MPI.MIN)

    def tunnelled(self, x0, x1):
        """Why the step from x0 to x1 must be refused, or None: a sliding
        crossing held at an end of its window (its conditions unmet; a
        smaller step keeps it inside), or a yarn point whose straight path
        went deeper than one yarn radius into a body (a resting knit sinks
        ~1e-3 r into the barrier's gap, so only a step that jumped the
        barrier goes there; collective)."""
        out = self.constraints.slid_out(x1)
        if out:
            return f"{out} sliding crossing(s) reached the end of their window"
        if self.barrier is None:
            return None
        local = self.barrier.swept_depth(self.yarn_points(x0), self.yarn_points(x1))
        depth = self.comm.tompi4py().allreduce(local, op=MPI.MIN)
        if depth >= -self.fabric.radius:
            return None
        return f"a yarn point went {-depth / self.fabric.radius:.2g} r into a body"

    def forces(self, x, v, Q):
        """Q = −∂E/∂ε + Q_g − c_d M ε̇ (collective)."""
        with EV_FORCES:
            applied_forces(self, v, Q)
            self.add_elastic_forces(x, Q)

    def constraint_residual(self, x, g):
        """g(ε) into g (a Vec of C's row layout). Collective."""
        self.constraints.residual(x, g)

    def constraint_jacobian(self, x):
        """C(ε) = ∂g/∂ε, written in place (fixed pattern). Collective."""
        with EV_ASSEMBLY:
            return self.constraints.jacobian(x)

    @property
    def slot3(self):
        """Value slots (ne, 12, 12) of the yarn elements' entries in their own
        3 × 3-block pattern (``pattern.blocks3``), made when first asked for
        (a sampled reduced model never asks)."""
        if self._slot3 is None:
            with EV_ASSEMBLY:
                _, indices3, (slot3,) = self.pattern.blocks3()
                self._slot3 = np.ascontiguousarray(slot3, dtype=np.int64)
                self.K_values = np.zeros(len(indices3))
        return self._slot3

    def _tangent_pattern(self, x):
        """K on the pattern of the yarn elements, the contacts' curvature
        and the yarn contact's pairs near x (``pattern.blocks3``), holding
        ``tangent_values`` itself; the places of the yarn elements' entries
        in it (``tangent_slot3``); the constraints' curvature operator into
        it. Made when K is first needed, and when the pairs moved."""
        lay, cons_asm = self.layout, self.constraints
        with EV_ASSEMBLY:
            sets = [self.conn, cons_asm.element_cols()]
            if self.yarn_contact is not None:
                if not self._pairs_given:
                    self.yarn_contact.relayout(self.all_points(x))
                self._pairs_given = False
                sets.append(self.yarn_contact.pair_points(self.all_conn))
            tangent = ElementPattern(sets, lay.cp_start, lay.ncp_local)
            indptr3, indices3, (slot3_yarn, slot3_contacts, *_) = \
                tangent.blocks3(diagonal=(1,) if cons_asm.diagonal_curvature else ())
            n, N = 3 * lay.ncp_local, 3 * lay.ncp
            K = OwnAIJ.from_csr(self.comm, ((n, N), (n, N)), indptr3, indices3, bsize=3)
            self.tangent_slot3 = np.ascontiguousarray(K.place(slot3_yarn),
                                                      dtype=np.int64)
            self.tangent_values = K.values
            cons_asm.B = cons_asm.curvature_operator(K.place(slot3_contacts),
                                                     len(indices3))
            if self.K is not None:
                self.K.destroy()
            self.K = K.mat
            self.K.setOptionsPrefix("full_K_")
            # K's entries by key (local row) · 3 ncp + column, for the yarn
            # contact's Hessian (csr_rows: CSR order is key order)
            self.entry_keys = csr_rows(indptr3).astype(np.int64) * N + indices3
            self.tangent_place = K.place(np.arange(len(indices3)))
            self._contact_slots = None
        self._tangent = K

    def _add_contact_hessian(self, x, values):
        """values += ∂²E_y/∂ε² (PSD-projected) in K's pattern, this rank's
        rows; entries the pattern lacks are dropped and counted
        (``yarn_contact.missed``). The places are found again only when
        the Hessian's pattern changed (the pairs in the band, or entries
        that vanish exactly, as at a symmetric crossing)."""
        lay = self.layout
        H = self.yarn_contact.hessian(self.all_points(x),
                                      rows=(lay.cp_start, lay.cp_end))
        slots = self._contact_slots        # (indptr, indices, hit, place)
        if slots is None or not (np.array_equal(slots[0], H.indptr)
                                 and np.array_equal(slots[1], H.indices)):
            keys = csr_rows(H.indptr).astype(np.int64) * (3 * lay.ncp) + H.indices
            k = np.minimum(np.searchsorted(self.entry_keys, keys),
                           len(self.entry_keys) - 1)
            hit = self.entry_keys[k] == keys
            slots = self._contact_slots = (H.indptr.copy(), H.indices.copy(),
                                           hit, self.tangent_place[k[hit]])
        _, _, hit, place = slots
        self.yarn_contact.missed += int(np.count_nonzero(H.data[~hit]))
        values[place] += H.data[hit]          # CSR: each place once

    def stiffness_values(self, x, xref=None):
        """Values of K = ∂²E/∂ε² (E_c included) in the yarn elements' CSR pattern
        (``pattern.blocks3``): K = Σ_e K_e, written into ``K_values``
        (returned) through the slots of the element entries. With the state
        ``xref`` of the last Newton linearisation, the Newton matrix whose
        axial force is linearised from it (MIP, ``yarn.stretch_terms``)."""
        return self._hessian(x, xref, self.slot3, self.K_values)

    def _hessian(self, x, xref, slot3, values):
        """Σ_e K_e written into ``values`` at the element slots ``slot3``."""
        with EV_TANGENT:
            P = self.yarn_points(x)
            ref = None if xref is None else self.yarn_points(xref)
            self.kernels.hessian_values(P, slot3, values, ref)
            if self.barrier is not None:
                self.barrier.add_hessian(P, slot3, values)
            return values

    def stiffness(self, x, mu=None, weight=1.0, xref=None):
        """K = ∂²E/∂ε² + w Σ_i μ_i ∇²g_i (symmetric, full 3×3 blocks, block
        size 3; reused), in the pattern (indptr3, indices3) of the yarn
        elements and the contacts; μ a Vec of C's row layout, or None;
        ``xref`` the MIP reference of ``stiffness_values``.

        K holds ``tangent_values`` itself: they are written, then K is
        assembled (a new state: factorisations redo)."""
        if self._tangent is None:
            self._tangent_pattern(x)
        values = self._hessian(x, xref, self.tangent_slot3, self.tangent_values)
        if self.yarn_contact is not None:
            with EV_TANGENT:
                self._add_contact_hessian(x, values)
        if mu is not None and weight:
            with EV_TANGENT:
                self.constraints.add_curvature(mu, weight, values, x)
        with EV_ASSEMBLY:
            self.K.assemble()
        return self.K

    def yarn_blocks(self, size, overlap):
        """Subdomains of whole yarns for an additive Schwarz method on
        [A Cᵀ; C 0]: this rank's yarns in runs of ``size``, each widened by
        ``overlap`` yarns either side (across ranks too). A block is
        (coordinates, constraint rows), global indices of A and C: every
        coordinate of its yarns and every constraint among them (one that
        reads no yarn outside the block: a contact of course k when k + 1 is
        in the block as well), so that its own saddle point is solvable."""
        lay = self.layout
        offset, nyarn = lay.yarn_offset, lay.nyarn
        row_low, row_high = np.repeat(self.constraints.reach,
                                      self.constraints.nrows, axis=0).T
        blocks = []
        for first in range(lay.yarn_start, lay.yarn_end, size):
            lo = max(first - overlap, 0)
            hi = min(first + size + overlap, nyarn)
            coords = np.arange(3 * offset[lo], 3 * offset[hi])
            rows = np.flatnonzero((row_low >= lo) & (row_high < hi))
            blocks.append((coords, rows))
        return blocks

    def slide_report(self, x):
        """``max_slide_m``, the largest arc length by which a sliding crossing
        has moved along one of its yarns from rest to the (accepted) state x,
        ``slide_reanchored``, how often a crossing's reference tangents
        moved (``sliding.SlidingCrossings.commit``), ``slide_locked``, how
        many crossings are locked at x (their yarns nearly parallel there),
        and ``slide_window_moves``, how often the windows moved and C's
        pattern was laid out again (``move_windows``); {} for fixed crossings
        (collective)."""
        if self.constraints.diagonal_curvature:
            return {}
        self.constraints.commit(x)
        slides = self.constraints.slides()
        return dict(max_slide_m=max_over_ranks(
            self.comm, float(slides.max()) if slides.size else 0.0),
            slide_reanchored=self.comm.tompi4py().allreduce(
                self.constraints.reanchored),
            slide_locked=self.comm.tompi4py().allreduce(
                int(np.count_nonzero(self.constraints.local.locked))),
            slide_window_moves=self.window_moves)

    def strain(self, x):
        """Green–Lagrange axial strain at every local quadrature point."""
        return self.elements.strain(self.yarn_points(x))

    def destroy(self):
        for A in (self.m, self.M, self.Qg, self.K):
            if A is not None:
                A.destroy()
        self.constraints.destroy()
