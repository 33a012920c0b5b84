"""The ``knitfem`` commands; each reads its options and does one job."""

import json
import os
from typing import NamedTuple

import numpy as np
from petsc4py import PETSc

from knitfem.cli.options import KnitError, KnitOptions
from knitfem.knit.chart import chart_from_spec
from knitfem.knit.pattern import HOLDS, SHAPES, Jersey, LoopShape, jersey_fabric, min_yarn_distance

__all__ = ["dofs", "pattern", "relax", "run", "deform"]


def jersey_from_options(opts, rows=7, cols=7):
    """The knit declared by -knit_rows, -knit_cols, -knit_pattern (its
    ``chart`` of knits and purls), -knit_radius and -knit_shape."""
    r = opts.getInt("rows", rows, "courses (rows) of stitches; one yarn each", 1)
    c = opts.getInt("cols", cols, "stitches (columns) a course (around a tube)", 1)
    spec = opts.getString("pattern", "jersey", "stitch pattern: jersey|rib1x1|"
                          "rib2x2|garter|seed over -knit_rows x -knit_cols, a chart "
                          "file CHART.txt (a course a line, bottom first, K or P "
                          "read from the face) or a knitout program FILE.k")
    try:
        chart = chart_from_spec(spec, r, c)
    except KnitError as err:
        raise KnitError(f"-knit_pattern {err}") from None
    for name, given, size in (("rows", r, chart.rows), ("cols", c, chart.cols)):
        if opts.db.hasName(name) and given != size:
            raise KnitError(f"-knit_{name} {given} contradicts -knit_pattern "
                            f"{spec}, whose chart has {size}; leave -knit_{name} out")
    radius = opts.getReal("radius", 5e-4, "yarn radius [m]", positive=True)
    knit = opts.getChoice("shape", "flat", SHAPES, "a flat swatch, or a tube knitted "
                          "in the round (every course closed on itself)")
    if knit == "tube" and chart.cols < 3:
        raise KnitError(f"-knit_cols {chart.cols}: a tube needs at least 3 stitches around")
    return Jersey(chart.rows, chart.cols, radius, LoopShape(), knit, chart=chart)


def rest_from_options(opts, jersey):
    """-knit_rest: the relaxed knit (``knitfem relax``'s relaxed.h5) the
    jersey's fabrics start from, or "template"; sets ``jersey.rest``, and
    -knit_yarn_contact, unless given, to the contact the knit relaxed with
    (without it a knit relaxed against contact is not in equilibrium)."""
    from knitfem.run.relax import RelaxedKnit

    path = opts.getString("rest", "template", "the knit a scene starts from: "
                          "FILE, the relaxed.h5 of knitfem relax (a naturally "
                          "straight yarn in equilibrium), or template (the "
                          "stress-free loops of the paper)")
    if path != "template" and not opts.helping():
        try:
            jersey.rest = RelaxedKnit.load(path)
            jersey.rest.check(jersey)
        except ValueError as err:
            raise KnitError(f"-knit_rest {path}: {err}") from None
        # the contact it relaxed with holds part of its prestress
        if not opts.db.hasName("yarn_contact"):
            opts.db.setValue("yarn_contact", "on" if jersey.rest.yarn_contact else "off")
    return jersey


def output_dir(path):
    """Create the output directory (-o DIR) on rank 0."""
    if PETSc.COMM_WORLD.rank == 0:
        try:
            os.makedirs(path, exist_ok=True)
        except OSError as err:
            raise KnitError(f"-o {path}: cannot create the output directory "
                            f"({err.strerror})") from None
    return path


