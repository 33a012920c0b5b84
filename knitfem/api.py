"""knitfem from Python: the objects the command line builds, by keyword.

Every builder here reads its settings through the command line's own
option declarations (``knitfem.cli``), so that a keyword has the name,
the default, the units and the checks of its ``-knit_`` option:
``reduced_model(fabric, lod=(6, 6))`` is ``-knit_model reduced -knit_lod
6,6``. A keyword wins over PETSc's options database, which wins over the
default: options given to ``petsc4py.init(argv)`` (or set with
``PETSc.Options().setValue``) still apply to whatever a keyword leaves
unsaid, and every solver reads its own prefix (``-full_``, ``-reduced_``,
``-mixed_``) as under ``knitfem run``.

    fabric = jersey(rows=7, cols=7, hold="top")        # what is knitted
    system = reduced_model(fabric, material())       # ε = Γ α, sampled
    sim = simulation(system, integrator(system))     # BDF2, error-controlled
    sim.run(0.1)                                     # the summary (a dict)
    P = centrelines(sim)                             # (yarns, points, 3)

All calls are collective on the system's communicator.
"""

from petsc4py import PETSc

from knitfem.cli.commands import (build_system, colliders_from_options,
                                  integrator_from_options, jersey_from_options,
                                  material_from_options, rest_from_options,
                                  start_rotation_from_options)
from knitfem.cli.options import KnitOptions
from knitfem.cli.scenes import SCENES, make_fabric
from knitfem.io import centrelines as sampled_centrelines
from knitfem.knit.pattern import jersey_fabric
from knitfem.run.simulation import Simulation

__all__ = ["jersey", "scene", "material", "model", "full_model", "reduced_model",
           "mixed_model", "integrator", "simulation", "start", "advance",
           "equilibrium", "control_points", "centrelines", "picture"]

SNAPSHOTS = (0.4, 1.0, 2.0, 3.0)
"""``knitfem run``'s default -knit_snapshots [s]: PNGs drawn at these times."""


