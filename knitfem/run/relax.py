"""A knit relaxed from its geometric template: a naturally straight yarn.

A real yarn is straight at rest: the loops of a knit are bent, and held so
by the yarns they interlock with. The knit's shape is the equilibrium of
that bending against the crossings (and, where they touch, the yarns'
contact), not the template's. ``natural_fabric`` makes the template's
fabric a natural one: its rest X is the template scaled uniformly so that
the yarn length a stitch is ℓ (``-knit_loop_length``; X then only gives the
rest line element |X'| and the mass), its natural curvature is zero, its
crossings hold the two centrelines 2r apart (touching), and it starts from
the template scaled by (s_x, s_y, s_z) along its course, wale and thickness
directions (``-knit_template_scale``). ``relax`` finds its static
equilibrium, free and without gravity, by Newton with pseudo-transient
continuation (``solvers.statics``).

A relaxed knit is written as ``relaxed.h5`` (``save`` / ``load``): the rest
X, the relaxed control points, the crossings' parameters and separation,
the yarn radius, the knit's size and shape and its loop length. A scene
started from it (``-knit_rest FILE``) builds the same jersey with the
relaxed knit as its start state (``RelaxedKnit.apply``); the full model keeps
the natural yarn, so the start is in equilibrium up to the relaxation's
residual, prestress included. A reduced or mixed model drops the crossings
(the embedding holds the stitches), which alone balance that prestress: it
takes the relaxed knit as its stress-free rest instead (``stress_free``).
"""

from dataclasses import dataclass, replace

import h5py
import numpy as np

from knitfem.contact import constraints
from knitfem.knit.measure import curl, loop_length, munden, spacings
from knitfem.yarn import bspline

__all__ = ["RelaxedKnit", "natural_fabric", "yarn_lengths", "stitch_length",
           "knit_measures",
           "stress_free", "VERSION"]

VERSION = 1
"""Layout of relaxed.h5."""


def yarn_lengths(fabric, P=None, nq=8):
    """Length ∫|P'| ds (nyarn,) of every yarn of ``fabric`` with control
    points P (N, 3; default its rest X), by nq-point Gauss a segment."""
    P = fabric.X if P is None else np.asarray(P, dtype=float).reshape(-1, 3)
    yarn = fabric.segments(0, fabric.nyarn)[0]
    conn = fabric.connectivity(0, fabric.nyarn)
    uq, wq = bspline.gauss(nq)
    d = np.einsum("qa,sad->sqd", bspline.basis(uq, 1), P[conn])
    return np.bincount(yarn, np.linalg.norm(d, axis=-1) @ wq,
                       minlength=fabric.nyarn)


def stitch_length(jersey, fabric, P=None):
    """Yarn length a stitch ℓ [m] of the jersey's ``fabric`` at control points
    P (default: its rest X)."""
    return loop_length(yarn_lengths(fabric, P), np.full(fabric.nyarn, jersey.cols))


def natural_fabric(jersey, fabric, length=None, scale=(1.0, 1.0, 1.0)):
    """``fabric`` (the jersey's template) as a naturally straight yarn of
    ``length`` a stitch (default: the template's): its rest X the template
    scaled uniformly to that length, its start X scaled by ``scale`` along
    the fabric's course, wale and thickness directions about its centroid
    and moved the least that makes its crossings 2r apart
    (``constraints.satisfied``)."""
    ell = stitch_length(jersey, fabric)
    centre = fabric.X.mean(axis=0)
    F = fabric.frame
    X = (fabric.X - centre) * ((length or ell) / ell) + centre
    S = F @ np.diag(scale) @ F.T
    natural = replace(fabric, X=X, start_X=(X - centre) @ S.T + centre, natural=True,
                      separation=2 * fabric.radius)
    contacts, _ = constraints.build(natural)
    return replace(natural, start_X=constraints.satisfied(
        contacts, natural.start_X, 1e-12 * fabric.radius))


def stress_free(fabric):
    """The fabric with its start state as a stress-free rest (curvature
    and lengths its own): how a reduced model holds a relaxed knit."""
    if fabric.start_X is None:
        return fabric
    return replace(fabric, X=fabric.start_X, start_X=None, natural=False,
                   separation=None)