def dofs(comm):
    """Print the unknowns table (Figure 9) counted from the assembled objects."""
    from knitfem.model.full import FullModel, Material
    from knitfem.lod.reduced import embedding_from_options, volume_options

    opts = KnitOptions()
    jersey = jersey_from_options(opts, 15, 30)
    fmt = opts.getChoice("format", "table", ("table", "json"), "output format")
    volume_options(opts)
    if opts.finish("knitfem dofs"):
        return
    fabric = jersey_fabric(jersey, hold="top")
    emb = embedding_from_options(opts, comm, fabric)
    full = FullModel(comm, fabric, Material())
    # constraint_kind lists every constraint of the fabric on every rank
    contacts, fixed = (int(np.sum(full.constraint_kind == kind))
                       for kind in ("contact", "fixed"))
    ncp_yarn = int(fabric.yarn_ncp.max())
    dof = full.M.getSize()[0]
    reduced_dofs = emb.Gamma.getSize()[1]
    rec = dict(rows=jersey.rows, cols=jersey.cols, control_points_per_yarn=ncp_yarn,
               dofs_per_yarn=3 * ncp_yarn, control_points=full.m.getSize()[0],
               dofs=dof, vector_constraints=contacts,
               scalar_constraints=3 * contacts, unknowns=dof + 3 * contacts,
               fixed_points_hanging=fixed,
               unknowns_hanging=full.M.getSize()[0] + full.C.getSize()[0],
               paper_scalar_constraints=3 * 2 * jersey.cols * jersey.rows,
               reduced_control_points=emb.Gamma_scalar.getSize()[1],
               reduced_dofs=reduced_dofs,
               ratio=(dof + 3 * contacts) / reduced_dofs)
    if fmt == "json":
        PETSc.Sys.Print(json.dumps(rec))
        return
    rows = [("Control points per yarn", rec["control_points_per_yarn"], ""),
            ("Degrees of freedom per yarn", rec["dofs_per_yarn"], ""),
            ("Control points total", rec["control_points"],
             rec["reduced_control_points"]),
            ("Degrees of freedom total", rec["dofs"], rec["reduced_dofs"]),
            ("Vector constraints total", rec["vector_constraints"], ""),
            ("Scalar constraints total", rec["scalar_constraints"], ""),
            ("Scalar unknowns total", rec["unknowns"], rec["reduced_dofs"])]
    lines = [f"{jersey.rows} rows x {jersey.cols} columns jersey, bounding volume "
             f"{emb.volume.n1}x{emb.volume.n2}x2",
             f"{'':30s}{'knitwear (initial)':>20s}{'bounding volume':>18s}"]
    lines += [f"{name:30s}{a:>20}{b:>18}" for name, a, b in rows]
    lines.append(f"{'Ratio of unknowns':30s}{rec['ratio']:>20.1f}")
    lines.append(f"(the paper counts 2 nc contacts for every course, "
                 f"{rec['paper_scalar_constraints']} scalar constraints; an open "
                 f"jersey has (r-1)·2·nc interlocks)")
    lines.append(f"hanging scene (knitfem run): top course held at {fixed} fixed "
                 f"points, {rec['unknowns']} + {3 * fixed} = "
                 f"{rec['unknowns_hanging']} unknowns")
    PETSc.Sys.Print("\n".join(lines))
    full.destroy()


def pattern(comm):
    """Print the pattern's chart; write a jersey's (or a tube's) centrelines
    (VTU) and a PNG picture."""
    from knitfem import io

    opts = KnitOptions()
    jersey = jersey_from_options(opts)
    out = opts.getOutput("out/pattern")
    if opts.finish("knitfem pattern"):
        return
    PETSc.Sys.Print(f"# {jersey.rows} courses of {jersey.cols} stitches, the "
                    f"bottom course first, read from the face\n{jersey.chart}")
    output_dir(out)
    if comm.rank:
        return
    fabric = jersey_fabric(jersey)
    P = fabric.curves(fabric.X)
    dist, f, g = min_yarn_distance(P)
    kind = "jersey" if jersey.chart.jersey else "pattern"
    name = f"{'tube' if jersey.closed else kind}_{jersey.rows}x{jersey.cols}"
    base = os.path.join(out, name)
    io.write_centrelines(base + ".vtu", P, jersey.radius)
    io.draw(base + ".png", P, jersey.radius, title=name.replace("_", " "),
            view="three_quarter" if jersey.closed else "front")
    PETSc.Sys.Print(f"wrote {base}.vtu and {base}.png; {fabric.nyarn} yarns of "
                    f"{fabric.yarn_ncp.max()} control points, min distance "
                    f"between yarns "
                    f"{dist / (2 * jersey.radius):.3f} x 2r")


