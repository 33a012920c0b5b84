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
sleeve      a tube of r courses × nc stitches round (radius R_s, length L_s
            at rest), its axis on z, centred on the elbow at the origin,
            course 0 at the shoulder (z < 0), free on an arm of two capsules
            of radius 0.75 R_s: the upper arm from (0, 0, −0.6 L_s) to the
            origin, the forearm from the origin to (0, 0, 0.6 L_s), which
            turns about x towards +y by the elbow angle, from rest to rest
            (``motion.Motion`` eased) over the elbow's time.

Any scene can start rigidly turned from its rest (``start_rotation``: the
rest, energies and contacts stay those of the unturned fabric, the holds
are taken where the turned start puts them).
"""

import numpy as np

from knitfem.contact.colliders import Capsule, Sphere
from knitfem.contact.motion import Kinematic, Motion
from knitfem.knit.fabric import Fabric
from knitfem.knit.pattern import Jersey, jersey_fabric

__all__ = ["SCENES", "Scene", "make_fabric", "rotation", "straight_yarn", "arc_yarn"]


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
    held = np.einsum("na,nai->ni", b, fabric.start_points()[cols])
    return fabric.rotated(R, held.mean(axis=0))


def drape(jersey, clearance=1e-3):
    """The free ``jersey`` turned flat (R_x(−90°): y, its wales, to −z; z,
    its thickness, to +y) and a sphere of radius width/4 under its centre,
    its top ``clearance`` below the lowest yarn surface."""
    fabric = jersey_fabric(jersey)
    centre = fabric.start_points().reshape(-1, 3).mean(axis=0)
    flat = fabric.rotated(rotation((-90, 0, 0)), centre)
    X = flat.start_points().reshape(-1, 3)
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


def sleeve(jersey, angle, duration):
    """The ``jersey`` knitted as a tube along z, centred on the origin, on an
    arm whose elbow, at the origin, bends by ``angle`` degrees over
    ``duration`` seconds (module docstring)."""
    tube = Jersey(jersey.rows, jersey.cols, jersey.radius, jersey.shape, "tube",
                  chart=jersey.chart)
    fabric = jersey_fabric(tube)
    X = fabric.X.reshape(-1, 3)
    centre = np.array([X[:, 0].mean(), 0.5 * (X[:, 1].min() + X[:, 1].max()),
                       X[:, 2].mean()])
    fabric = fabric.rotated(rotation((90, 0, 0)), centre)     # y (courses) to z
    fabric.X = fabric.X - centre
    X = fabric.X.reshape(-1, 3)
    Rs, Ls = np.mean(np.hypot(X[:, 0], X[:, 1])), np.ptp(X[:, 2])
    reach, arm = np.array([0.0, 0.0, 0.6 * Ls]), 0.75 * Rs
    elbow = Motion([0.0, duration], rotations=[[0.0, 0.0, 0.0],
                                               [-np.radians(angle), 0.0, 0.0]],
                   ease=True)
    fabric.bodies = (Capsule(-reach, np.zeros(3), arm),
                     Kinematic(Capsule(np.zeros(3), reach, arm), elbow))
    return fabric


class Scene:
    """A built-in scene: the fabric it makes, its defaults and its picture.

    A scene is made of its parameters (``params``, the keyword arguments of
    its constructor, which are also its options without the ``knit_``
    prefix); ``fabric(jersey)`` builds the fabric at rest, ``problem(jersey)``
    describes it (a checkpoint's fingerprint). Class attributes: ``view``,
    the picture's camera; ``air_drag``, the default c_d [1/s]; ``friction``,
    the default Coulomb μ against bodies; ``knitted``, whether a jersey
    (-knit_rows, -knit_cols, -knit_shape) is its fabric.
    """

    name = ""
    view = "front"
    air_drag = 0.0
    friction = 0.0
    knitted = True
    bodies = False                  # the scene has bodies of its own

    def timed(self, t_end):
        """This scene for a run to ``t_end`` [s] (a motion over the run)."""
        return self

    def report(self):
        """What the summary says of this scene beyond the run's measures."""
        return {}

    def __init__(self, **params):
        self.params = params

    @classmethod
    def declare(cls, opts, jersey):
        """This scene's own options (declared on ``opts``), as its params."""
        return {}

    @classmethod
    def from_options(cls, opts, jersey):
        return cls(**cls.declare(opts, jersey))

    def fabric(self, jersey):
        raise NotImplementedError

    def problem(self, jersey):
        if not self.knitted:
            shape = {}
        else:
            shape = dict(rows=jersey.rows, cols=jersey.cols, shape=jersey.knit,
                         chart=jersey.chart.text())
        return dict(scene=self.name, radius=jersey.radius, **shape, **self.params)


class Hanging(Scene):
    """r × nc jersey held by ``hold`` and started turned by ``tilt``."""

    name, view = "hanging", "three_quarter"
    air_drag = 1.4
    """Air drag on a swinging knit, linearised: c_d = ½ ρ_air C_D U / ρ_A =
    ½ · 1.2 kg/m³ · 1.2 · 0.5 m/s / 0.26 kg/m² (flat plate normal to the
    flow, C_D ≈ 1.2, Hoerner, *Fluid-Dynamic Drag*, 1965; U the swatch's
    swinging speed; ρ_A the 7×7 jersey's areal density)."""

    def __init__(self, tilt=90.0, hold="top"):
        super().__init__(tilt=tilt, hold=hold)

    @classmethod
    def declare(cls, opts, jersey):
        from knitfem.knit.pattern import HOLDS

        return dict(
            tilt=opts.getReal("tilt", 90.0, "hanging: start turned by this angle "
                              "[deg] about the held course (90 horizontal, 0 "
                              "hanging)"),
            hold=opts.getChoice("hold", "top", HOLDS, "hanging: held by the loop "
                                "heads of the top course, the first stitch of "
                                "every course, or the top course's first stitch"))

    def fabric(self, jersey):
        return tilted(jersey_fabric(jersey, hold=self.params["hold"]),
                      self.params["tilt"])


class Pulled(Scene):
    """The jersey hanging from its top course, pulled at one loop head."""

    name = "pulled"

    def __init__(self, stitch=(0, 0), force=(0.0, -0.005, 0.0)):
        super().__init__(stitch=tuple(stitch), force=tuple(force))

    @classmethod
    def declare(cls, opts, jersey):
        return dict(
            stitch=opts.getInts("pull_stitch", (jersey.cols // 2, 0), "pulled: "
                                "stitch (column, course) whose loop head is "
                                "pulled", 2, 0),
            force=opts.getReals("pull_force", (0.0, -0.005, 0.0), "pulled: point "
                                "force fx,fy,fz [N]", 3))

    def fabric(self, jersey):
        return pulled(jersey, self.params["stitch"], self.params["force"])

    def problem(self, jersey):
        rec = super().problem(jersey)
        return {k: v for k, v in rec.items() if k not in ("stitch", "force")}


class Freefall(Scene):
    """The free jersey (no world constraints)."""

    name, view = "freefall", "oblique"

    def fabric(self, jersey):
        return jersey_fabric(jersey)


class Drape(Scene):
    """The free jersey laid flat above a sphere, on which it falls."""

    name, view = "drape", "three_quarter"
    bodies = True
    friction = 0.5
    """A middling μ for fabric on a body; without friction the swatch
    balanced on the sphere slides off it."""

    def fabric(self, jersey):
        if jersey.closed:
            raise ValueError("-knit_scene drape lays a flat swatch on a sphere: use "
                             "-knit_shape flat (a tube: the hanging or freefall "
                             "scene with -knit_collider)")
        return drape(jersey)


def single_yarn_options(opts):
    """-knit_length and -knit_segments of the one-yarn scenes."""
    return dict(
        length=opts.getReal("length", 0.1, "yarn length [m] (catenary, "
                            "cantilever)", positive=True),
        segments=opts.getInt("segments", 40, "segments of the single yarn "
                             "(catenary, cantilever)", 1))


class Catenary(Scene):
    """One yarn of length L pinned at both ends, at rest an arc (in vacuum)."""

    name, knitted = "catenary", False

    def __init__(self, length=0.1, span=0.08, segments=40):
        super().__init__(length=length, segments=segments, span=span)

    @classmethod
    def declare(cls, opts, jersey):
        return dict(single_yarn_options(opts),
                    span=opts.getReal("span", 0.08, "distance between the pins "
                                      "[m] (catenary)", positive=True))

    def fabric(self, jersey):
        p = self.params
        X = arc_yarn(p["length"], p["span"], p["segments"])[None]
        return Fabric(X, jersey.radius,
                      fixed=(np.zeros(2, int), np.array([0.0, p["segments"]])))


class Cantilever(Scene):
    """One straight yarn along +x clamped at the origin (in vacuum)."""

    name, knitted = "cantilever", False

    def __init__(self, length=0.1, segments=40):
        super().__init__(length=length, segments=segments)

    @classmethod
    def declare(cls, opts, jersey):
        return single_yarn_options(opts)

    def fabric(self, jersey):
        X = straight_yarn(self.params["length"], self.params["segments"])[None]
        root = (np.zeros(1, int), np.zeros(1))
        return Fabric(X, jersey.radius, fixed=root, clamped=root)


class Sleeve(Scene):
    """A sleeve on an arm whose elbow bends (``sleeve``)."""

    name, view = "sleeve", "side"
    bodies = True
    friction = 0.3
    """Knitted fabric on skin or a shirt, a middling μ."""

    def __init__(self, elbow_angle=60.0, elbow_time=0.0):
        super().__init__(elbow_angle=elbow_angle, elbow_time=elbow_time)

    @classmethod
    def declare(cls, opts, jersey):
        return dict(
            elbow_angle=opts.getReal("elbow_angle", 60.0, "sleeve: the elbow bends "
                                     "by this angle [deg], the forearm turning "
                                     "towards +y"),
            elbow_time=opts.getReal("elbow_time", 0.0, "sleeve: over this time [s] "
                                    "from the start (0: over the whole run, "
                                    "-knit_t_end)", nonnegative=True))

    def timed(self, t_end):
        if not self.params["elbow_time"]:
            self.params["elbow_time"] = t_end
        return self

    def report(self):
        return dict(elbow_angle_deg=self.params["elbow_angle"])

    def fabric(self, jersey):
        return sleeve(jersey, self.params["elbow_angle"],
                      self.params["elbow_time"] or 1.0)

    def problem(self, jersey):
        return dict(super().problem(jersey), shape="tube")


SCENES = {cls.name: cls for cls in (Hanging, Pulled, Freefall, Drape, Catenary,
                                    Cantilever, Sleeve)}
"""The built-in scenes by name (-knit_scene)."""


def make_fabric(scene, jersey=None, start_rotation=(0, 0, 0), **params):
    """The ``Fabric`` of the scene named ``scene`` with ``params`` (see its
    class), started turned by ``start_rotation`` (degrees about x, then y,
    then z, about the fabric's centroid); ``jersey`` a ``Jersey`` (its radius
    is the single yarn's too)."""
    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}: use one of {', '.join(SCENES)}")
    fabric = SCENES[scene](**params).fabric(jersey or Jersey(7, 7))
    if np.any(start_rotation):
        fabric = fabric.started_turned(rotation(start_rotation))
    return fabric
