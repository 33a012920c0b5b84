"""Scenes: the fabric, its world constraints and what to report.

Axes: x along the courses, y along the wales and up, z through the
thickness; gravity acts along −y.

hanging     r × nc jersey held by ``hold``: the nc loop heads of its top
            course ("top"), the first stitch of every course ("side") or the
            top course's first stitch ("corner"); the fabric starts turned
            by ``tilt`` degrees about the x-parallel line through the held
            heads (90: horizontal, so it falls and swings down to hang; 0:
            already hanging, it only settles under its weight).
pulled      r × nc jersey hanging from its top course (held at its loop
            heads, at rest, not turned), pulled at the loop head of one
            stitch by a constant point force: smooth far away, the loops
            deform near the pull (the scene of the mixed and adaptive models).
freefall    r × nc jersey, no world constraints.
drape       r × nc jersey, free, released horizontally (its thickness along
            y) a little above a sphere of a quarter of its width under its
            centre: it falls on it and drapes.
catenary    one yarn of length L, ends pinned at (0,0,0) and (span,0,0); at
            rest a circular arc of length L sagging in −y (stress free).
cantilever  one straight yarn of length L along +x, clamped at the origin.

Any scene can start rigidly turned from its rest (``start_rotation``: the
rest, energies and contacts stay those of the unturned fabric, the holds
are taken where the turned start puts them).
"""

import numpy as np

from knitfem.contact.colliders import Sphere
from knitfem.knit.fabric import Fabric
from knitfem.knit.pattern import jersey_fabric

__all__ = ["SCENES", "make_fabric", "rotation", "straight_yarn", "arc_yarn"]

SCENES = ("hanging", "pulled", "freefall", "drape", "catenary", "cantilever")


def interpolating_control_points(points):
    """Control points whose uniform cubic B-spline passes through ``points``
    (nseg + 1, 3) at its junctions, with zero second derivative at the ends."""
    n = len(points) + 2
    A = np.zeros((n, n))
    rows = np.arange(n - 2)
    A[rows + 1, rows], A[rows + 1, rows + 1], A[rows + 1, rows + 2] = 1 / 6, 4 / 6, 1 / 6
    A[0, :3] = A[-1, -3:] = (1, -2, 1)
    rhs = np.zeros((n, 3))
    rhs[1:-1] = points
    return np.linalg.solve(A, rhs)


def straight_yarn(length, nseg):
    """Control points of a straight yarn from the origin along +x, |X'| constant."""
    X = np.zeros((nseg + 3, 3))
    X[:, 0] = (np.arange(nseg + 3) - 1) * length / nseg
    return X


def arc_yarn(length, span, nseg):
    """A circular arc of length L through (0,0,0) and (span,0,0), sagging in −y."""
    if not span < length:
        raise ValueError(f"catenary span {span} must be shorter than the yarn "
                         f"length {length}")
    from scipy.optimize import brentq          # on first use: 20 ms of import

    # chord = 2R sin(θ/2), L = Rθ
    half = brentq(lambda a: np.sin(a) / a - span / length, 1e-9, np.pi - 1e-12)
    R = length / (2 * half)
    phi = np.linspace(-half, half, nseg + 1)
    pts = np.stack([span / 2 + R * np.sin(phi), R * np.cos(half) - R * np.cos(phi),
                    np.zeros_like(phi)], axis=-1)
    return interpolating_control_points(pts)


def tilted(fabric, degrees):
    """``fabric`` turned by ``degrees`` about the x-parallel line through its
    fixed points: R = R_x(θ) turns +y towards −z, so the fabric hanging below
    the held course is lifted out to +z (horizontal at θ = 90°)."""
    theta = np.radians(degrees)
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
    yarn, s_fixed = fabric.fixed
    cols, b = fabric.point_rows(yarn, s_fixed)
    held = np.einsum("na,nai->ni", b, fabric.X[cols])
    return fabric.rotated(R, held.mean(axis=0))


def drape(jersey, clearance=1e-3):
    """The free ``jersey`` turned flat (R_x(−90°): y, its wales, to −z; z,
    its thickness, to +y) and a sphere of radius width/4 under its centre,
    its top ``clearance`` below the lowest yarn surface."""
    fabric = jersey_fabric(jersey)
    centre = fabric.X.reshape(-1, 3).mean(axis=0)
    flat = fabric.rotated(rotation((-90, 0, 0)), centre)
    X = flat.X.reshape(-1, 3)
    width = np.ptp(X[:, 0])
    R = width / 4
    top = X[:, 1].min() - flat.radius - clearance
    flat.bodies = (Sphere(np.array([centre[0], top - R, centre[2]]), R),)
    return flat


def rotation(degrees):
    """R = R_z R_y R_x for angles (a_x, a_y, a_z) in degrees: a turn about x,
    then about y, then about z (fixed world axes)."""
    R = np.eye(3)
    for axis, a in enumerate(np.radians(degrees)):
        c, s = np.cos(a), np.sin(a)
        i, j = (axis + 1) % 3, (axis + 2) % 3
        Ra = np.eye(3)
        Ra[i, i], Ra[i, j], Ra[j, i], Ra[j, j] = c, -s, s, c
        R = Ra @ R
    return R


def pulled(jersey, stitch, force):
    """The hanging jersey with a point force [N] at the loop head of
    ``stitch`` = (column, course)."""
    c, r = stitch
    if not (0 <= c < jersey.cols and 0 <= r < jersey.rows):
        raise ValueError(f"pulled stitch ({c}, {r}) lies outside the "
                         f"{jersey.cols} x {jersey.rows} stitches of the fabric")
    fab = jersey_fabric(jersey, hold="top")
    fab.loads = (np.array([r]), jersey.heads(r)[[c]],
                 np.asarray(force, dtype=float).reshape(1, 3))
    return fab


def make_fabric(scene, jersey=None, length=0.1, span=0.08, nseg=40, radius=5e-4,
                tilt=0.0, pull=None, hold="top", start_rotation=(0, 0, 0)):
    """The ``Fabric`` of a scene; ``pull`` = (stitch, force) for "pulled",
    ``hold`` for "hanging"; started turned by ``start_rotation`` (degrees
    about x, then y, then z, about the fabric's centroid)."""
    fabric = scene_fabric(scene, jersey, length, span, nseg, radius, tilt, pull, hold)
    if np.any(start_rotation):
        fabric = fabric.started_turned(rotation(start_rotation))
    return fabric


def scene_fabric(scene, jersey, length, span, nseg, radius, tilt, pull, hold):
    """The ``Fabric`` of a scene at rest (``make_fabric``)."""
    if scene == "hanging":
        return tilted(jersey_fabric(jersey, hold=hold), tilt)
    if scene == "pulled":
        return pulled(jersey, *pull)
    if scene == "freefall":
        return jersey_fabric(jersey)
    if scene == "drape":
        if jersey.closed:
            raise ValueError("-knit_scene drape lays a flat swatch on a sphere: use "
                             "-knit_shape flat (a tube: the hanging or freefall scene "
                             "with -knit_collider)")
        return drape(jersey)
    if scene == "catenary":
        X = arc_yarn(length, span, nseg)[None]
        return Fabric(X, radius, fixed=(np.zeros(2, int), np.array([0.0, nseg])))
    if scene == "cantilever":
        X = straight_yarn(length, nseg)[None]
        root = (np.zeros(1, int), np.zeros(1))
        return Fabric(X, radius, fixed=root, clamped=root)
    raise ValueError(f"unknown scene {scene!r}: use one of {', '.join(SCENES)}")