def relax(comm):
    """Relax a knit from its geometric template: a naturally straight yarn
    bent into its loops, at equilibrium (``run.relax``)."""
    import sys

    from knitfem import io
    from knitfem.knit.pattern import jersey_fabric
    from knitfem.model.full import FullModel
    from knitfem.run.output import OutputDirectory
    from knitfem.run.relax import (Relaxation, RelaxedKnit, knit_measures,
                                   natural_fabric, shortest_loop, stitch_length)
    from knitfem.run.simulation import Simulation

    opts = KnitOptions()
    jersey = jersey_from_options(opts)
    template = jersey_fabric(jersey)
    ell0 = stitch_length(jersey, template)
    ell = opts.getReal("loop_length", float(f"{ell0:.4g}"), "yarn length a stitch "
                       "[m] (default: the unscaled template's)", positive=True)
    scale = opts.getReals("template_scale", (1.0, 1.0, 1.0), "start from the "
                          "template scaled by sx,sy,sz along its courses, wales and "
                          "thickness (the loop length stays -knit_loop_length's)", 3)
    if min(scale) <= 0:
        raise KnitError(f"-knit_template_scale {','.join(map(str, scale))}: "
                        "expected three positive factors")
    material = material_from_options(opts, gravity=0.0, damping=0.0)
    yarn_contact = yarn_contact_option(opts)
    shortest = shortest_loop(jersey, template) if yarn_contact else 0.0
    if ell < shortest:
        raise KnitError(f"-knit_loop_length {ell:g}: the template scaled to that "
                        f"loop brings two yarns within their thickness; give at "
                        f"least {np.ceil(shortest / 1e-5) * 1e-5:.5f} (the template's "
                        f"own is {ell0:.4g}) or -knit_yarn_contact off")
    steps = opts.getInt("load_steps", 5, "load steps that take the crossings from "
                        "the template's to the natural knit's (all but the last "
                        "with a spring to the template's shape)", 1)
    accel = opts.getReal("rest_accel", 1e-4, "the knit is at rest when no "
                         "coordinate's residual force over its mass exceeds this "
                         "[m/s^2]", positive=True)
    restart = opts.getString("restart", "", "continue an interrupted relaxation "
                             "from this HDF5 checkpoint")
    path = opts.getOutput("out/relax")
    if opts.finish("knitfem relax"):
        return
    out = OutputDirectory(comm, path, " ".join(sys.argv)).claim()
    try:
        fabric = natural_fabric(jersey, template, ell, scale)
        system = FullModel(comm, fabric, material, yarn_contact=yarn_contact)
        PETSc.Sys.Print(f"knitfem relax: {jersey.rows}x{jersey.cols} {jersey.knit}, "
                        f"loop length {1e3 * ell:.4g} mm, {system.M.getSize()[0]} "
                        f"coordinates + {system.C.getSize()[0]} constraints")
        relaxation = Relaxation(system, steps, accel)
        sim = Simulation(system, relaxation, out=out, scene="relax", output_every=1,
                         series="relaxed.xdmf", energy_growth=0,
                         view="three_quarter", command=sys.argv)
        if restart:
            sim.restart(restart)
        out.rank0(out.remove, "relaxed.h5")     # an earlier relaxation's
        rec = simulate(sim, 1.0, "relax", out)
        if isinstance(rec, int):
            return rec
        P = sim.control_points()
        if comm.rank == 0:
            rec.update(knit_measures(jersey, fabric, P),
                       residual_acceleration_m_s2=relaxation.solver.acceleration,
                       yarn_contact=yarn_contact, rows=jersey.rows,
                       cols=jersey.cols, shape=jersey.knit, load_steps=steps,
                       chart=jersey.chart.text(), template_scale=list(scale),
                       **{f"descent_{k}": v for k, v in relaxation.solver.stats.items()})
            RelaxedKnit(jersey.rows, jersey.cols, jersey.knit, jersey.radius,
                        fabric.X, P, fabric.contacts, fabric.separation,
                        rec["loop_length_m"], yarn_contact=yarn_contact).save(
                            os.path.join(out.path, "relaxed.h5"))
            io.draw(os.path.join(out.path, "relaxed.png"), fabric.curves(P),
                    jersey.radius, view="three_quarter",
                    title=f"{jersey.rows}x{jersey.cols} "
                          f"{'jersey' if jersey.chart.jersey else 'pattern'} relaxed: k_c "
                          f"{rec['k_c']:.2f}, k_w {rec['k_w']:.2f}")
        sim.write_summary(rec, "completed")
        if comm.rank == 0:
            PETSc.Sys.Print(
                f"relaxed in {rec['newton_iterations']} Newton iterations "
                f"({rec['wall_time_s']:.3g} s): loop length "
                f"{1e3 * rec['loop_length_m']:.3f} mm, courses "
                f"{1e3 * rec['course_spacing_m']:.3f} mm, wales "
                f"{1e3 * rec['wale_spacing_m']:.3f} mm apart; k_c {rec['k_c']:.3f}, "
                f"k_w {rec['k_w']:.3f}, k_s {rec['k_s']:.2f}; written to "
                f"{out.path}/relaxed.h5")
    finally:
        out.release()
    return 0


def material_from_options(opts, scene=None, gravity=9.81, damping=None):
    """Yarn material from -knit_rho, -knit_EA, -knit_EI, -knit_gravity, -knit_damping
    (default damping: ``damping`` where given, else the air drag of ``scene``,
    a ``Scene`` class)."""
    from knitfem.model.full import Material

    d = Material(gravity=gravity, damping=damping if damping is not None else
                 scene.air_drag if scene else 0.0)
    return Material(
        rho=opts.getReal("rho", d.rho, "linear density [kg/m]", positive=True),
        EA=opts.getReal("EA", d.EA, "axial stiffness EA [N]", positive=True),
        EI=opts.getReal("EI", d.EI, "bending stiffness EI [N m^2]", nonnegative=True),
        gravity=opts.getReal("gravity", d.gravity, "gravity g along -y [m/s^2]"),
        damping=opts.getReal("damping", d.damping, "mass-proportional damping c_d "
                             "[1/s] (air drag; hanging: 1.4, else 0)",
                             nonnegative=True))


def yarn_contact_option(opts):
    """-knit_yarn_contact: True for on (the default)."""
    return opts.getChoice("yarn_contact", "on", ("on", "off"),
                          "barrier keeping the yarns apart in the full "
                          "model (clearance band 0.072 r above 2r)") == "on"


class ModelChoice(NamedTuple):
    """What -knit_model and its companions ask for (``model_options``)."""

    kind: str
    quadrature: int
    kernels: str
    yarn_contact: bool
    contacts: str
    slide_margin: int