def _text(value):
    """A keyword's value as the command line would spell it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


class GivenOptions(KnitOptions):
    """``KnitOptions`` that answer from keyword arguments first.

    ``GivenOptions(lod=(6, 6))`` reads ``-knit_lod`` as "6,6"; a name no
    keyword gives is read from PETSc's options database, else takes the
    command line's default. ``check`` refuses a keyword that no
    declaration asked for (a misspelt name).
    """

    def __init__(self, **given):
        super().__init__()
        self.given = {name: _text(v) for name, v in given.items() if v is not None}
        self.asked = set()

    def _raw(self, name, default, text):
        raw = super()._raw(name, default, text)
        self.asked.add(name)
        return self.given.get(name, raw)

    def check(self, where):
        """Raise TypeError naming the keywords nobody declared."""
        unknown = sorted(set(self.given) - self.asked)
        if unknown:
            raise TypeError(f"{where}: unknown keyword(s) {', '.join(unknown)} (they "
                            "are the -knit_ options of knitfem run -help, without "
                            "the prefix)")


def jersey(hold=None, **options):
    """A jersey's ``Fabric``: r courses of nc stitches, one yarn a course.

    Parameters
    ----------
    hold : {None, "top", "side", "corner"}
        Fixed points P_f(s) = x₀: none (a free knit), the loop heads of the
        top course, the first stitch of every course, or the top course's
        first stitch.
    **options
        ``rows`` (7), ``cols`` (7), ``radius`` (5e-4 m), ``shape`` ("flat"
        or "tube"), ``pattern`` ("jersey", a pattern's name, a chart or a
        knitout file): the ``-knit_`` options of the same names.

    Not collective: pure geometry, the same on every rank.
    """
    opts = GivenOptions(**options)
    knitted = jersey_from_options(opts)
    opts.check("jersey")
    return jersey_fabric(knitted, hold)


def scene(name="hanging", friction=None, **options):
    """The ``Fabric`` of one of ``knitfem run``'s scenes, as -knit_scene sets it up.

    Parameters
    ----------
    name : str
        One of ``knitfem.cli.scenes.SCENES``: hanging, pulled, freefall,
        drape, catenary, cantilever or sleeve.
    friction : float
        Coulomb μ against the bodies (the scene's default: drape 0.5,
        others 0).
    **options
        The jersey's ``rows``, ``cols``, ``radius``, ``shape`` and ``rest``
        (a relaxed.h5 of ``knitfem relax``); the scene's own options (the
        hanging scene's ``tilt`` (90°: it starts horizontal) and ``hold``, the
        pulled scene's ``pull_stitch`` and ``pull_force``, the single yarn's
        ``length``, ``segments`` and ``span``, the sleeve's ``elbow_angle``
        [deg] and ``elbow_time`` [s], 1 s when not given); ``start_rotation``;
        ``collider`` (bodies, e.g. "sphere:0,0,0,0.01").
    """
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}: use one of {', '.join(SCENES)}")
    opts = GivenOptions(**options)
    knitted = rest_from_options(opts, jersey_from_options(opts))
    params = SCENES[name].declare(opts, knitted)
    turn = start_rotation_from_options(opts)
    bodies = colliders_from_options(opts)
    opts.check("scene")
    fabric = make_fabric(name, knitted, turn, **params)
    fabric.bodies = fabric.bodies + bodies
    fabric.friction = SCENES[name].friction if friction is None else friction
    return fabric


def material(scene=None, **options):
    """The yarn ``Material`` (SI units) of -knit_rho, -knit_EA, -knit_EI,
    -knit_gravity and -knit_damping.

    ``scene`` (a name) picks the scene's default damping c_d (hanging: 1.4
    1/s of air drag, Q_d = −c_d M ε̇; else 0); keywords ``rho`` (2.5e-4
    kg/m), ``EA`` (250 N), ``EI`` (1.5e-8 N m²), ``gravity`` (9.81 m/s²)
    and ``damping`` override it.
    """
    opts = GivenOptions(**options)
    value = material_from_options(opts, SCENES[scene] if scene else None)
    opts.check("material")
    return value


def model(fabric, kind="full", material=None, comm=None, **options):
    """The mechanical system of -knit_model ``kind`` for ``fabric``. Collective.

    full:    M ε̈ = Q(ε, ε̇) + C(ε)ᵀ λ,  g(ε) = 0 (yarn level);
    reduced: M^V α̈ = Γᵀ Q(Γα, Γα̇) + (CΓ)ᵀ λ,  M^V = Γᵀ M Γ, sampled
             (ECSW) unless ``sampling="exact"``;
    mixed:   yarn level in ``full_region``, the volume elsewhere.

    Parameters
    ----------
    fabric : knitfem.knit.fabric.Fabric
        From ``jersey`` or ``scene``.
    material : Material
        Default: that of the -knit_ options in PETSc's database, else
        ``Material()`` (no damping).
    comm : PETSc.Comm
        Default ``PETSc.COMM_WORLD``.
    **options
        The model's ``-knit_`` options without the prefix: ``quadrature`` (4),
        ``kernels`` ("compiled"), ``lod`` ((5, 5); (6, 6) with bodies),
        ``volume``, ``sampling`` ("sampled"), ``sampling_tol`` (2e-3),
        ``stretch`` ("yarn"; "shell" with bodies), ``full_region(s)``.
    """
    opts = GivenOptions(model=kind, **options)
    if material is None:                 # -knit_rho, -knit_EA ... if given
        material = material_from_options(opts)
    system = build_system(comm or PETSc.COMM_WORLD, opts, fabric, material)
    opts.check("model")
    return system


def full_model(fabric, material=None, comm=None, **options):
    """The yarn-level model of ``fabric``: ``model(fabric, "full", ...)``."""
    return model(fabric, "full", material, comm, **options)


def reduced_model(fabric, material=None, comm=None, **options):
    """The reduced model ε = Γα, sampled as on the command line:
    ``model(fabric, "reduced", ...)``."""
    return model(fabric, "reduced", material, comm, **options)


def mixed_model(fabric, material=None, comm=None, **options):
    """The mixed model, yarn level in ``full_region`` (e.g. "2:5,1:3",
    columns and courses): ``model(fabric, "mixed", ...)``."""
    return model(fabric, "mixed", material, comm, **options)


def integrator(system, **options):
    """The time integrator of -knit_integrator for ``system``. Collective.

    Keywords: ``integrator`` ("bdf2"; "implicit", backward Euler at fixed
    1e-2 s steps, for a reduced model on bodies), ``dt`` (0: error
    controlled by ``rtol`` 2e-4 and ``atol`` 2e-6 m), ``dt_initial``,
    ``dt_min``, ``dt_max``, ``rho_inf``, ``tangent``. Its ``step(t, x, v,
    t_stop)`` advances (ε, ε̇) in place (``advance`` counts steps for you).
    """
    opts = GivenOptions(**options)
    make = integrator_from_options(
        opts, settle=system.kind == "reduced" and bool(system.fabric.bodies))
    opts.check("integrator")
    return make(system)


def simulation(system, stepper=None, out=None, scene="", snapshots=SNAPSHOTS,
               **kwargs):
    """A ``Simulation`` of ``system``, writing to the directory ``out``.

    Parameters
    ----------
    stepper : integrator
        Default ``integrator(system)``.
    out : str or None
        Output directory (claimed for the run: the time series yarns.xdmf,
        summary.json, the PNG ``snapshots`` [s]); None writes nothing, and
        then ``run`` may be called again with a later t_end.
    scene : str
        The scene's name, for the pictures' titles, file names and view.
    **kwargs
        ``Simulation``'s own: ``output_every`` (10), ``drift_tol`` (1e-6 m),
        ``energy_growth`` (0.5), ``stall_steps`` (100),
        ``checkpoint_every`` (0), ``animation`` (a GIF's file name).

    ``run(t_end)`` returns the summary (a dict, as summary.json);
    ``energies()`` the kinetic, elastic and gravity energy now.
    """
    kwargs.setdefault("view", SCENES[scene].view if scene in SCENES else "oblique")
    return Simulation(system, stepper or integrator(system), out=out, scene=scene,
                      snapshots=snapshots, **kwargs)


def start(system):
    """(ε, ε̇) at the start, the velocity zero: the state vectors an
    integrator's ``step`` advances (PETSc Vecs; collective)."""
    x = system.start_state()
    v = x.duplicate()
    v.zeroEntries()
    return x, v


def advance(integrator, x, v, t=0.0, steps=1):
    """Take ``steps`` accepted steps of (x, v) in place from time t; returns
    the time reached (collective). Each step's dt is the integrator's: fixed,
    or chosen by its error control."""
    for _ in range(steps):
        t += integrator.step(t, x, v)["dt"]
    return t


def equilibrium(system, x=None, load_steps=1):
    """Static equilibrium of ``system`` (collective):

        −Q(ε, 0) + C(ε)ᵀμ = 0,   g(ε) = 0,

    by Newton with pseudo-transient continuation from ``x`` (default: the
    start state), gravity and loads applied in ``load_steps`` equal
    increments; ``-static_snes_monitor`` and the other ``-static_`` options
    apply. Returns (x, Newton iterations); raises SimulationError when
    Newton does not converge.
    """
    from solvers.statics import StaticSolver

    if x is None:
        x = system.start_state()
    return x, StaticSolver(system, load_steps).solve(x)


def control_points(system, q=None):
    """The yarns' control points of a state, on every rank (collective), as
    ``yarn.curves.Curves``: ``points`` (N, 3) yarn after yarn (a closed
    yarn's first three repeated at its end), ``yarn(f)`` yarn f's, ``start``
    its offsets and ``course`` the course of every point; ``np.asarray``
    gives the points.

    ``system`` a model and ``q`` its state, reduced (α) or yarn level (ε =
    Γα, say from ``system.full_state``): either is read; or ``system`` a
    ``Simulation`` and ``q`` None, its current state.
    """
    if isinstance(system, Simulation):
        system, q = system.system, system.x if q is None else q
    full = getattr(system, "full", system)
    if q.getSize() == full.M.getSize()[0] and system is not full:
        P = full.gather_points(q)
    else:
        P = system.gather_points(q)
    return system.comm.tompi4py().bcast(P, root=0)


def centrelines(system, q=None):
    """Points along every yarn's centreline of a state, as the output's time
    series samples them (``yarn.curves.Samples``: ``points`` (M, 3), and the
    ``yarn`` and ``course`` of every point); arguments as ``control_points``
    (collective)."""
    return sampled_centrelines(control_points(system, q))


def picture(path, system, q=None, title="", view="front"):
    """Draw a state as a PNG at ``path``: the yarns as tubes of their radius
    and the bodies, seen from ``view`` ("front", "side", "oblique",
    "three_quarter"); arguments as ``control_points`` (collective; rank 0
    draws)."""
    from knitfem import io

    P = control_points(system, q)
    fabric = getattr(system, "system", system).fabric
    if system.comm.rank == 0:
        io.draw(path, P, fabric.radius, title=title, view=view, bodies=fabric.bodies)