def knit_measures(jersey, fabric, P):
    """Textile measures of the knit at control points P (N, 3):
    loop length, course and wale spacings, Munden's constants and the curl
    of each edge (``knit.measure``)."""
    P = np.asarray(P, dtype=float).reshape(-1, 3)
    ell = stitch_length(jersey, fabric, P)
    yarn = np.repeat(np.arange(fabric.nyarn), jersey.cols)
    cols, b = fabric.point_rows(yarn, np.tile(jersey.heads(0), fabric.nyarn))
    heads = np.einsum("na,nai->ni", b, P[cols]).reshape(fabric.nyarn, jersey.cols, 3)
    cs, ws = spacings(heads, fabric.frame[:, 2])
    kc, kw, ks = munden(ell, cs, ws)
    rec = dict(loop_length_m=ell, course_spacing_m=cs, wale_spacing_m=ws,
               k_c=kc, k_w=kw, k_s=ks)
    if not fabric.closed.any() and fabric.nyarn > 2 and jersey.cols > 2:
        rec["curl"] = curl(heads, fabric.frame[:, 2], fabric.radius)
    return rec


@dataclass
class RelaxedKnit:
    """A relaxed knit as ``relaxed.h5`` holds it (module docstring)."""

    rows: int
    cols: int
    shape: str
    radius: float
    rest: np.ndarray
    positions: np.ndarray
    contacts: tuple
    separation: float
    loop_length: float
    source: str = ""

    def save(self, path):
        """Write relaxed.h5 (call on one rank)."""
        from knitfem.io import atomic_write, write_hdf5

        def fill(f):
            f.attrs.update(version=VERSION, rows=self.rows, cols=self.cols,
                           shape=self.shape, radius=self.radius,
                           separation=self.separation, loop_length=self.loop_length)
            f["rest"], f["positions"] = self.rest, self.positions
            for name, values in zip(("yarn_a", "s_a", "yarn_b", "s_b"),
                                    self.contacts):
                f[f"contacts/{name}"] = values

        atomic_write(path, lambda tmp: write_hdf5(tmp, fill))

    @classmethod
    def load(cls, path):
        """Read relaxed.h5; ValueError with what is wrong if it is not one."""
        import os

        if not os.path.isfile(path):
            raise ValueError("no such file (knitfem relax -o DIR writes "
                             "DIR/relaxed.h5)")
        try:
            with h5py.File(path, "r") as f:
                a = f.attrs
                if a.get("version") != VERSION:
                    raise ValueError("not a relaxed knit of this version "
                                     "(knitfem relax writes one)")
                return cls(int(a["rows"]), int(a["cols"]), str(a["shape"]),
                           float(a["radius"]), f["rest"][()], f["positions"][()],
                           tuple(f[f"contacts/{n}"][()] for n in
                                 ("yarn_a", "s_a", "yarn_b", "s_b")),
                           float(a["separation"]), float(a["loop_length"]),
                           source=str(path))
        except (OSError, KeyError) as err:
            raise ValueError(f"cannot read a relaxed knit ({err})") from None

    def check(self, jersey):
        """ValueError unless ``jersey`` is the knit this one relaxed."""
        mine = (self.rows, self.cols, self.shape, self.radius)
        theirs = (jersey.rows, jersey.cols, jersey.knit, jersey.radius)
        if mine != theirs:
            raise ValueError(
                f"the relaxed knit is {self.rows}x{self.cols} {self.shape} of radius "
                f"{self.radius:g}; the options ask for {jersey.rows}x{jersey.cols} "
                f"{jersey.knit} of radius {jersey.radius:g}: give the same "
                f"-knit_rows, -knit_cols, -knit_shape and -knit_radius")

    def apply(self, fabric):
        """The jersey's template ``fabric`` started from this relaxed knit:
        a natural yarn with the relaxed rest lengths and crossings."""
        return replace(fabric, X=np.reshape(self.rest, (-1, 3)),
                       start_X=np.reshape(self.positions, (-1, 3)), natural=True,
                       contacts=self.contacts, separation=self.separation)