def model_options(opts):
    """The model's choices (``ModelChoice``) from -knit_model,
    -knit_quadrature, -knit_kernels, -knit_yarn_contact and -knit_contacts,
    -knit_slide_margin; declares the options read only for some models, too
    (-knit_lod, -knit_volume; -knit_full_region(s))."""
    from knitfem.yarn.kernels import KINDS
    from knitfem.lod.mixed import region_options
    from knitfem.lod.reduced import (sampling_options, stretch_options, threads_option,
                                     volume_options)

    kind = opts.getChoice("model", "full", ("full", "reduced", "mixed"),
                          "mechanical model")
    yarn_contact = yarn_contact_option(opts)
    nq = opts.getInt("quadrature", 4, "Gauss points a yarn segment (at least 2, "
                     "which keeps the mass matrix positive definite; 4 integrates "
                     "it exactly)", 2)
    kernels = opts.getChoice("kernels", "compiled", KINDS, "yarn element kernels: "
                             "compiled loops or the numpy reference")
    contacts = opts.getChoice("contacts", "fixed", ("fixed", "sliding"),
                              "persistent crossings: at fixed spline parameters, "
                              "or sliding through the stitches without friction "
                              "(full model)")
    margin = opts.getInt("slide_margin", 1, "sliding crossings: segments a "
                         "crossing may slide within a step either way from the "
                         "middle of its window, which follows it between steps "
                         "[segments, default 1]", 1)
    if contacts == "sliding" and kind != "full":
        raise KnitError(f"-knit_contacts sliding: the {kind} model keeps no "
                        f"crossings of its own; use -knit_model full")
    volume_options(opts)
    sampling_options(opts)
    threads_option(opts)
    stretch_options(opts)
    region_options(opts)
    return ModelChoice(kind, nq, kernels, yarn_contact, contacts, margin)


def build_system(comm, opts, fabric, material):
    """The full, reduced or mixed model of -knit_model, from a fabric."""
    from knitfem.lod.mixed import mixed_from_options
    from knitfem.model.full import FullModel
    from knitfem.lod.reduced import embedding_from_options, reduced_from_options, stretch_options
    from knitfem.run.relax import stress_free

    choice = model_options(opts)
    kind = choice.kind
    stage = PETSc.Log.Stage("Model set-up")
    stage.push()
    if kind != "full":                   # the embedding holds the stitches
        fabric = stress_free(fabric)
    try:
        own = kind != "reduced" or stretch_options(opts, bool(fabric.bodies)) == "yarn"
        full = FullModel(comm, fabric, material, nq=choice.quadrature,
                         kernels=choice.kernels, stretch=own,
                         yarn_contact=choice.yarn_contact and kind == "full",
                         contacts=choice.contacts, slide_margin=choice.slide_margin)
        if kind == "full":
            return full
        embedding = embedding_from_options(opts, comm, fabric, full.layout)
        if kind == "mixed":
            return mixed_from_options(opts, full, embedding)
        return reduced_from_options(opts, full, embedding)
    finally:
        stage.pop()


RUN_HELP_FOOTER = """\
PETSc options reach each solver through its prefix, named by the model:
-full_, -reduced_ and -mixed_ (the implicit Newton: -full_snes_monitor,
-full_ksp_type, -full_pc_type ...; fieldsplit fields u and l),
-full_explicit_ (symplectic, likewise -reduced_explicit_ ...), -static_
(-knit_static: -static_snes_monitor); -log_view, -options_file FILE. Example:
  knitfem run -knit_scene cantilever -knit_static -static_snes_monitor"""

def start_rotation_from_options(opts):
    """-knit_start_rotation ax,ay,az [deg] (``scenes.make_fabric``)."""
    return opts.getReals("start_rotation", (0.0, 0.0, 0.0), "start the fabric "
                         "rigidly turned from its rest by ax,ay,az [deg] about x, "
                         "then y, then z (through its centroid)", 3)


def colliders_from_options(opts):
    """Rigid bodies of -knit_collider (``colliders.parse_colliders``)."""
    from knitfem.contact.colliders import parse_colliders

    text = opts.getString("collider", "", "rigid bodies the yarns keep out of: "
                          "sphere:cx,cy,cz,R, capsule:x0,y0,z0,x1,y1,z1,R, "
                          "plane:px,py,pz,nx,ny,nz; several separated by ';' "
                          "(the drape scene has its sphere)")
    try:
        return parse_colliders(text)
    except ValueError as err:
        raise KnitError(f"-knit_collider: {err}") from None


def moving_bodies(path, bodies):
    """``bodies`` keyframed by the file of -knit_collider_motion (``motion``)."""
    from knitfem.contact.motion import load_motions

    if not path:
        return bodies
    try:
        return load_motions(path, bodies)
    except (OSError, ValueError) as err:
        raise KnitError(f"-knit_collider_motion {path}: {err}") from None


SETTLING = ("implicit", 1e-2)
"""Default (integrator, fixed step) of a reduced model on bodies: its soft
loops ring against the body, which BDF2's error control follows in steps of
1e-5 s (the drape stalls, the sleeve takes 3 473 steps for 0.5 s); backward
Euler damps the ringing and settles in 1e-2 s steps, each Newton solve
started from the step's start (``BackwardEuler`` guess "start"; 884 Newton
iterations for the 12×12 drape, 1 214 from the extrapolated guess). (The
full model keeps BDF2: its stiff yarns take hundreds of Newton iterations a
step at 1e-2 s.)"""


def integrator_from_options(opts, settle=False):
    """The integrator of -knit_integrator with its step control: fixed steps
    under -knit_dt, else error-controlled (-knit_rtol, -knit_atol); by
    default ``SETTLING``'s with ``settle``. Returns a function of the system
    (the options are read now)."""
    from solvers.integrators import INTEGRATORS, GeneralizedAlpha
    from solvers.stepping import StepControl

    method0, fixed0 = SETTLING if settle else ("bdf2", 0.0)
    method = opts.getChoice("integrator", method0, tuple(INTEGRATORS),
                            "integrator: BDF2, generalized-alpha (both 2nd order), "
                            "backward Euler, symplectic Euler (explicit) (a "
                            "reduced model on bodies: implicit, else bdf2)")
    dt = opts.getReal("dt", fixed0 if method == method0 else 0.0,
                      "fixed time step [s] (0: error-controlled steps; a "
                      "reduced model on bodies: 1e-2 with its implicit default)",
                      nonnegative=True)
    rtol = opts.getReal("rtol", 2e-4, "relative tolerance of the local error",
                        nonnegative=True)
    atol = opts.getReal("atol", 2e-6, "absolute tolerance of the local error [m]",
                        nonnegative=True)
    dt0 = opts.getReal("dt_initial", 1e-3, "first trial step [s] (error-controlled)",
                       positive=True)
    dt_min = opts.getReal("dt_min", 1e-9, "smallest step [s] before the run stops",
                          positive=True)
    dt_max = opts.getReal("dt_max", 0.1, "largest step [s]", positive=True)
    rho_inf = opts.getReal("rho_inf", 0.5, "generalized-alpha spectral radius at "
                           "infinite frequency (1: no numerical dissipation)",
                           nonnegative=True)
    if rho_inf > 1:
        raise KnitError(f"-knit_rho_inf {rho_inf:g}: expected a value in [0, 1]")
    tangent = opts.getChoice("tangent", "auto", ("auto", "exact", "mip"),
                             "Newton matrix: its axial force linearised from the "
                             "last iterate (mixed integration point) on a first "
                             "step, where the predictor knows no velocity, and "
                             "exact after; always exact; always MIP")
    if method == "symplectic" and dt == 0:
        raise KnitError("-knit_integrator symplectic: an explicit step needs a "
                        "fixed -knit_dt (say 5e-7)")
    if dt == 0 and rtol == 0 and atol == 0:
        raise KnitError("-knit_rtol 0 -knit_atol 0: give a positive tolerance or "
                        "a fixed -knit_dt")

    def make(system):
        control = StepControl(dt or dt0, adaptive=dt == 0, rtol=rtol, atol=atol,
                              dt_min=dt_min, dt_max=dt_max)
        if method == "alpha":
            return GeneralizedAlpha(system, control.dt, control, rho_inf=rho_inf,
                                    tangent=tangent)
        if method == "symplectic":
            return INTEGRATORS[method](system, control.dt, control)
        if method == "implicit" and settle:      # Newton from the knit at rest on the body
            return INTEGRATORS[method](system, control.dt, control, tangent=tangent,
                                       guess="start")
        return INTEGRATORS[method](system, control.dt, control, tangent=tangent)

    return make


def run(comm):
    """Simulate a scene with the full or reduced model (or solve its statics)."""
    import sys

    from solvers.statics import StaticSolver

    from knitfem.io import TUBE_FORMATS
    from knitfem.lod.adapt import adapt_options, adaptation_from_options
    from knitfem.run.output import CHANGEABLE, OutputDirectory
    from knitfem.run.painter import Painter
    from knitfem.cli.scenes import SCENES, make_fabric
    from knitfem.run.simulation import Simulation

    opts = KnitOptions()
    name = opts.getChoice("scene", "hanging", tuple(SCENES), "scene")
    jersey = rest_from_options(opts, jersey_from_options(opts))
    for cls in SCENES.values():                  # every scene's options declared
        params = cls.declare(opts, jersey)
        if cls.name == name:
            scene = cls(**params)
    turn = start_rotation_from_options(opts)
    bodies = colliders_from_options(opts)
    motion = opts.getString("collider_motion", "", "JSON keyframes moving the "
                            "bodies (the scene's, then -knit_collider's, by "
                            "index): time [s], translation [m], rotation vector "
                            "[deg] about a pivot [m] (knitfem.contact.motion)")
    friction = opts.getReal("friction", scene.friction, "Coulomb friction "
                            "coefficient between the yarns and the bodies (implicit "
                            "integrators; drape: 0.5, others 0)", nonnegative=True)
    material = material_from_options(opts, type(scene))
    t_end = opts.getReal("t_end", 3.0, "simulated time [s]", positive=True)
    scene = scene.timed(t_end)
    kind = model_options(opts)[0]
    make_integrator = integrator_from_options(
        opts, settle=kind == "reduced" and (bool(bodies) or scene.bodies))
    unstable = opts.getBool("unstable_dt", False, "run the symplectic integrator "
                            "even above its stable step 2/omega_max (it blows up)")
    static = opts.getBool("static", False, "solve for the static equilibrium instead "
                          "(Newton with pseudo-transient continuation, -static_snes_* "
                          "options)")
    load_steps = opts.getInt("load_steps", 1, "load steps of the static solve", 1)
    every = opts.getInt("output_every", 10, "steps between progress lines and "
                        "output frames", 1)
    slow = opts.getReal("slow_step", 5.0, "seconds into a step after which each "
                        "retry of it gets a progress line (0: every retry; more "
                        "MUMPS workspace always does) [s]", nonnegative=True)
    snaps = opts.getString("snapshots", "0.4,1,2,3", "times of the PNG snapshots [s]")
    movie = opts.getString("animation", "", "file name of a GIF of every output "
                           "frame, in the output directory (e.g. hanging.gif)")
    tubes = opts.getChoice("tube_mesh", "none", ("none",) + TUBE_FORMATS,
                           "every output frame also as a triangle mesh of the "
                           "yarns' tubes for renderers, DIR/tubes/STEP.FORMAT (PLY: "
                           "a colour and the index of each yarn)")
    ckpt = opts.getInt("checkpoint_every", 0, "steps between HDF5 checkpoints "
                       "(0: none)", 0)
    restart = opts.getString("restart", "", "continue from this HDF5 checkpoint")
    change = opts.getString("restart_change", "", "comma-separated checkpoint "
                            "entries this restart changes on purpose (of "
                            + ",".join(CHANGEABLE) + ")")
    drift = opts.getReal("drift_tol", 1e-6, "largest constraint violation [m] "
                         "before the run stops", positive=True)
    growth = opts.getReal("energy_growth", 0.5, "largest growth of the total energy, "
                          "in units of the motion's energy, before the run stops "
                          "(0: no limit)", nonnegative=True)
    stall = opts.getInt("stall_steps", 100, "steps in a row shorter than 1e-5 "
                        "t_end before the run stops as crawling (0: no limit)", 0)
    try:
        snapshots = [float(s) for s in snaps.split(",") if s]
    except ValueError:
        raise KnitError(f"-knit_snapshots {snaps!r}: expected comma-separated "
                        "times in seconds") from None
    late = [ts for ts in snapshots if ts > t_end]
    short = ""                           # said once the model is built
    if late and len(late) == len(snapshots) and not static:
        short = (f"knitfem run: note: -knit_t_end {t_end:g} ends before the "
                 f"snapshot times ({','.join(f'{ts:g}' for ts in late)} s): "
                 f"the final state is drawn instead")
        snapshots, late = [t_end], []
    if late and PETSc.Options().hasName("knit_snapshots"):
        PETSc.Sys.Print(f"knitfem run: warning: -knit_snapshots "
                        f"{','.join(f'{ts:g}' for ts in late)} after -knit_t_end "
                        f"{t_end:g}: not drawn")
    change = tuple(c for c in change.split(",") if c)
    for c in change:
        if c not in CHANGEABLE:
            raise KnitError(f"-knit_restart_change {c!r}: a restart can change only "
                            + ", ".join(CHANGEABLE))
    adapt_options(opts)
    path = opts.getOutput(f"out/{name}", shown="out/SCENE")
    if opts.finish("knitfem run", RUN_HELP_FOOTER):
        return
    drawn = not static and (movie or any(ts <= t_end for ts in snapshots))
    painter = None
    out = OutputDirectory(comm, path, " ".join(sys.argv)).claim()
    try:                                 # from the claim on, the lock is given back
        if out.note:
            PETSc.Sys.Print(f"knitfem run: {out.note}")
        if drawn and comm.rank == 0:     # its matplotlib import overlaps the set-up
            painter = Painter()
        try:
            fabric = make_fabric(name, jersey, turn, **scene.params)
        except ValueError as err:
            raise KnitError(str(err)) from None
        fabric.bodies = moving_bodies(motion, fabric.bodies + bodies)
        fabric.friction = friction
        friction_fits(fabric, static, PETSc.Options().getString("knit_integrator", ""))
        system = build_system(comm, opts, fabric, material)
        n, k = system.M.getSize()[0], system.C.getSize()[0]
        from knitfem.lod.reduced import sampling_note, threads_note

        PETSc.Sys.Print(f"knitfem run: {name}, {system.kind} model"
                        f"{sampling_note(system)}, {n} coordinates "
                        f"+ {k} constraints (contacts, fixed points) = {n + k} "
                        f"unknowns, {threads_note(system)}{comm.size} rank(s)")
        if static:
            return run_static(comm, system, scene, out, load_steps, StaticSolver)
        with PETSc.Log.Stage("Solver set-up"):
            integrator = make_integrator(system)
            if integrator.name == "symplectic" and not unstable:
                explicit_step_fits(system, integrator.dt)
            adapt = adaptation_from_options(opts, system)
        if short:                        # once nothing can refuse the run
            PETSc.Sys.Print(short)
        lod = getattr(getattr(system, "embedding", None), "volume", None)
        problem = dict(scene.problem(jersey), rho=material.rho, EA=material.EA,
                       EI=material.EI, gravity=material.gravity,
                       damping=material.damping,
                       quadrature=PETSc.Options().getInt("knit_quadrature", 4),
                       lod=[lod.n1, lod.n2] if lod else None)
        if any(turn):
            problem["start_rotation"] = list(turn)
        if jersey.rest is not None:
            problem["rest"] = jersey.rest.source
        if fabric.bodies:
            problem["bodies"] = [b.describe() for b in fabric.bodies]
            problem["friction"] = friction
        if getattr(system, "shell", None) is not None:
            problem["stretch"] = "shell"
        knitted = {"chart": problem["chart"]} if "chart" in problem else {}
        sim = Simulation(system, integrator, out=out, scene=name,
                         output_every=every, snapshots=snapshots, drift_tol=drift,
                         energy_growth=growth, stall_steps=stall,
                         checkpoint_every=ckpt, view=scene.view, problem=problem,
                         command=sys.argv, adapt=adapt, animation=movie,
                         painter=painter, slow_step=slow,
                         report=dict(scene.report(), **knitted),
                         tubes="" if tubes == "none" else tubes)
        if restart:
            sim.restart(restart, change)
        if adapt is not None:
            adapt(sim)                   # the indicator (and regions) at the start
        rec = simulate(sim, t_end, "run", out)
        if isinstance(rec, int):
            return rec
        if adapt is not None:
            adapt.report(sim, out.path)
        for prefix, icntl14 in rec["mumps_workspace_raised"].items():
            PETSc.Sys.Print(f"knitfem run: note: MUMPS ran out of workspace and was "
                            f"given more (-{prefix}mat_mumps_icntl_14 {icntl14} "
                            f"starts there)")
        if rec["linear_failures"]:
            PETSc.Sys.Print(f"knitfem run: note: {rec['linear_failures']} linear solves "
                            f"did not converge and their steps were retried shorter "
                            f"(-{system.kind}_ksp_type / -{system.kind}_pc_type)")
        PETSc.Sys.Print(f"done: {rec['steps']} steps in {rec['wall_time_s']:.2f} s; "
                        f"centroid {np.round(rec['centroid'], 6).tolist()}, lowest "
                        f"point dropped {rec['drop']:.4g} m; summary in "
                        f"{out.path}/summary.json")
    finally:
        if painter is not None:          # finished by the run's close, or set-up failed
            painter.stop()
        out.release()


def simulate(sim, t_end, command, out):
    """``sim.run(t_end)``: its summary, or the exit status of a run that
    failed (3) or was interrupted, after one line saying so."""
    from solvers.integrators import SimulationError

    from knitfem.run.interrupts import Interrupted

    try:
        return sim.run(t_end)
    except SimulationError as err:
        PETSc.Sys.Print(f"knitfem {command}: error: {err} (output so far kept in "
                        f"{out.path})")
        return 3
    except Interrupted as stop:
        if not stop.said:
            PETSc.Sys.Print(f"knitfem {command}: {stop}")
        return stop.code


def friction_fits(fabric, static, integrator):
    """Refuse friction against bodies where it cannot act (KnitError, exit 2).

    Friction is lagged (``knitfem.contact.colliders``): a dissipative
    potential D(ε; ε⁰) whose force is zero at the step's start ε⁰ and grows
    as the step moves the yarn along the body. The symplectic integrator
    evaluates its forces at ε⁰, so it would see none; a static solve is one
    step from a knit not yet touching the body (λ = 0 at ε⁰), so friction
    would never hold it."""
    from knitfem.errors import KnitError

    if not (fabric.friction and fabric.bodies):
        return
    if static:
        raise KnitError(f"-knit_static has no friction against bodies (-knit_friction "
                        f"{fabric.friction:g}): friction is lagged over the steps of "
                        "a motion; use -knit_friction 0 for the frictionless "
                        "equilibrium, or leave out -knit_static to settle the knit "
                        "with friction")
    if integrator == "symplectic":
        raise KnitError(f"-knit_integrator symplectic has no friction against bodies "
                        f"(-knit_friction {fabric.friction:g}): lagged friction acts "
                        "only within an implicit step; use -knit_friction 0, or "
                        "leave out -knit_integrator (its default is implicit)")


def explicit_step_fits(system, dt):
    """Refuse a symplectic step above its stability limit 2/ω_max: the run
    would blow up, so it is a bad option value (KnitError, exit 2)."""
    from solvers.stability import stable_step

    from knitfem.errors import KnitError

    h = stable_step(system)
    if dt > h:
        raise KnitError(f"-knit_dt {dt:g} is above the symplectic integrator's stable "
                        f"step 2/omega_max = {h:.3g} s for this yarn and model: use "
                        f"-knit_dt {float(f'{0.9 * h:.2g}'):g}, or leave out "
                        f"-knit_integrator for the default bdf2 (-knit_unstable_dt "
                        f"runs it anyway)")


def run_static(comm, system, scene, out, load_steps, StaticSolver):
    """Static equilibrium by Newton with pseudo-transient continuation
    (``solvers/statics.py``); writes summary.json, a VTU and a PNG."""
    import time

    from solvers.integrators import SimulationError

    from knitfem.run.simulation import Simulation

    start = time.perf_counter()
    with PETSc.Log.Stage("Static solve"):
        solver = StaticSolver(system, load_steps)
        sim = Simulation(system, solver, out=out, scene=scene.name, verbose=False)
        out.rank0(out.remove_pictures)
        out = out.path
        _, pts0 = sim.geometry()
        if comm.rank == 0:
            sim.initial_lowest = pts0.points[:, 1].min()
        try:
            its = solver.solve(sim.x, monitor=lambda i, load, snes: PETSc.Sys.Print(
                f"load step {i}/{load_steps}  load {load:.2f}  newton "
                f"{snes.getIterationNumber()}  |F| {snes.getFunctionNorm():.3e}"))
        except SimulationError as err:
            PETSc.Sys.Print(f"knitfem run: error: {err}")
            return 3
    sim.wall_time = time.perf_counter() - start
    sim.stats.update(newton=its, ksp=solver.ksp_iterations)
    rec = sim.summary()
    sim.write_summary(rec, "completed")
    P, _ = sim.geometry()
    if comm.rank == 0 and out:
        from knitfem import io

        io.write_centrelines(os.path.join(out, f"{scene.name}_static.vtu"), P,
                             system.fabric.radius)
        io.draw(os.path.join(out, f"{scene.name}_static.png"), P,
                system.fabric.radius,
                title=f"{scene.name}, static equilibrium ({system.kind} model)",
                view=scene.view if system.fabric.bodies else "front",
                bodies=system.fabric.bodies)
    PETSc.Sys.Print(f"static equilibrium in {its} Newton iterations; tip "
                    f"{np.round(rec['tip'], 6).tolist()}, lowest point dropped "
                    f"{rec['drop']:.4g} m")


def fitting_metrics(fabric, P, nq=4):
    """Quality of the stitches fitting for deformed control points P (N, 3).

    max and RMS Green–Lagrange axial strain, the smallest centreline distance
    between different yarns over 2r (penetration when < 1) and the largest
    contact residual max |g| (``constraints.Contacts``) over r.
    """
    from knitfem.contact import constraints as cons
    from knitfem.yarn.elements import YarnElements

    el = YarnElements(fabric.X, fabric.connectivity(0, fabric.nyarn),
                      1.0, 1.0, 0.0, nq=nq)
    e = el.strain(P.reshape(-1, 3))
    dist = min_yarn_distance(fabric.curves(P), 16)[0]
    contacts, _ = cons.build(fabric)
    res = np.abs(contacts.values(P.reshape(-1, 3)[contacts.cols])).max(axis=1)
    return dict(max_strain=float(np.abs(e).max()),
                rms_strain=float(np.sqrt(np.mean(e**2))),
                min_distance_over_2r=float(dist / (2 * fabric.radius)),
                penetration=bool(dist < 2 * fabric.radius),
                max_contact_residual_over_r=float(res.max() / fabric.radius)
                if res.size else 0.0)


def deform(comm):
    """Move the bounding volume's control points; rebuild the yarns through Γ."""
    from knitfem import io
    from knitfem.lod.volume import DEFAULT_AMOUNTS, MODES, BoundingVolume

    opts = KnitOptions()
    jersey = jersey_from_options(opts, 15, 30)
    mode = opts.getChoice("mode", "flexion", MODES, "imposed deformation")
    amount = opts.getReal("amount", DEFAULT_AMOUNTS[mode], "amount: degrees "
                          "(flexion, shear, torsion) or stretch ratio (traction); "
                          "by default " + ", ".join(f"{m} {a:g}" for m, a in
                                                    DEFAULT_AMOUNTS.items()))
    lod = opts.getInts("lod", (5, 5), "bounding-volume control points n1,n2", 2, 4)
    out = opts.getOutput(f"out/deform_{mode}", shown="out/deform_MODE")
    if opts.finish("knitfem deform"):
        return
    output_dir(out)
    if comm.rank:
        return
    fabric = jersey_fabric(jersey)
    volume = BoundingVolume.around(fabric.X, *lod, margin=jersey.radius)
    params = volume.embed(fabric.X)
    try:
        moved = volume.deformed(mode, amount)
    except ValueError as err:
        raise KnitError(f"-knit_mode {mode} -knit_amount {amount:g}: {err}") from None
    cols, vals = moved.weights(*params)
    P = np.einsum("na,nai->ni", vals, moved.flat[cols])
    rec = dict(mode=mode, amount=amount, lod=list(lod), rows=jersey.rows,
               cols=jersey.cols, **fitting_metrics(fabric, P))
    P = fabric.curves(P)
    base = os.path.join(out, f"{mode}")
    io.write_centrelines(base + ".vtu", P, jersey.radius)
    moved.save(base + "_volume.vtu")
    # flexion bends the swatch in x–z and torsion turns it about x: 3-D
    view = "three_quarter" if mode in ("flexion", "torsion") else "front"
    io.draw(base + ".png", P, jersey.radius, view=view,
            title=f"{mode} {amount:g}: max strain {rec['max_strain']:.3f}, "
                  f"min distance {rec['min_distance_over_2r']:.2f} x 2r")
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(rec, f, indent=1)
    PETSc.Sys.Print(json.dumps(rec))
